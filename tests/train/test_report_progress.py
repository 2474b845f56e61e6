"""issue 44: a policy's report (minutes of sampler runs at real size) says how far it is while it runs, as
status lines (``Job.say``: one stderr line each in `prop personalize`), unsealed and sealed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """The tiny ACT of the plugin tests (tests/plugin/tiny.py): its data and the original, no bundle."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature

    from examples import lerobot_reach_task as reach
    from tests.plugin import tiny

    work = tmp_path_factory.mktemp("progress")
    torch.manual_seed(0)
    tiny.record(work / "general", 1, 0, 0.0)
    tiny.record(work / "user", 2, 1, 0.6)
    stats = reach.dataset_stats(work / "general", keys=(tiny.STATE, tiny.IMAGE, tiny.ACTION))
    built = reach.build_act(
        stats, input_features={tiny.STATE: PolicyFeature(FeatureType.STATE, (4,)),
                               tiny.IMAGE: PolicyFeature(FeatureType.VISUAL, (3, tiny.SIZE, tiny.SIZE))},
        output_features={tiny.ACTION: PolicyFeature(FeatureType.ACTION, (4,))}, vision_backbone="resnet18",
    )  # fmt: skip
    reach.train_base(work / "general", work / "act", steps=2, batch=8, built=built)
    return work


@pytest.mark.parametrize("seal", [False, True])
def test_a_policy_report_says_how_many_sampler_runs_are_done(work, tmp_path, seal):
    import numpy as np

    from prop_cli import api
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core.key_files import KeySource
    from tests.plugin.tiny import TINY

    said: list[str] = []
    key = KeySource(np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8), "file")
    cfg = PersonalizeConfig.of(**{**TINY, "steps": 2}, seal=seal)
    general = None if seal else work / "general"  # as the plugin tests personalize it
    out = tmp_path / "b"
    api.personalize_checkpoint(str(work / "act"), [(work / "user", key)], out, cfg, general=general,
                               status=said.append)  # fmt: skip
    report = [s.removeprefix("report of user 1: ") for s in said if s.startswith("report of user 1: ")]
    total = int(re.match(r"(\d+) sampler runs \(", report[0])[1])  # the plan first
    done = [re.match(r"(\d+) of (\d+) sampler runs done \(", s) for s in report[1:]]
    assert done and all(done), report
    counts = [int(m[1]) for m in done]
    assert all(int(m[2]) == total for m in done)
    assert counts == sorted(set(counts)) and 0 < counts[0] and counts[-1] < total, report
    assert any("original's chunks" in s for s in report)
