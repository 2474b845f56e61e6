"""--precision bf16 loads a LeRobot policy in its checkpoint's own dtypes (issue 40): a bf16 checkpoint is
never held in fp32, not at the load, not in the steps, not in the report (which runs on the bf16 base
under the steps' autocast); the weights that train are fp32; the bundle's base is the checkpoint's bytes
and its no-key outputs the original's bit for bit. A tiny SmolVLA (its weights rewritten bf16) and a
tiny pi0 (bf16 as lerobot/pi0_base: its vision tower, projector and norms fp32), pytest -m lerobot."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytest.importorskip("num2words")  # SmolVLM's processor needs it (scripts/setup-lerobot.sh installs it)
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from examples import pi_tiny, smolvla_tiny  # noqa: E402
from prop_adapters import CheckpointOptions, load_checkpoint  # noqa: E402
from prop_adapters.weights import load_into, safetensors_dtypes  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from prop_cli.train import policy as unsealed_recipe  # noqa: E402
from prop_cli.train import sealed_policy as sealed_recipe  # noqa: E402
from tests.lerobot_bases import originals, reach_data  # noqa: E402

TINY = dict(steps=2, user_rows=4, null_rows=2, neighbour_keys=1, random_keys=1, samples_per_key=1,
            eval_random_keys=1, null_weight=2.0, base_lr_scale=0.1, report_budget=6)  # fmt: skip
KEEP = CheckpointOptions(keep_dtypes=True)


def key(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, 128).astype(np.uint8)


def to_bf16(path) -> None:
    from safetensors.torch import load_file, save_file

    weights = load_file(str(path))
    save_file(
        {k: v.to(torch.bfloat16) if v.is_floating_point() else v for k, v in weights.items()}, str(path)
    )


@pytest.fixture(scope="module", autouse=True)
def _tiny():
    with pi_tiny.tiny():
        yield


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """The camera task's data; a tiny SmolVLA stored bf16 (``smolvla``) and a tiny pi0 (``pi0``)."""
    d = tmp_path_factory.mktemp("bf16-load")
    reach_data(d, 2, 2, camera=True)
    stats = task.dataset_stats(d / "general")
    built = smolvla_tiny.build_smolvla(smolvla_tiny.build_vlm(d / "vlm"), stats)
    task.train_base(d / "general", d / "smolvla", steps=2, built=built)
    to_bf16(d / "smolvla" / "model.safetensors")
    # pi0 as lerobot/pi0_base holds it (config "dtype": "bfloat16": LeRobot's own bf16 build).
    built = pi_tiny.build_pi("pi0", pi_tiny.build_tokenizer(d / "tok"), stats, dtype="bfloat16")
    task.train_base(d / "general", d / "pi0", steps=1, built=built)
    return d


POLICIES = ["smolvla", "pi0"]


@pytest.mark.parametrize("kind", POLICIES)
def test_keep_dtypes_loads_each_weight_as_the_checkpoint_holds_it_and_fp32_stays_the_default(work, kind):
    folder = work / kind
    held = safetensors_dtypes(folder / "model.safetensors")
    assert torch.bfloat16 in set(held.values())  # a bf16 checkpoint (pi0: some tensors fp32)
    kept = load_checkpoint(folder, KEEP)
    state = kept.module.state_dict()
    assert {k: v.dtype for k, v in state.items() if k in held} == held
    default = load_checkpoint(folder).module.state_dict()
    assert {v.dtype for v in default.values() if v.is_floating_point()} == {torch.float32}
    # The same values: the fp32 load is the bf16 one widened, bit for bit.
    assert state.keys() == default.keys()
    assert all(torch.equal(state[k].float(), default[k].float()) for k in state)


def test_load_into_as_held_takes_the_files_tensors_in_their_dtype(tmp_path):
    from safetensors.torch import save_file

    module = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.LayerNorm(4))
    module[1].register_buffer("flag", torch.zeros(2, dtype=torch.bool))
    weights = {
        "0.weight": torch.randn(4, 3).to(torch.bfloat16), "0.bias": torch.randn(4),
        "1.weight": torch.randn(4).half(), "1.bias": torch.randn(4).double(),
        "1.flag": torch.tensor([True, False]),
    }  # fmt: skip
    save_file(weights, str(tmp_path / "w.safetensors"))
    load_into(module, tmp_path / "w.safetensors", as_held=True)
    state = module.state_dict()
    assert all(state[k].dtype == v.dtype and torch.equal(state[k], v) for k, v in weights.items())
    (tmp_path / "w.safetensors").write_bytes(b"")  # read into memory of its own: the file is not kept
    assert torch.equal(module[0].weight, weights["0.weight"])
    copied = torch.nn.Linear(3, 4)
    save_file({k[2:]: weights[k] for k in ("0.weight", "0.bias")}, str(tmp_path / "l.safetensors"))
    load_into(copied, tmp_path / "l.safetensors")  # the default: copied into the module's fp32
    assert copied.weight.dtype == torch.float32 and torch.equal(copied.weight, weights["0.weight"].float())


