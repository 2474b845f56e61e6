"""Keyed convolutions: Eq. 5 as one delta per input channel, in hooks, folds, payloads and layer matching."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.core.layers import describe_layer, in_width, select_layers
from prop_cli.core.payload import Payload, PayloadSpec


class ConvNet(nn.Module):
    """Conv2d (zero padding), a grouped Conv2d (reflect padding), a Conv1d over rows, a linear head."""

    def __init__(self) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(3, 8, 3, padding=1)
        self.c2 = nn.Conv2d(8, 6, 3, padding=1, groups=2, padding_mode="reflect")
        self.c3 = nn.Conv1d(6, 4, 3, padding=1)
        self.head = nn.Linear(4 * 25, 5)

    def forward(self, x):
        h = torch.relu(self.c2(torch.relu(self.c1(x))))  # (B, 6, 5, 5)
        h = torch.relu(self.c3(h.flatten(2)))  # (B, 4, 25)
        return self.head(h.flatten(1))


CONVS = ["c1", "c2", "c3"]


def _net() -> ConvNet:
    torch.manual_seed(0)
    return ConvNet().eval()


def _keyed(module: nn.Module, names: list[str]) -> KeyedModel:
    mods = dict(module.named_modules())
    enc = KeyEncoder(32, [in_width(mods[n]) for n in names], [16], 2.0)
    torch.manual_seed(1)
    nn.init.normal_(enc.net[-1].weight, std=0.5)
    return KeyedModel(module, enc, names).eval()


def _codes(k: int) -> torch.Tensor:
    return key_codes(np.random.default_rng(0).integers(0, 2, (k, 32), dtype=np.uint8), "hashed")


def _by_hand(module: nn.Module, names: list[str], deltas: list[torch.Tensor], x: torch.Tensor):
    """Eq. 5 for convolutions written out: each key's input channels scaled before the layer."""
    outs = []
    for k in range(deltas[0].shape[0]):
        m = copy.deepcopy(module)
        mods = dict(m.named_modules())
        for name, d in zip(names, deltas):
            shape = (1, -1) if isinstance(mods[name], nn.Linear) else None

            def pre(mod, args, d=d[k], shape=shape):
                z = args[0]
                return (z * (d.view(*shape) if shape else d.view(1, -1, *([1] * (z.dim() - 2)))),)

            mods[name].register_forward_pre_hook(pre)
        outs.append(m(x))
    return torch.stack(outs)


def test_hooks_folds_and_every_path_compute_eq5_per_input_channel():
    module = _net()
    names = [*CONVS, "head"]
    km = _keyed(module, names)
    x, codes = torch.randn(4, 3, 5, 5), _codes(3)
    with torch.no_grad():
        deltas = km.layer_deltas(codes)
        ref = _by_hand(module, names, deltas, x)
        grid = km.run_keys(x, deltas)
        rows = km.run_rows(x, deltas, torch.arange(3).repeat_interleave(4), torch.arange(4).repeat(3))
        called = km.call_rows([d.repeat_interleave(4, 0) for d in deltas], module, x.repeat(3, 1, 1, 1))
        folded = torch.stack([km.fold(codes[i : i + 1])(x) for i in range(3)])
    assert km.share_prefix is True  # rows stay independent through convolutions
    for got in (grid, rows.view(3, 4, -1), called.view(3, 4, -1), folded):
        assert torch.allclose(got, ref, atol=1e-5)
    assert not torch.allclose(ref[0], module(x), atol=1e-3)  # the key does something
    assert torch.equal(km(x), module(x))  # no key: the module


@pytest.mark.parametrize("kind", ["delta", "lora", "full"])
def test_conv_payloads_attach_and_fold_alike(kind):
    module = _net()
    mods = dict(module.named_modules())
    layers = [describe_layer(n, mods[n]) for n in [*CONVS, "head"]]
    spec = PayloadSpec(kind, layers, 2 if kind == "lora" else 0)
    p = Payload(spec, torch.Generator().manual_seed(0))
    with torch.no_grad():
        for t in p.parameters():
            t.add_(0.1 * torch.randn_like(t))
    x = torch.randn(3, 3, 5, 5)
    with torch.no_grad(), p.attached(module):
        attached = module(x)
    assert list(module.state_dict()) == list(_net().state_dict())  # names and order kept
    with torch.no_grad():
        assert torch.allclose(p.fold(module)(x), attached, atol=1e-5)
        assert not torch.allclose(attached, module(x), atol=1e-3)
    again = Payload.from_tensors(spec, p.tensors())
    with torch.no_grad():
        assert torch.allclose(again.fold(module)(x), attached, atol=1e-6)


