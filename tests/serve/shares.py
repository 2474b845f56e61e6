"""Helpers of the prop serve tests."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import FAST

# openpi-client 0.1.2 calls websockets' sync connect() outside a `with`, which websockets >= 16 deprecates.
OPENPI_CONNECT = pytest.mark.filterwarnings("ignore:connect\\(\\) must be used:DeprecationWarning")


def personalize_here(wd: Path, out: str = "mine.prop", *extra: str) -> None:
    """prop personalize in a subprocess: a module-scoped fixture cannot use the in-process `cli` one."""
    args = ["personalize", wd / "model.safetensors", "--data", wd / "mine.npz", "--key-file", wd / "k.bin",
            "--out", wd / out, *FAST, *extra]  # fmt: skip
    code = "from prop_cli.cli.main import main; main()"
    done = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr


def routed_rounds(connect, keys: dict, obs) -> list[dict]:
    """prop serve-ray's routing, seen by clients: each user in ``keys`` (name: key text) connects
    (``connect(key)``: an openpi client), asks once and reads (replica, held) from the metadata. Settles
    first, bounded at 10 rounds (a new user goes to the replica holding the fewest, and a router learns
    what a replica holds only every 0.1 s, later on a loaded machine, so a user can be sent once to the
    other replica), then returns 3 rounds."""

    def round_() -> dict:
        seen = {}
        for name, key in keys.items():
            client = connect(key)
            client.infer(obs)
            meta = client.get_server_metadata()
            seen[name] = (meta["replica"], meta["held"])
            client._ws.close()
            time.sleep(0.3)  # a replica tells the routers what it holds every 0.1 s
        return seen

    for _ in range(10):
        if all(held for _, held in round_().values()):
            break
    return [round_() for _ in range(3)]


def start_serve_ray(bundle: Path, port: int) -> tuple[subprocess.Popen, str]:
    """`prop serve-ray BUNDLE --json` on the loopback (a local Ray, one replica of 0.5 CPU) in a subprocess,
    and the first line it prints once deployed (Ray starts: tens of seconds on a busy machine)."""
    args = ["serve-ray", bundle, "--port", port, "--num-cpus", "2", "--replicas", "1",
            "--replica-cpus", "0.5", "--json"]  # fmt: skip
    code = "from prop_cli.cli.main import main; main()"
    proc = subprocess.Popen([sys.executable, "-c", code, *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    return proc, proc.stdout.readline()
