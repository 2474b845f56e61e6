"""LeRobot policies personalized on several processes (`accelerate launch`, 2 CPU processes on gloo)
train what one process trains (pytest -m lerobot; prop_cli.train.distributed, row_noise).

A tiny ACT (dropout 0.1 and its VAE: it draws inside its loss) for a few steps, unsealed and sealed;
benchmarks/bench_dist_policies.py measures ACT, Diffusion and SmolVLA over 50 steps (docs/speed.md).
Tolerance: 1e-5 on all but a thousandth of the trained weights, 1e-4 on the actions the two bundles
give with the key. Adam's first update is ``lr * g / (|g| + 1e-8)``: a weight whose gradient is at
rounding level (an attention key bias, whose true gradient is 0) moves by up to the learning rate either
way, whichever process count computes it; a split that draws other noise or scales the loss wrongly
moves nearly all of them.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytest.importorskip("accelerate")
pytestmark = pytest.mark.lerobot

from benchmarks.bench_dist_policies import personalize, trained_weights  # noqa: E402
from examples import lerobot_reach_task as task  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.core.key_files import read_key_file  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from prop_cli.run.policy import run_policy  # noqa: E402

TOLERANCE = 1e-5
STEPS = 8


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("dist-act")
    task.record(d / "general", 3, 0, np.zeros(3, np.float32))
    task.record(d / "user", 3, 50_000, task.USER_OFFSET)
    task.train_base(d / "general", d / "act", steps=3)
    key = d / "k.bin"
    key.write_bytes(np.random.default_rng(3).integers(0, 256, 16, dtype=np.uint8).tobytes())
    key.chmod(0o600)
    return d


@pytest.mark.parametrize("seal", [False, True], ids=["unsealed", "sealed"])
def test_two_processes_train_the_policy_one_process_trains(work, seal):
    mode = "sealed" if seal else "unsealed"
    outs, reports = [], []
    for n in (1, 2):
        out = work / f"{mode}-{n}"
        _, report = personalize(n, work / "act", work / "user", work / "k.bin", out, STEPS, seal,
                                work / "general")  # fmt: skip
        outs.append(out)
        reports.append(report)
    assert [r["processes"] for r in reports] == [1, 2]  # one report: the first process writes and prints
    a, b = (trained_weights(o, work / "k.bin") for o in outs)
    assert a.keys() == b.keys() and a
    diffs = np.concatenate([np.abs(a[k].astype(np.float64) - b[k]).ravel() for k in a])
    assert (diffs > TOLERANCE).mean() <= 1e-3, (int((diffs > TOLERANCE).sum()), diffs.size, diffs.max())
    key = read_key_file(work / "k.bin")
    data = load_data(work / "user")
    with torch.no_grad():
        one, two = (run_policy(load_bundle(o), data, key) for o in outs)
    assert np.abs(one - two).max() <= 1e-4
    assert sorted(p.name for p in work.iterdir() if p.name.startswith(mode)) == [f"{mode}-1", f"{mode}-2"]
