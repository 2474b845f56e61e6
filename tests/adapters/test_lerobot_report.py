"""A sealed LeRobot policy's report within --report-budget (issue 44; pytest -m lerobot, .venv-lerobot)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from tests.adapters.test_lerobot_quiet import work  # noqa: E402, F401 - a tiny ACT and its data


def test_a_sealed_policy_report_honours_report_budget_and_says_its_coverage(work, cli):  # noqa: F811
    """issue 44: the sealed report ran every held-out frame whatever --report-budget said (740 s after 3
    steps of a real-size SmolVLA); now it keeps what the budget holds and prints what it covered."""
    r = cli("personalize", work / "act", "--data", work / "data", "--key-file", work / "k.bin", "--out",
            work / "s.prop", "--seal", "--steps", "2", "--report-budget", "4", "--json")  # fmt: skip
    assert r.code == 0, r.err
    (m,) = json.loads(r.out)["metrics"]
    ran, of = m["coverage"]["ran"]["frames"], m["coverage"]["of"]["frames"]
    assert ran == 2 < of and m["coverage"]["budget"] == 4 and m["samples"] == ran
    assert f"report covers {ran} of {of} held-out frames (--report-budget 4" in r.err
    r = cli("personalize", work / "act", "--data", work / "data", "--key-file", work / "k.bin", "--out",
            work / "s0.prop", "--seal", "--steps", "2", "--report-budget", "0", "--json")  # fmt: skip
    assert r.code == 0, r.err
    (m,) = json.loads(r.out)["metrics"]
    assert "coverage" not in m and m["samples"] == of and "report covers" not in r.err