def test_conv_lora_is_peft_conv_lora_merged():
    """B (out, r) A (r, in * k * k) reshaped to the kernel = peft's conv LoRA: A a conv with the layer's
    kernel, stride and padding into r channels, then B a 1x1 conv."""
    conv = _net().c1
    spec = PayloadSpec("lora", [describe_layer("c1", conv)], 3)
    p = Payload(spec, torch.Generator().manual_seed(0))
    a, b = p.tensor("c1", "lora_a"), p.tensor("c1", "lora_b")
    with torch.no_grad():
        b.normal_()
    x = torch.randn(2, 3, 5, 5)
    with torch.no_grad():
        merged = F.conv2d(x, p.weight("c1", conv.weight), conv.bias, padding=1)
        lora_a = F.conv2d(x, a.view(3, 3, 3, 3), padding=1)
        peft = conv(x) + F.conv2d(lora_a, b.view(8, 3, 1, 1))
    assert torch.allclose(merged, peft, atol=1e-5)


def test_layer_matching_covers_convolutions_but_defaults_stay_linear():
    module = _net()
    assert select_layers(module) == ["head"]  # the default (every linear layer but the first) is as before
    assert select_layers(module, ["all-linear"]) == ["head"]
    assert select_layers(module, ["c2", "head"]) == ["c2", "head"]
    assert select_layers(module, [r"c\d"]) == CONVS
    assert select_layers(module, [r"c\d"], exclude=["c1"]) == ["c2", "c3"]
    assert describe_layer("c2", module.c2) == {
        "name": "c2", "in_features": 8, "out_features": 6, "kernel": [3, 3], "groups": 2
    }  # fmt: skip
    assert describe_layer("head", module.head) == {"name": "head", "in_features": 100, "out_features": 5}


def test_cnn_keyed_at_its_convolution_personalizes_runs_and_exports(tmp_path, cli):
    """An array model keyed at a Conv2d and its head, end to end: inspect's keyed share, personalize
    (unsealed and sealed LoRA), run with and without the key, and the ONNX exports verified."""
    from safetensors.torch import save_file

    from tests.fixtures_arch import make_cnn

    torch.manual_seed(0)
    model = make_cnn()
    save_file(model.state_dict(), str(tmp_path / "cnn.safetensors"))
    arch = ["--arch", "tests.fixtures_arch:make_cnn"]
    layers = ["--layers", "features.0", "--layers", "head.2"]
    r = cli("inspect", tmp_path / "cnn.safetensors", *arch, *layers, "--json")
    assert r.code == 0, r.err
    info = json.loads(r.out)
    kinds = {x["name"]: (x["kind"], x["keyed"]) for x in info["layers"]}
    assert kinds == {"features.0": ("Conv2d", True), "head.0": ("Linear", False), "head.2": ("Linear", True)}
    assert info["keyed_parameters"] == 40 + 27  # the conv's 4 x 1 x 3 x 3 + 4, the head's 8 x 3 + 3
    assert info["keyed_share"] == pytest.approx(67 / info["parameters"])
    rng = np.random.default_rng(0)
    x = rng.standard_normal((64, 1, 6, 6)).astype(np.float32)
    with torch.no_grad():
        y = model(torch.from_numpy(x)).argmax(1).numpy()
    np.savez(tmp_path / "d.npz", x=x, y=((y + 1) % 3).astype(np.int64))
    np.save(tmp_path / "x.npy", x[:8])
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    for name, extra in (("unsealed", []), ("sealed", ["--seal"])):
        out = tmp_path / name
        r = cli("personalize", tmp_path / "cnn.safetensors", *arch, *layers, "--data", tmp_path / "d.npz",
                "--key-file", tmp_path / "k.bin", "--out", out, "--steps", "30", *extra)  # fmt: skip
        assert r.code == 0, r.err
        manifest = json.loads((out / "manifest.json").read_text())
        assert [x["name"] for x in manifest["keyed_layers"]] == ["features.0", "head.2"]
        assert manifest["keyed_layers"][0]["features"] == 1
        y = {}
        for run, args in (("none", []), ("key", ["--key-file", tmp_path / "k.bin"]),
                          ("onnx", ["--key-file", tmp_path / "k.bin", "--onnx"])):  # fmt: skip
            if run == "onnx":
                pytest.importorskip("onnxruntime")
                r = cli("export", out, "--onnx", "--key-file", tmp_path / "k.bin", "--json",
                        "--trust-remote-code")  # fmt: skip
                assert r.code == 0, r.err
            r = cli("run", out, "--input", tmp_path / "x.npy", "--output", tmp_path / f"{name}-{run}.npy",
                    "--trust-remote-code", *args)  # fmt: skip
            assert r.code == 0, r.err
            y[run] = np.load(tmp_path / f"{name}-{run}.npy")
        assert not np.allclose(y["none"], y["key"], atol=1e-4)
        np.testing.assert_allclose(y["onnx"], y["key"], atol=1e-5)
