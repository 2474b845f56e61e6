"""LeRobot's own chatter stays out of prop's output (issue 41, the newcomer list): from_pretrained prints
"Loading weights from local directory" on stdout at every local load; prop shows it with PROP_DEBUG only,
and then on stderr (stdout holds results)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402

CHATTER = "Loading weights from local directory"


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("quiet")
    task.record(d / "data", 2, 0, np.zeros(3, np.float32))
    task.train_base(d / "data", d / "act", steps=2)
    (d / "k.bin").write_bytes(bytes(range(16)))
    (d / "k.bin").chmod(0o600)
    return d


def test_loading_a_policy_folder_prints_no_lerobot_line(work, cli, monkeypatch):
    monkeypatch.delenv("PROP_DEBUG", raising=False)
    r = cli("inspect", work / "act")
    assert r.code == 0 and "lerobot adapter" in r.out, r.err
    assert CHATTER not in r.out and CHATTER not in r.err
    r = cli("personalize", work / "act", "--data", work / "data", "--key-file", work / "k.bin", "--out",
            work / "b.prop", "--steps", "2", "--report-budget", "4", "--json")  # fmt: skip
    assert r.code == 0, r.err
    assert CHATTER not in r.out and CHATTER not in r.err and r.out.startswith("{")
    r = cli("run", work / "b.prop", "--input", work / "data", "--key-file", work / "k.bin", "--output",
            work / "y.npy")  # fmt: skip
    assert r.code == 0 and CHATTER not in r.out + r.err, r.err


def test_prop_debug_shows_it_on_stderr(work, cli, monkeypatch):
    monkeypatch.setenv("PROP_DEBUG", "1")
    r = cli("inspect", work / "act", "--json")
    assert r.code == 0 and CHATTER in r.err and CHATTER not in r.out, r.err
