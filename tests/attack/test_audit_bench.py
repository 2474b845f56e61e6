"""benchmarks.table's row for the tiny ACT's audit (issue 44): run in LeRobot's environment as a user runs
`prop attack`, or one line saying why it was skipped. A stand-in for that environment's python here."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from benchmarks import table

# Builds nothing and writes a report for `prop attack ... --json PATH`, as the real commands do.
FAKE = """#!/bin/sh
if [ "$1" = "-c" ]; then mkdir -p "$3"; exit 0; fi
while [ "$#" -gt 0 ]; do
  if [ "$1" = "--json" ]; then
    printf '%s' '{"speed": {"wall_seconds": 30.5, "stage_seconds": {"blackbox": 12.0, "latent": 9.5,
      "relaxed": 8.0, "null": 0.0}}, "coverage": {"cut_short": [], "not_tried": []}}' > "$2"; exit 0
  fi
  shift
done
exit 9
"""


def _script(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


def test_the_tiny_act_row_is_the_audits_wall_time_with_its_largest_stages(tmp_path):
    (tmp_path / "bin").mkdir()
    python = _script(tmp_path / "bin" / "python", FAKE)
    row, skip = table.tiny_act_row(tmp_path, python, "")
    assert skip is None
    what, ratio, figures = row
    assert what == "audit wall, tiny ACT (unsealed, default probes)"
    wall = float(figures.split()[0])  # the subprocess's wall time, against the 60 s goal
    assert ratio.endswith("x") and float(ratio[:-1]) == pytest.approx(wall / 60, abs=0.01)
    assert "(the probes 30.5 s; blackbox 12.0 s, latent 9.5 s, relaxed 8.0 s) vs the 60 s goal" in figures


def test_the_row_says_why_it_was_skipped(tmp_path):
    assert table.tiny_act_row(tmp_path, None, "no LeRobot environment") == (
        None, "audit wall, tiny ACT (unsealed, default probes): skipped: no LeRobot environment")  # fmt: skip
    python, why = table.lerobot_python(tmp_path / "nowhere" / "python")
    assert python is None and why == f"--lerobot-python {tmp_path / 'nowhere' / 'python'} does not exist"
    broken = _script(tmp_path / "python", "#!/bin/sh\necho 'No module named lerobot' >&2\nexit 1\n")
    row, skip = table.tiny_act_row(tmp_path, broken, "")
    assert row is None and skip.endswith(f"building the tiny ACT in {broken} failed: No module named lerobot")


def test_the_table_runs_only_the_rows_asked_for(capsys):
    with pytest.raises(SystemExit) as e:
        table.main(["--rows", "audit-wall,nothing"])
    assert e.value.code == 2 and "--rows" in capsys.readouterr().err
