"""Issue 42, items 4 and 8: two `prop add-user` started together on one sealed bundle (who enrols, what
the manifest lists, whether every key runs keyed), and how long `prop run --key-file` takes to refuse a
state file nested 100,000 deep or linked to /dev/zero (the whole command, start-up included).

    PYTHONPATH=$PWD python -m benchmarks.bench_concurrent_writers
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tests.conftest import make_mlp_checkpoint

d = Path(tempfile.mkdtemp(prefix="prop-bench-writers-"))
os.environ["PROP_STATE_DIR"] = str(d / "state")
make_mlp_checkpoint(d / "model.safetensors")
rng = np.random.default_rng(0)
x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
np.savez(d / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
np.save(d / "x.npy", x[:8])
for k in ("k", "k2", "k3"):
    (d / f"{k}.bin").write_bytes(os.urandom(16))
    (d / f"{k}.bin").chmod(0o600)
P = [sys.executable, "-m", "prop_cli.cli.main"]
env = {**os.environ, "OMP_NUM_THREADS": "1"}
r = subprocess.run(
    [
        *P,
        "personalize",
        d / "model.safetensors",
        "--data",
        d / "mine.npz",
        "--key-file",
        d / "k.bin",
        "--out",
        d / "b.prop",
        "--steps",
        "40",
        "--device",
        "cpu",
        "--seal",
    ],
    capture_output=True,
    text=True,
    env=env,
)
assert r.returncode == 0, r.stderr
t = time.time()


def start(k: str) -> subprocess.Popen:
    cmd = [*P, "add-user", d / "b.prop", "--data", d / "mine.npz", "--key-file", d / f"{k}.bin",
           "--steps", "20", "--device", "cpu"]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


ps = [start(k) for k in ("k2", "k3")]
for k, p in zip(("k2", "k3"), ps):
    out, err = p.communicate()
    print(k, "exit", p.returncode, err.strip().splitlines()[-1][:160] if err.strip() else "")
print(f"both done in {time.time() - t:.1f} s")
m = json.loads((d / "b.prop" / "manifest.json").read_text())
print("records listed", len(m["records"]), "files", len(list((d / "b.prop" / "users").iterdir())))
for k in ("k", "k2", "k3"):
    r = subprocess.run(
        [
            *P,
            "run",
            d / "b.prop",
            "--input",
            d / "x.npy",
            "--output",
            d / f"y{k}.npy",
            "--key-file",
            d / f"{k}.bin",
            "--json",
        ],
        capture_output=True,
        text=True,
        env=env,
    )
    print(
        k,
        "run exit",
        r.returncode,
        json.loads(r.stdout)["keyed"] if r.returncode == 0 else r.stderr.strip()[:120],
    )
f = d / "state" / "bundles" / f"{m['bundle_id']}.json"
for name, make in (
    ("deep", lambda: f.write_text("[" * 100000 + "]" * 100000)),
    ("/dev/zero link", lambda: os.symlink("/dev/zero", f)),
):
    f.unlink()
    make()
    t = time.time()
    r = subprocess.run(
        [*P, "run", d / "b.prop", "--input", d / "x.npy", "--output", d / "y.npy", "--key-file", d / "k.bin"],
        capture_output=True,
        text=True,
        env=env,
    )
    print(name, "exit", r.returncode, f"{time.time() - t:.2f} s (whole command)", r.stderr.strip()[:140])
