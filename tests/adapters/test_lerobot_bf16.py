"""--precision bf16 on LeRobot policies (issue 40): the frozen base held bf16 during the steps, the
bundle's base in the checkpoint's own dtype (a bf16 checkpoint gives a bf16 base, not an fp32 one of
twice its size), its no-key outputs the original's bit for bit. A tiny ACT (pytest -m lerobot)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from prop_cli.train import policy as unsealed_recipe  # noqa: E402
from prop_cli.train import sealed_policy as sealed_recipe  # noqa: E402
from tests.lerobot_bases import originals  # noqa: E402

TINY = dict(steps=6, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=2, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip


def key(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A tiny ACT trained fp32, and the same folder with its weights stored bf16."""
    from safetensors.torch import load_file, save_file

    d = tmp_path_factory.mktemp("lerobot-bf16")
    task.record(d / "general", 3, 0, np.zeros(3, np.float32))
    task.record(d / "user", 2, 50_000, task.USER_OFFSET)
    task.train_base(d / "general", d / "act", steps=3)
    shutil.copytree(d / "act", d / "act16")
    weights = load_file(str(d / "act" / "model.safetensors"))
    half = {k: v.to(torch.bfloat16) if v.is_floating_point() else v for k, v in weights.items()}
    save_file(half, str(d / "act16" / "model.safetensors"))
    return d


def _watch(monkeypatch, recipe) -> list[set[torch.dtype]]:
    """The frozen parameters' dtypes right after the recipe casts them (i.e. while its steps run)."""
    seen: list[set[torch.dtype]] = []
    real = recipe.frozen_in_bf16

    def watched(module, loaded, *a):
        restore = real(module, loaded, *a)
        seen.append({p.dtype for p in module.parameters() if not p.requires_grad and p.is_floating_point()})
        return restore

    monkeypatch.setattr(recipe, "frozen_in_bf16", watched)
    return seen


@pytest.mark.parametrize("seal", [True, False], ids=["sealed", "unsealed"])
def test_a_bf16_checkpoint_trains_on_a_bf16_base_and_gives_a_bf16_bundle_base(
    work, tmp_path, monkeypatch, seal
):
    from safetensors.torch import load_file

    from prop_cli.run.policy import run_policy

    seen = _watch(monkeypatch, sealed_recipe if seal else unsealed_recipe)
    out = tmp_path / "b.prop"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": seal, "precision": "bf16", "freeze_base": not seal}))
    general = None if seal else work / "general"  # --seal takes no general data
    result = api.personalize_checkpoint(
        str(work / "act16"), [(work / "user", KeySource(key(), "file"))], out, cfg, general=general
    )
    assert np.isfinite(result.metrics[0]["personalization"])
    assert seen == [{torch.bfloat16}]  # every frozen parameter bf16 during the steps
    original = load_file(str(work / "act16" / "model.safetensors"))
    written = load_file(str(out / "lerobot" / "model.safetensors"))
    assert written.keys() == original.keys()
    assert all(
        written[k].dtype == original[k].dtype and torch.equal(written[k], original[k]) for k in written
    )
    ratio = (out / "lerobot" / "model.safetensors").stat().st_size / (
        work / "act" / "model.safetensors"
    ).stat().st_size
    assert ratio < 0.55  # half the fp32 checkpoint's bytes, not the same
    data = load_data(work / "user")
    b = load_bundle(out)
    assert all(p.dtype == torch.float32 for p in b.loaded.module.parameters())  # loads as before: fp32
    expected = originals(work / "act16", data)
    assert np.array_equal(run_policy(b, data, None), expected)
    assert not np.allclose(run_policy(b, data, key()), expected, atol=1e-4)  # the key still personalizes


def test_fp32_stays_the_default_and_an_fp32_checkpoint_an_fp32_base(work, tmp_path, monkeypatch):
    from safetensors.torch import load_file

    seen = _watch(monkeypatch, unsealed_recipe)
    out = tmp_path / "b.prop"
    cfg = PersonalizeConfig.of(**(TINY | {"freeze_base": True}))
    api.personalize_checkpoint(str(work / "act"), [(work / "user", KeySource(key(), "file"))], out, cfg)
    assert seen == [] and cfg.train.precision == "fp32"
    written = load_file(str(out / "lerobot" / "model.safetensors"))
    assert {v.dtype for v in written.values() if v.is_floating_point()} == {torch.float32}