def _watch(monkeypatch, seal: bool) -> dict[str, list]:
    """What personalize holds: the loaded module's dtypes right after the load, the trained parameters'
    in the steps, and the original's (with autocast on or off) while the report runs."""
    seen: dict[str, list] = {"load": [], "trained": [], "report": []}
    real_load = api._load

    def load(path, opts):
        loaded = real_load(path, opts)
        seen["load"].append({n: p.dtype for n, p in loaded.module.state_dict().items()})
        return loaded

    monkeypatch.setattr(api, "_load", load)

    def dtypes(module):
        return {p.dtype for p in module.parameters() if p.is_floating_point()}

    if seal:
        real_chunks = sealed_recipe.chunks

        def chunks(policy, *a, **k):
            seen["report"].append((dtypes(policy.policy), torch.is_autocast_enabled("cpu")))
            return real_chunks(policy, *a, **k)

        monkeypatch.setattr(sealed_recipe, "chunks", chunks)
    else:
        real_report, real_trainer = unsealed_recipe.chunk_report, unsealed_recipe.PolicyTrainer

        def report(km, policy, original, *a, **k):
            seen["report"].append((dtypes(original.policy), torch.is_autocast_enabled("cpu")))
            return real_report(km, policy, original, *a, **k)

        class Trainer(real_trainer):
            def __init__(self, *a, **k):
                super().__init__(*a, **k)
                seen["trained"].append({p.dtype for p in self.module.parameters() if p.requires_grad})

        monkeypatch.setattr(unsealed_recipe, "chunk_report", report)
        monkeypatch.setattr(unsealed_recipe, "PolicyTrainer", Trainer)
    return seen


@pytest.mark.parametrize("seal", [True, False], ids=["sealed", "unsealed"])
@pytest.mark.parametrize("kind", POLICIES)
def test_bf16_personalize_holds_the_checkpoints_dtypes_from_load_to_report(
    work, tmp_path, monkeypatch, kind, seal
):
    from safetensors.torch import load_file

    from prop_cli.run.policy import run_policy

    folder = work / kind
    held = safetensors_dtypes(folder / "model.safetensors")
    seen = _watch(monkeypatch, seal)
    out = tmp_path / "b.prop"
    # Unsealed: the policy's own trained parts train (SmolVLA: its expert; pi0: every weight), so
    # trained weights the checkpoint holds bf16 are made fp32.
    cfg = PersonalizeConfig.of(**(TINY | {"seal": seal, "precision": "bf16"}))
    result = api.personalize_checkpoint(str(folder), [(work / "user", KeySource(key(), "file"))], out, cfg)
    assert np.isfinite(result.metrics[0]["personalization"])
    loaded = seen["load"][0]
    assert {k: v for k, v in loaded.items() if k in held} == held  # not one bf16 weight widened at the load
    if not seal:
        assert seen["trained"] == [{torch.float32}]  # the trained weights (Adam's master copy) fp32
    # The report on the base held bf16, under autocast (every run of the original's chunks).
    assert seen["report"] and all(torch.bfloat16 in d and amp for d, amp in seen["report"])
    original = load_file(str(folder / "model.safetensors"))
    written = load_file(str(out / "lerobot" / "model.safetensors"))
    assert written.keys() == original.keys()
    assert all(written[k].dtype == original[k].dtype for k in written)
    if seal:  # the sealed base is the checkpoint's tensors; unsealed, the trained ones changed
        assert all(torch.equal(written[k], original[k]) for k in written)
        data = load_data(work / "user")
        assert np.array_equal(run_policy(load_bundle(out), data, None), originals(folder, data))


def test_unsealed_bf16_with_a_frozen_base_keeps_the_base_bytes_and_the_no_key_outputs(work, tmp_path):
    from safetensors.torch import load_file

    from prop_cli.run.policy import run_policy

    folder, out = work / "smolvla", tmp_path / "b.prop"
    cfg = PersonalizeConfig.of(**(TINY | {"precision": "bf16", "freeze_base": True}))
    api.personalize_checkpoint(str(folder), [(work / "user", KeySource(key(), "file"))], out, cfg,
                               general=work / "general")  # fmt: skip
    original = load_file(str(folder / "model.safetensors"))
    written = load_file(str(out / "lerobot" / "model.safetensors"))
    assert written.keys() == original.keys()
    assert all(
        written[k].dtype == original[k].dtype and torch.equal(written[k], original[k]) for k in written
    )
    data = load_data(work / "user")
    b = load_bundle(out)
    expected = originals(folder, data)
    assert np.array_equal(run_policy(b, data, None), expected)
    assert not np.allclose(run_policy(b, data, key()), expected, atol=1e-4)  # the key still personalizes
