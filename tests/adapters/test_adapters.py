"""Checkpoint -> module adapters."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file
from torch import nn

from prop_adapters import LoadedModel, load_checkpoint, read_weights, rebuild
from prop_adapters.mlp import natural_key
from prop_cli.errors import PropError

HERE = Path(__file__).parent


@pytest.fixture
def fixtures_path(monkeypatch):
    # Works whether or not tests/ is a package.
    monkeypatch.syspath_prepend(str(HERE))
    return "fixtures_arch"


def _save(sd: dict, path: Path, metadata: dict | None = None) -> Path:
    sd = {k: v.detach().clone().contiguous() for k, v in sd.items()}
    if path.suffix == ".safetensors":
        save_file(sd, str(path), metadata=metadata)
    else:
        torch.save(sd, path)
    return path


def _sequential(sizes=(4, 16, 8, 2), act=nn.ReLU) -> nn.Sequential:
    torch.manual_seed(0)
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(act())
    return nn.Sequential(*layers)


def _assert_matches(loaded: LoadedModel, ref: nn.Module, n_in: int) -> None:
    x = torch.randn(7, n_in)
    with torch.no_grad():
        torch.testing.assert_close(loaded.module(x), ref(x))


# ---- chain inference -------------------------------------------------------------------------


def test_sequential_prefix_names_forward_and_spec(tmp_path):
    ref = _sequential()
    path = _save(ref.state_dict(), tmp_path / "m.safetensors")
    loaded = load_checkpoint(path)
    assert list(loaded.module.state_dict()) == list(ref.state_dict())
    assert loaded.spec == {
        "adapter": "mlp",
        "layers": ["0", "2", "4"],
        "activation": "relu",
        "bias": {"0": True, "2": True, "4": True},
        "sizes": [4, 16, 8, 2],
    }
    json.dumps(loaded.spec)
    assert loaded.input_shape == (4,)
    assert loaded.source == str(path)
    assert not loaded.module.training
    _assert_matches(loaded, ref, 4)


def test_net_prefix(tmp_path):
    ref = _sequential()
    sd = {f"net.{k}": v for k, v in ref.state_dict().items()}
    loaded = load_checkpoint(_save(sd, tmp_path / "m.pt"))
    assert set(loaded.module.state_dict()) == set(sd)
    assert loaded.spec["layers"] == ["net.0", "net.2", "net.4"]
    _assert_matches(loaded, ref, 4)


def test_named_layers_and_out_of_order_keys(tmp_path):
    ref = _sequential()
    names = {"0": "actor.fc1", "2": "actor.fc2", "4": "actor.out"}
    sd = {}
    for k, v in reversed(list(ref.state_dict().items())):  # stored last layer first
        layer, leaf = k.split(".")
        sd[f"{names[layer]}.{leaf}"] = v
    loaded = load_checkpoint(_save(sd, tmp_path / "m.safetensors"))
    assert loaded.spec["layers"] == ["actor.fc1", "actor.fc2", "actor.out"]
    assert set(loaded.module.state_dict()) == set(sd)
    for k, v in sd.items():
        torch.testing.assert_close(loaded.module.state_dict()[k], v)
    _assert_matches(loaded, ref, 4)


def test_natural_sort_orders_numbers_numerically(tmp_path):
    sizes = (3,) + (5,) * 11 + (2,)  # 12 layers: "10" must come after "9"
    ref = _sequential(sizes)
    loaded = load_checkpoint(_save(ref.state_dict(), tmp_path / "m.safetensors"))
    assert loaded.spec["layers"] == [str(2 * i) for i in range(12)]
    _assert_matches(loaded, ref, 3)
    assert sorted(["fc10", "fc2", "fc1"], key=natural_key) == ["fc1", "fc2", "fc10"]


def test_names_out_of_layer_order_resolved_by_shapes(tmp_path):
    ref = _sequential((4, 16, 2))
    sd = ref.state_dict()
    # 'head' sorts before 'trunk' but only trunk (4->16) can come first.
    renamed = {k.replace("0.", "trunk.").replace("2.", "head."): v for k, v in sd.items()}
    loaded = load_checkpoint(_save(renamed, tmp_path / "m.safetensors"))
    assert loaded.spec["layers"] == ["trunk", "head"]
    _assert_matches(loaded, ref, 4)


def test_no_bias_layers(tmp_path):
    torch.manual_seed(1)
    ref = nn.Sequential(nn.Linear(4, 6, bias=False), nn.ReLU(), nn.Linear(6, 2))
    loaded = load_checkpoint(_save(ref.state_dict(), tmp_path / "m.safetensors"))
    assert loaded.spec["bias"] == {"0": False, "2": True}
    _assert_matches(loaded, ref, 4)


def test_activation_from_metadata_and_argument(tmp_path):
    ref = _sequential(act=nn.Tanh)
    path = _save(ref.state_dict(), tmp_path / "m.safetensors", metadata={"activation": "tanh"})
    loaded = load_checkpoint(path)
    assert loaded.spec["activation"] == "tanh"
    _assert_matches(loaded, ref, 4)
    # The argument wins over the metadata.
    loaded = load_checkpoint(path, activation="elu")
    _assert_matches(loaded, _sequential(act=nn.ELU), 4)


def test_unknown_activation_lists_valid(tmp_path):
    path = _save(_sequential().state_dict(), tmp_path / "m.safetensors", {"activation": "swish"})
    with pytest.raises(PropError, match=r"metadata 'activation' of .*m\.safetensors.*relu, tanh"):
        load_checkpoint(path)
    with pytest.raises(PropError, match=r"--activation.*'swish'.*leaky_relu"):
        load_checkpoint(tmp_path / "m.safetensors", activation="swish")


def test_half_precision_dtypes_are_remembered(tmp_path):
    ref = _sequential()
    sd = {k: v.half() for k, v in ref.state_dict().items()}
    loaded = load_checkpoint(_save(sd, tmp_path / "m.safetensors"))
    assert set(loaded.dtypes.values()) == {torch.float16}
    assert all(p.dtype == torch.float32 for p in loaded.module.parameters())


def test_state_dict_wrapper_in_pt(tmp_path):
    ref = _sequential()
    path = tmp_path / "ckpt.pth"
    torch.save({"model_state_dict": ref.state_dict(), "epoch": 3}, path)
    _assert_matches(load_checkpoint(path), ref, 4)


def test_deepcopy_keeps_forward(tmp_path):
    import copy

    ref = _sequential()
    loaded = load_checkpoint(_save(ref.state_dict(), tmp_path / "m.safetensors"))
    clone = copy.deepcopy(loaded.module)
    with torch.no_grad():
        clone.get_submodule("4").weight.zero_()
        clone.get_submodule("4").bias.zero_()
    _assert_matches(loaded, ref, 4)  # the original is untouched
    assert torch.count_nonzero(clone(torch.randn(3, 4))) == 0


# ---- chain errors --------------------------------------------------------------------------


def test_ambiguous_chain(tmp_path):
    g = torch.Generator().manual_seed(0)
    sd = {
        "a.weight": torch.randn(2, 8, generator=g),  # 8->2, must be last
        "b.weight": torch.randn(4, 4, generator=g),  # 4->4 twice: b,c or c,b
        "c.weight": torch.randn(4, 4, generator=g),
        "d.weight": torch.randn(8, 4, generator=g),  # 4->8
    }
    path = _save(sd, tmp_path / "amb.safetensors")
    with pytest.raises(PropError, match=r"ambiguous.*amb\.safetensors") as e:
        load_checkpoint(path)
    assert "--arch" in str(e.value)


def test_branching_layers_are_not_a_chain(tmp_path):
    g = torch.Generator().manual_seed(0)
    sd = {
        "trunk.weight": torch.randn(16, 4, generator=g),
        "mu.weight": torch.randn(2, 16, generator=g),
        "log_std.weight": torch.randn(2, 16, generator=g),
    }
    with pytest.raises(PropError, match=r"br\.safetensors is not a plain MLP.*one chain.*--arch"):
        load_checkpoint(_save(sd, tmp_path / "br.safetensors"))


def test_non_mlp_tensors(tmp_path):
    model = nn.Sequential(nn.Linear(4, 8), nn.BatchNorm1d(8), nn.Linear(8, 2))
    path = _save(model.state_dict(), tmp_path / "bn.pt")
    with pytest.raises(PropError, match=r"bn\.pt is not a plain MLP.*1\.running_mean.*--arch"):
        load_checkpoint(path)


def test_no_linear_layers(tmp_path):
    path = _save(nn.Sequential(nn.Conv2d(1, 2, 3)).state_dict(), tmp_path / "conv.safetensors")
    with pytest.raises(PropError, match=r"no linear layers in .*conv\.safetensors"):
        load_checkpoint(path)


def test_bare_linear_refused(tmp_path):
    path = _save(nn.Linear(3, 2).state_dict(), tmp_path / "bare.safetensors")
    with pytest.raises(PropError, match=r"bare\.safetensors.*bare layer"):
        load_checkpoint(path)


# ---- file errors ---------------------------------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(PropError, match=r"nope\.safetensors does not exist"):
        load_checkpoint(tmp_path / "nope.safetensors")


def test_empty_file(tmp_path):
    (tmp_path / "e.pt").write_bytes(b"")
    with pytest.raises(PropError, match=r"e\.pt is empty"):
        load_checkpoint(tmp_path / "e.pt")


@pytest.mark.parametrize("name", ["junk.pt", "junk.safetensors", "junk.bin"])
@pytest.mark.parametrize("first", [b"this is", b"\x80\x02", b"PK\x03\x04"])
def test_random_bytes_are_not_a_torch_or_safetensors_file(tmp_path, name, first):
    """Issue 10, fix 8: random bytes used to be refused for "pickling objects other than tensors"."""
    junk = first + np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8).tobytes()
    (tmp_path / name).write_bytes(junk)
    with pytest.raises(
        PropError, match=rf"{name.replace('.', '[.]')} is (not a torch or safetensors|corrupt)"
    ) as e:
        load_checkpoint(tmp_path / name)
    assert "pickles" not in str(e.value)


def test_truncated_pt(tmp_path):
    good = _save(_sequential().state_dict(), tmp_path / "good.pt")
    (tmp_path / "cut.pt").write_bytes(good.read_bytes()[:200])
    with pytest.raises(PropError, match=r"cut\.pt is corrupt"):
        load_checkpoint(tmp_path / "cut.pt")


def test_unsupported_extension(tmp_path):
    (tmp_path / "m.h5").write_bytes(b"xx")
    with pytest.raises(PropError, match=r"m\.h5 has unsupported extension.*\.safetensors"):
        load_checkpoint(tmp_path / "m.h5")


def test_directory_refused(tmp_path):
    with pytest.raises(PropError, match="is a directory"):
        read_weights(tmp_path)


def test_no_tensors(tmp_path):
    torch.save({}, tmp_path / "empty_dict.pt")
    with pytest.raises(PropError, match=r"empty_dict\.pt contains no tensors"):
        read_weights(tmp_path / "empty_dict.pt")


class Evil:
    def __reduce__(self):
        return (print, ("pwned",))


def test_pickled_object_refused(tmp_path, capsys):
    path = tmp_path / "evil.pt"
    torch.save({"w": torch.zeros(2), "obj": Evil()}, path)
    with pytest.raises(PropError, match=r"evil\.pt was refused.*never unpickles"):
        read_weights(path)
    assert "pwned" not in capsys.readouterr().out


def test_non_tensor_entries_refused(tmp_path):
    torch.save({"w": torch.zeros(2), "epoch": 3}, tmp_path / "mixed.pt")
    with pytest.raises(PropError, match=r"mixed\.pt is not a flat state dict.*epoch"):
        read_weights(tmp_path / "mixed.pt")
    torch.save([torch.zeros(2)], tmp_path / "list.pt")
    with pytest.raises(PropError, match=r"list\.pt holds a list"):
        read_weights(tmp_path / "list.pt")


def test_read_weights_metadata(tmp_path):
    path = _save(_sequential().state_dict(), tmp_path / "m.safetensors", {"activation": "gelu"})
    tensors, meta = read_weights(path)
    assert meta == {"activation": "gelu"}
    assert set(tensors) == {"0.weight", "0.bias", "2.weight", "2.bias", "4.weight", "4.bias"}
    assert read_weights(_save(_sequential().state_dict(), tmp_path / "m.pt"))[1] == {}


# ---- --arch --------------------------------------------------------------------------------


def _cnn_checkpoint(tmp_path, fixtures_path, **kwargs) -> tuple[nn.Module, Path]:
    import importlib

    mod = importlib.import_module(fixtures_path)
    torch.manual_seed(0)
    model = mod.make_cnn(**kwargs)
    return model, _save(model.state_dict(), tmp_path / "cnn.safetensors")


def test_arch_module(tmp_path, fixtures_path):
    model, path = _cnn_checkpoint(tmp_path, fixtures_path, hidden=5)
    loaded = load_checkpoint(path, arch=f"{fixtures_path}:make_cnn", arch_kwargs={"hidden": 5})
    assert loaded.spec == {
        "adapter": "module",
        "arch": f"{fixtures_path}:make_cnn",
        "arch_kwargs": {"hidden": 5},
    }
    assert set(loaded.module.state_dict()) == set(model.state_dict())
    assert loaded.input_shape == (1, 6, 6)
    x = torch.randn(2, 1, 6, 6)
    with torch.no_grad():
        torch.testing.assert_close(loaded.module(x), model(x))


def test_arch_strict_load_lists_missing_and_unexpected(tmp_path, fixtures_path):
    model, _ = _cnn_checkpoint(tmp_path, fixtures_path)
    sd = {k.replace("head.", "policy."): v for k, v in model.state_dict().items()}
    path = _save(sd, tmp_path / "renamed.safetensors")
    with pytest.raises(PropError) as e:
        load_checkpoint(path, arch=f"{fixtures_path}:make_cnn")
    msg = str(e.value)
    assert "renamed.safetensors" in msg and f"--arch '{fixtures_path}:make_cnn'" in msg
    assert "missing keys: head.0.bias, head.0.weight, head.2.bias, head.2.weight (4)" in msg
    assert "unexpected keys: policy.0.bias" in msg


def test_arch_shape_mismatch(tmp_path, fixtures_path):
    _, path = _cnn_checkpoint(tmp_path, fixtures_path, hidden=5)
    pattern = r"cnn\.safetensors does not fit --arch.*shape mismatch.*head\.0\.weight \(5, 64\) vs"
    with pytest.raises(PropError, match=pattern):
        load_checkpoint(path, arch=f"{fixtures_path}:make_cnn", arch_kwargs={"hidden": 6})


@pytest.mark.parametrize(
    ("arch", "pattern"),
    [
        ("no_colon", "not of the form package.module:factory"),
        ("no_such_module_xyz:make", "cannot import 'no_such_module_xyz'"),
        ("fixtures_arch:missing", "has no attribute 'missing'"),
        ("fixtures_arch:not_a_module", "returned a dict, not a torch.nn.Module"),
    ],
)
def test_arch_errors(tmp_path, fixtures_path, arch, pattern):
    _, path = _cnn_checkpoint(tmp_path, fixtures_path)
    with pytest.raises(PropError, match=f"--arch '{arch}'.*{pattern}"):
        load_checkpoint(path, arch=arch)


def test_arch_bad_kwargs(tmp_path, fixtures_path):
    _, path = _cnn_checkpoint(tmp_path, fixtures_path)
    with pytest.raises(PropError, match=r"--arch-kwargs .*'depth'"):
        load_checkpoint(path, arch=f"{fixtures_path}:make_cnn", arch_kwargs={"depth": 3})


def test_arch_without_linear(tmp_path, fixtures_path):
    from prop_cli.core.layers import select_layers

    path = _save(nn.Sequential(nn.Conv2d(1, 2, 3)).state_dict(), tmp_path / "c.safetensors")
    loaded = load_checkpoint(path, arch=f"{fixtures_path}:make_conv_only")  # a convolution is keyable
    with pytest.raises(PropError, match=r"no nn.Linear layers, which the default choice keys.*--layers"):
        select_layers(loaded.module)
    assert select_layers(loaded.module, ["0"]) == ["0"]
    bn = _save(nn.Sequential(nn.BatchNorm1d(2)).state_dict(), tmp_path / "bn.safetensors")
    with pytest.raises(PropError, match=r"no linear layers or convolutions in .*bn\.safetensors"):
        load_checkpoint(bn, arch=f"{fixtures_path}:make_bn_only")


def test_arch_from_current_directory(tmp_path, monkeypatch):
    (tmp_path / "my_local_policy_mod.py").write_text(
        "from torch import nn\n\ndef make():\n    return nn.Sequential(nn.Linear(3, 2))\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", [p for p in __import__("sys").path if p not in ("", ".")])
    path = _save(nn.Sequential(nn.Linear(3, 2)).state_dict(), tmp_path / "p.safetensors")
    loaded = load_checkpoint(path, arch="my_local_policy_mod:make")
    assert loaded.input_shape is None
    assert set(loaded.module.state_dict()) == {"0.weight", "0.bias"}


# ---- rebuild -------------------------------------------------------------------------------


def test_rebuild_round_trip_mlp(tmp_path):
    ref = _sequential(act=nn.GELU)
    loaded = load_checkpoint(_save(ref.state_dict(), tmp_path / "m.safetensors"), activation="gelu")
    spec = json.loads(json.dumps(loaded.spec))
    again = rebuild(spec, loaded.module.state_dict(), "bundle/base.safetensors")
    assert again.spec == loaded.spec and again.source == "bundle/base.safetensors"
    assert list(again.module.state_dict()) == list(loaded.module.state_dict())
    _assert_matches(again, ref, 4)


def test_rebuild_round_trip_module(tmp_path, fixtures_path):
    model, path = _cnn_checkpoint(tmp_path, fixtures_path)
    loaded = load_checkpoint(path, arch=f"{fixtures_path}:make_cnn")
    spec = json.loads(json.dumps(loaded.spec))
    with pytest.raises(PropError, match="--trust-remote-code"):  # a bundle's model.arch: not without consent
        rebuild(spec, dict(loaded.module.state_dict()), "b")
    again = rebuild(spec, dict(loaded.module.state_dict()), "b", trust_remote_code=True)
    x = torch.randn(2, 1, 6, 6)
    with torch.no_grad():
        torch.testing.assert_close(again.module(x), model(x))


def test_rebuild_unknown_adapter_and_bad_weights(tmp_path):
    with pytest.raises(PropError, match=r"bundle-x: unknown model adapter 'keras'"):
        rebuild({"adapter": "keras"}, {}, "bundle-x")
    ref = _sequential()
    loaded = load_checkpoint(_save(ref.state_dict(), tmp_path / "m.safetensors"))
    sd = dict(loaded.module.state_dict())
    del sd["4.bias"]
    with pytest.raises(PropError, match=r"bundle-y.*4\.bias"):
        rebuild(loaded.spec, sd, "bundle-y")
    with pytest.raises(PropError, match=r"bundle-z: model spec lacks field 'layers'"):
        rebuild({"adapter": "mlp"}, sd, "bundle-z")


def test_weights_load_into_a_module_tensor_by_tensor_and_refuse_a_mismatch(tmp_path):
    from safetensors.torch import save_file

    from prop_adapters.weights import load_into, safetensors_shapes

    torch.manual_seed(0)
    src, dst = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
    path = tmp_path / "w.safetensors"
    save_file(src.state_dict(), str(path))
    assert safetensors_shapes(path) == {"weight": (2, 3), "bias": (2,)}
    load_into(dst, path)
    assert all(torch.equal(a, b) for a, b in zip(src.state_dict().values(), dst.state_dict().values()))
    with pytest.raises(PropError, match="'weight' has shape \\(2, 3\\), the model's \\(2, 4\\)"):
        load_into(torch.nn.Linear(4, 2), path)
    with pytest.raises(PropError, match="'0.bias' is missing"):
        load_into(torch.nn.Sequential(torch.nn.Linear(3, 2)), path)


def test_load_into_as_held_refuses_a_file_swapped_after_safe_open_checked_it(tmp_path, monkeypatch):
    """``as_held`` reads the header a second time, by path: a file swapped in between whose header claims a
    huge tensor is refused in one line before anything is allocated (it would size torch.empty)."""
    from prop_adapters import weights

    src = torch.nn.Linear(3, 2).to(torch.bfloat16)
    path = tmp_path / "w.safetensors"
    save_file(src.state_dict(), str(path))
    header = {"bias": {"dtype": "BF16", "shape": [2], "data_offsets": [0, 4]},
              "weight": {"dtype": "BF16", "shape": [2**40, 3], "data_offsets": [4, 16]}}  # fmt: skip
    head = json.dumps(header).encode()
    swapped = tmp_path / "swapped.safetensors"
    swapped.write_bytes(len(head).to_bytes(8, "little") + head + bytes(16))
    monkeypatch.setattr(weights, "open", lambda p, mode: open(swapped, mode), raising=False)
    with pytest.raises(PropError, match="changed while the file was read"):
        weights.load_into(torch.nn.Linear(3, 2), path, as_held=True)
    monkeypatch.undo()
    dst = torch.nn.Linear(3, 2)
    weights.load_into(dst, path, as_held=True)
    assert dst.weight.dtype == torch.bfloat16 and torch.equal(dst.weight, src.weight)
