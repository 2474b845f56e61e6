"""prop serve from the command line: refusals in one line, and a real process serving until SIGTERM."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from prop_cli.core.key_files import key_text
from tests.cli.shares import assert_clean_error
from tests.serve.shares import OPENPI_CONNECT

client_policy = pytest.importorskip("openpi_client.websocket_client_policy")
pytestmark = OPENPI_CONNECT


@pytest.mark.parametrize(
    "flags, words",
    [
        (["--host", "0.0.0.0"], ["--host 0.0.0.0", "--tls-cert"]),
        (["--host", "192.168.1.5", "--tls-cert", "c.pem"], ["--tls-cert and --tls-key go together"]),
        (["--tls-cert", "missing.pem", "--tls-key", "missing.key"], ["--tls-cert missing.pem is not a file"]),
        (["--max-connections", "0"], ["--max-connections"]),
        (["--batch-window-ms", "5000"], ["--batch-window-ms 5000", "0 to 1000"]),
        (["--max-batch", "0"], ["--max-batch"]),
    ],
)
def test_refusals_are_one_line(cli, served_bundle, flags, words):
    res = cli("serve", served_bundle / "mine.prop", *flags)
    assert_clean_error(res, *words)


@contextlib.contextmanager
def serving(bundle, *flags: str):
    """``prop serve BUNDLE --port 0 --json *flags`` in a process: (the process, its url); killed at the
    end if it still runs."""
    code = "from prop_cli.cli.main import main; main()"
    args = [sys.executable, "-c", code, "serve", str(bundle), "--port", "0", "--json", *flags]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # the address comes first, on stdout
        url = json.loads(line)["url"] if line.startswith("{") else line
        assert url.startswith("ws://127.0.0.1:"), (url, proc.stderr.read() if proc.poll() is not None else "")
        yield proc, url
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_a_served_process_answers_openpi_client_and_stops_on_sigterm(served_bundle):
    with serving(served_bundle / "mine.prop") as (proc, url):
        text = key_text(served_bundle / "k.bin")
        client = client_policy.WebsocketClientPolicy(host=url, api_key=text)
        actions = client.infer({"observation": np.zeros(4, np.float32)})["actions"]
        assert actions.shape == (2,)
        client._ws.close()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert json.loads(out) == {"connections": 1}
    assert "connected (keyed)" in err and "stopped after 1 connection" in err and "Traceback" not in err
    key_bytes = (served_bundle / "k.bin").read_bytes()
    assert text not in err + out and text.upper() not in err + out and key_bytes.hex() not in err + out


def test_sigterm_drains_the_requests_waiting_in_a_batch(served_bundle):
    """A request waiting in its batch window when SIGTERM comes is answered; then the process exits 0."""
    with serving(served_bundle / "mine.prop", "--batch-window-ms", "800") as (proc, url):
        client = client_policy.WebsocketClientPolicy(host=url, api_key=key_text(served_bundle / "k.bin"))
        x = {"observation": np.zeros(4, np.float32)}
        want = client.infer(x)["actions"]  # the first: its window passes alone
        with cf.ThreadPoolExecutor(1) as pool:
            job = pool.submit(client.infer, x)
            time.sleep(0.3)  # the request is in its window (800 ms)
            proc.send_signal(signal.SIGTERM)
            np.testing.assert_array_equal(job.result(timeout=30)["actions"], want)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "drained" in err and "Traceback" not in err
