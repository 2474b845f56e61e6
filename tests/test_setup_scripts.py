"""The set-up scripts talk: scripts/common.sh's pip_install streams pip's lines (less the expected noise)
while pip runs, still fails on a failed install and retries network errors; `timed` prints the total. pip
is a fake here (a small script given as pip_install's PIP): no network, no install."""

from __future__ import annotations

import os
import queue
import re
import subprocess
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"

# What the fake pip says in every mode besides its own lines: messages pip_install must drop.
NOISE = [
    "WARNING: Location 'file:///opt/pypi/simple/numpy/' is ignored: it is neither a file nor a directory.",
    "Requirement already satisfied: numpy>=1.24 in ./.venv/lib/python3.11/site-packages (2.4.6)",
    "Collecting safetensors>=0.4",
    "  Downloading safetensors-0.8.0-py3-none-any.whl (12 kB)",
    "  Downloading pip-26.3-py3-none-any.whl (2.0 MB)",
]


def fake_pip(tmp_path: Path, body: str) -> Path:
    """A pip that counts its calls (tmp_path/calls), records its arguments and then runs `body`."""
    pip = tmp_path / "pip"
    noise = "\n".join(f"echo {line!r}" for line in NOISE)
    pip.write_text(
        "#!/usr/bin/env bash\n"
        f'calls=$(( $(cat {tmp_path}/calls 2>/dev/null || echo 0) + 1 )); echo "$calls" > {tmp_path}/calls\n'
        f'echo "$*" > {tmp_path}/args\n'
        f"{noise}\n{body}\n"
    )
    pip.chmod(0o755)
    return pip


def run_bash(script: str, tmp_path: Path, **env: str) -> subprocess.Popen:
    return subprocess.Popen(
        ["bash", "-c", f"set -euo pipefail\n. scripts/common.sh\n{script}"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PIP_RETRY_DELAY": "0", **env},
    )


def calls(tmp_path: Path) -> int:
    return int((tmp_path / "calls").read_text())


def test_pip_lines_reach_stderr_while_pip_runs_less_the_expected_noise(tmp_path: Path) -> None:
    # The fake pip announces a download, then waits until the test has seen that line on stderr: output
    # held until pip exits would make it give up (exit 3) instead of finishing.
    go = tmp_path / "go"
    pip = fake_pip(
        tmp_path,
        f"""echo '  Downloading torch-2.13.0-cp311-cp311-manylinux_2_28_x86_64.whl (191.8 MB)'
for _ in $(seq 300); do [ -e {go} ] && break; sleep 0.1; done
[ -e {go} ] || {{ echo 'nobody saw the download line' >&2; exit 3; }}
echo 'Installing collected packages: torch'
echo 'Successfully installed torch-2.13.0'""",
    )
    proc = run_bash(f'pip_install {pip} "torch==2.13.0"', tmp_path)
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stderr], daemon=True)
    reader.start()
    seen = []
    while not any("Downloading torch" in line for line in seen):
        seen.append(lines.get(timeout=30))  # queue.Empty here: the line was held back
    go.touch()
    assert proc.wait(timeout=30) == 0
    reader.join(timeout=10)
    while not lines.empty():
        seen.append(lines.get())
    err = "".join(seen)
    assert "Successfully installed torch-2.13.0" in err and "Installing collected packages: torch" in err
    for line in NOISE:
        assert line.strip() not in err
    assert (tmp_path / "args").read_text().split()[0] == "install"
    assert "torch==2.13.0" in (tmp_path / "args").read_text()


def test_a_failed_install_fails_at_once_with_pips_message(tmp_path: Path) -> None:
    pip = fake_pip(tmp_path, "echo 'ERROR: No matching distribution found for nope' >&2; exit 1")
    proc = run_bash(f"pip_install {pip} nope\necho after", tmp_path)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert "after" not in out
    assert "ERROR: No matching distribution found for nope" in err
    assert calls(tmp_path) == 1  # not retried: not a network error


def test_a_network_error_is_retried(tmp_path: Path) -> None:
    pip = fake_pip(
        tmp_path,
        f"""if [ "$(cat {tmp_path}/calls)" -lt 3 ]; then
  echo 'ERROR: Exception: ... ProtocolError: Connection reset by peer' >&2; exit 2
fi
echo 'Successfully installed torch-2.13.0'""",
    )
    proc = run_bash(f"pip_install {pip} torch\necho after", tmp_path)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.strip() == "after"
    assert calls(tmp_path) == 3
    assert "pip_install: network error (attempt 1 of 3)" in err
    assert "pip_install: network error (attempt 2 of 3)" in err


def test_a_network_error_that_persists_fails_after_three_attempts(tmp_path: Path) -> None:
    pip = fake_pip(tmp_path, "echo 'Read timed out.' >&2; exit 2")
    proc = run_bash(f"pip_install {pip} torch\necho after", tmp_path)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert "after" not in out
    assert calls(tmp_path) == 3


@pytest.mark.parametrize(
    ("body", "rc", "said"),
    [("true", 0, "done in"), ("false", 1, "failed after"), ("exit 3", 3, "failed after")],
)
def test_timed_says_the_total_and_keeps_the_exit_status(
    tmp_path: Path, body: str, rc: int, said: str
) -> None:
    proc = run_bash(f"timed setup\n{body}", tmp_path)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == rc
    assert re.fullmatch(rf"setup: {said} \d+ s\n", err), err


def installing_scripts() -> list[str]:
    """The scripts that run pip_install (common.sh defines it)."""
    return sorted(
        p.name
        for p in SCRIPTS.glob("*.sh")
        if any(line.strip().startswith("pip_install ") for line in p.read_text().splitlines())
    )


def test_the_set_up_scripts_install_through_pip_install() -> None:
    assert installing_scripts() == ["setup-lerobot.sh", "setup-ray.sh", "setup.sh"]


@pytest.mark.parametrize(
    "script",
    ["demo.sh", "setup.sh", "setup-lerobot.sh", "setup-ray.sh", "test.sh", "test-lerobot.sh", "test-ray.sh"],
)
def test_each_set_up_script_says_its_total(script: str) -> None:
    lines = [line.strip() for line in (SCRIPTS / script).read_text().splitlines()]
    name = script.removesuffix(".sh")
    assert f"timed {name}" in lines, f"scripts/{script}: no `timed {name}` (the total at the end)"


@pytest.mark.parametrize("script", installing_scripts())
def test_each_install_is_said_before_it_starts(script: str) -> None:
    lines = [line.strip() for line in (SCRIPTS / script).read_text().splitlines()]
    for i, line in enumerate(lines):
        if not line.startswith("pip_install "):
            continue
        before = [x for x in lines[:i] if x and not x.startswith("#")]
        # The step's own line, or an if/else whose branches each say it.
        assert before[-1].startswith(("say ", "fi")), f"scripts/{script}: nothing said before `{line}`"
