"""--precision bf16: autocast mixed precision in the shared step loop, on the CPU (CI has no GPU;
scripts/gpu-smoke.sh runs the same on CUDA)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from prop_cli import constants as C
from prop_cli.errors import PropError
from prop_cli.train import loop
from tests.conftest import FAST


def personalize(cli, wd, *extra: str, out: str = "mine.prop"):
    res = cli(
        "personalize", wd / "model.safetensors", "--data", wd / "mine.npz", "--key-file", wd / "k.bin",
        "--out", wd / out, "--json", *FAST, *extra,
    )  # fmt: skip
    assert res.code == 0, res.err
    return json.loads(res.out)


def run_bundle(cli, wd, bundle, *key: str) -> np.ndarray:
    y = wd / f"y{len(key)}.npy"
    res = cli("run", bundle, "--input", wd / "x.npy", "--output", y, *key)
    assert res.code == 0, res.err
    return np.load(y)


@pytest.mark.parametrize("seal", [False, True])
def test_bf16_personalize_runs_and_records_precision(cli, workdir, seal):
    wd = workdir
    # A half-precision checkpoint: the bundle must keep fp16, whatever the step computed in.
    ckpt = load_file(wd / "model.safetensors")
    save_file({k: v.half() for k, v in ckpt.items()}, str(wd / "model.safetensors"), {"activation": "relu"})
    extra = ["--seal"] if seal else []
    report = personalize(cli, wd, "--precision", "bf16", *extra)
    bundle = wd / "mine.prop"
    manifest = json.loads((bundle / C.MANIFEST).read_text())
    assert manifest[C.M_CONFIG]["precision"] == "bf16"
    assert {v.dtype for v in load_file(bundle / C.BASE_WEIGHTS).values()} == {torch.float16}
    assert report["metrics"][0]["personalization"] > 0.5
    y, y0 = run_bundle(cli, wd, bundle, "--key-file", str(wd / "k.bin")), run_bundle(cli, wd, bundle)
    assert y.shape == y0.shape == (8, 2)
    assert not np.allclose(y, y0, atol=1e-3)  # the key changes the behaviour, as with fp32


def test_bf16_trains_in_bf16_and_fp32_is_the_default(cli, workdir):
    fp32 = personalize(cli, workdir, out="a.prop")
    bf16 = personalize(cli, workdir, "--precision", "bf16", out="b.prop")
    assert json.loads((workdir / "a.prop" / C.MANIFEST).read_text())[C.M_CONFIG]["precision"] == "fp32"
    # Same seed and data: only the forward's precision differs, so the losses must too.
    assert fp32["final_losses"] != bf16["final_losses"]


def test_bad_precision_is_one_line(cli, workdir):
    res = cli(
        "personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
        workdir / "k.bin", "--out", workdir / "o.prop", *FAST, "--precision", "fp16",
    )  # fmt: skip
    assert res.code == 2, res.err
    lines = [ln for ln in res.err.strip().splitlines() if ln.startswith("prop: error:")]
    assert len(lines) == 1 and "Traceback" not in res.err, res.err
    assert "--precision 'fp16'" in lines[0] and "fp32 or bf16" in lines[0]
    assert not (workdir / "o.prop").exists()


@pytest.mark.parametrize("precision, dtype", [("fp32", torch.float32), ("bf16", torch.bfloat16)])
def test_step_loop_autocasts_forward_but_keeps_fp32_state(precision, dtype):
    torch.manual_seed(0)
    layer = torch.nn.Linear(8, 8)
    optim = loop.Optimiser(list(layer.parameters()), 1e-2, 3, 0.5, clip=1.0)
    x, seen = torch.randn(16, 8), []

    def step() -> dict[str, float]:
        out = layer(x)
        seen.append(out.dtype)
        loss = (out.float() ** 2).mean()
        optim.update(loss)
        return {"loss": loss.item()}

    loop.run_steps(step, 3, None, precision, "cpu")
    assert seen == [dtype] * 3
    assert layer(x).dtype == torch.float32  # the autocast ends with the loop
    assert {p.dtype for p in layer.parameters()} == {torch.float32}
    assert {p.grad.dtype for p in layer.parameters()} == {torch.float32}
    assert {m.dtype for g in optim.adam.groups for m in g["m"] + g["v"]} == {torch.float32}


def test_bf16_refused_on_a_gpu_without_bf16(monkeypatch):
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda dev=None: (7, 5))
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda dev=None: "Tesla T4")
    monkeypatch.setattr(torch.version, "hip", None)
    with pytest.raises(PropError, match=r"--precision bf16: Tesla T4 .*--precision fp32"):
        loop.mixed_precision("bf16", "cuda")
