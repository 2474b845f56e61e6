"""--precision bf16 on array models (issue 40): the frozen base's matrices held bf16 while the steps
run (--freeze-base unsealed; the base of a sealed run), put back exactly after them; the bundle's base in
the checkpoint's own dtype; fp32 the default, nothing cast."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from prop_cli import constants as C
from prop_cli.train import array, sealed_array
from prop_cli.train.frozen import frozen_in_bf16
from tests.train.test_precision import personalize, run_bundle


def watch(monkeypatch, recipe) -> list[set[torch.dtype]]:
    """The frozen matrices' dtypes right after the recipe casts them (i.e. while its steps run)."""
    seen: list[set[torch.dtype]] = []
    real = recipe.frozen_in_bf16

    def watched(module, loaded, *a):
        restore = real(module, loaded, *a)
        seen.append({p.dtype for p in module.parameters() if not p.requires_grad and p.dim() >= 2})
        return restore

    monkeypatch.setattr(recipe, "frozen_in_bf16", watched)
    return seen


@pytest.mark.parametrize("stored", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("seal", [False, True])
def test_frozen_base_is_bf16_during_the_steps_and_the_bundle_keeps_the_checkpoints_dtype(
    cli, workdir, monkeypatch, seal, stored
):
    wd = workdir
    ckpt = load_file(wd / "model.safetensors")
    save_file(
        {k: v.to(stored) for k, v in ckpt.items()}, str(wd / "model.safetensors"), {"activation": "relu"}
    )
    seen = watch(monkeypatch, sealed_array if seal else array)
    extra = ["--seal"] if seal else ["--freeze-base"]
    report = personalize(cli, wd, "--precision", "bf16", *extra)
    assert seen and all(s == {torch.bfloat16} for s in seen)
    bundle = wd / "mine.prop"
    base = load_file(bundle / C.BASE_WEIGHTS)
    original = load_file(wd / "model.safetensors")
    # The base is the checkpoint's own tensors, in its dtype: put back exactly after the steps.
    assert all(base[k].dtype == stored and torch.equal(base[k], original[k]) for k in original)
    assert report["metrics"][0]["personalization"] > 0.5  # the user key still personalizes
    y, y0 = run_bundle(cli, wd, bundle, "--key-file", str(wd / "k.bin")), run_bundle(cli, wd, bundle)
    x = torch.from_numpy(np.load(wd / "x.npy"))
    w = {k: v.float() for k, v in original.items()}
    expected = torch.relu(torch.relu(x @ w["0.weight"].T + w["0.bias"]) @ w["2.weight"].T + w["2.bias"])
    expected = expected @ w["4.weight"].T + w["4.bias"]
    np.testing.assert_allclose(y0, expected.numpy(), rtol=1e-5, atol=1e-6)  # no key: the original
    assert not np.allclose(y, y0, atol=1e-3)


def test_fp32_casts_nothing(cli, workdir, monkeypatch):
    seen = watch(monkeypatch, array)
    personalize(cli, workdir, "--freeze-base")
    assert seen == []
    assert {v.dtype for v in load_file(workdir / "mine.prop" / C.BASE_WEIGHTS).values()} == {torch.float32}


def test_what_cannot_be_put_back_exactly_is_not_cast(tmp_path):
    from prop_adapters import load_checkpoint
    from tests.conftest import make_mlp_checkpoint

    path = make_mlp_checkpoint(tmp_path / "m.safetensors")
    loaded = load_checkpoint(str(path))
    module = loaded.module.requires_grad_(False)
    before = {k: v.clone() for k, v in module.state_dict().items()}
    restore = frozen_in_bf16(module, loaded, matrices_only=True)
    assert {p.dtype for p in module.parameters() if p.dim() >= 2} == {torch.bfloat16}
    assert {p.dtype for p in module.parameters() if p.dim() == 1} == {torch.float32}
    restore()
    assert all(torch.equal(before[k], v) and v.dtype == torch.float32 for k, v in module.state_dict().items())
    loaded.source = str(tmp_path / "gone.safetensors")  # fp32 and its file gone: no exact way back
    assert frozen_in_bf16(module, loaded) is None
    assert {p.dtype for p in module.parameters()} == {torch.float32}
