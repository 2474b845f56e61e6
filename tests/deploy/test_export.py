"""prop export --onnx and prop run --onnx: graphs verified by onnxruntime, no key material inside."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prop_cli import constants as C
from prop_cli.api import CheckpointOptions, KeySource, personalize_checkpoint, run_bundle
from prop_cli.bundle import load_bundle
from prop_cli.config import ExportSettings, PersonalizeConfig
from prop_cli.core.key_files import read_key_file
from prop_cli.core.keyed_model import key_codes
from prop_cli.errors import PropError
from prop_cli.run import onnx as ex
from prop_cli.run import onnx as rt
from tests.conftest import make_mlp_checkpoint

pytest.importorskip("onnxruntime")


def _make_bundle(root: Path, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    make_mlp_checkpoint(root / "model.safetensors")
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(root / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
    np.save(root / "x.npy", x[:8])
    key = rng.integers(0, 256, 16, dtype=np.uint8).tobytes()
    (root / "k.bin").write_bytes(key)
    (root / "k.bin").chmod(0o600)
    bits = np.unpackbits(np.frombuffer(key, np.uint8))
    out = root / "mine.prop"
    personalize_checkpoint(
        str(root / "model.safetensors"),
        [(root / "mine.npz", KeySource(bits, "file"))],
        out,
        PersonalizeConfig.of(steps=40, seed=seed),
    )
    return out


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """A personalized bundle, exported (with the user's key for verification) to BUNDLE/onnx."""
    root = tmp_path_factory.mktemp("export")
    bundle = _make_bundle(root)
    b = load_bundle(bundle)
    res = ex.export_onnx(b, key=read_key_file(root / "k.bin", 128))
    assert res.ok
    return bundle


def test_export_cli_writes_and_verifies_every_graph(cli, tmp_path, exported):
    root = exported.parent
    out = tmp_path / "graphs"
    r = cli("export", exported, "--onnx", "--out", out, "--key-file", root / "k.bin", "--json")
    assert r.code == 0, r.err
    res = json.loads(r.out)
    assert res["ok"] and res["opset"] == ExportSettings.opset
    assert sorted(res["files"]) == sorted([*C.GRAPHS, C.EXPORT_META])
    seen = {(row["graph"], row["key"]) for row in res["verification"]}
    for g in ("policy.onnx", "keyed.onnx", "encoder.onnx"):
        assert {(g, "random"), (g, "user")} <= seen
    assert {("base.onnx", "null"), ("policy.onnx", "null")} <= seen
    assert all(row["max_abs"] <= 1e-5 for row in res["verification"])
    meta = json.loads((out / C.EXPORT_META).read_text())
    assert meta["key"] == {"bits": 128, "encoding": "hashed"}
    assert [d["input"] for d in meta["deltas"]] == ["delta_1", "delta_2"]
    # The human table goes to stdout too.
    r = cli("export", exported, "--onnx", "--out", out, "--force")
    assert r.code == 0 and "policy.onnx" in r.out and "max abs diff" in r.out


def test_graphs_have_dynamic_batch_and_documented_inputs(exported):
    import onnxruntime as ort

    folder = exported / C.EXPORT_DIR
    ins = {g: [i.name for i in ort.InferenceSession(str(folder / g)).get_inputs()] for g in C.GRAPHS}
    assert ins == {
        "base.onnx": ["x"],
        "keyed.onnx": ["x", "code"],
        "encoder.onnx": ["code"],
        "policy.onnx": ["x", "delta_1", "delta_2"],
    }
    b = load_bundle(exported)
    for n in (1, 5):
        x = np.random.default_rng(n).standard_normal((n, 4)).astype(np.float32)
        y = ort.InferenceSession(str(folder / "base.onnx")).run(None, {"x": x})[0]
        np.testing.assert_allclose(y, run_bundle(b, x, None), atol=1e-5)


def _needles(bundle: Path) -> dict[str, list[bytes]]:
    """Byte strings that must never appear in an export: the key, its code, its deltas, folded weights."""
    b = load_bundle(bundle)
    key = (bundle.parent / "k.bin").read_bytes()
    code = key_codes(np.unpackbits(np.frombuffer(key, np.uint8)), b.key_encoding)
    needles = {"key bytes": [key], "code": [code.numpy().astype(np.float32).tobytes()]}
    with torch.no_grad():
        deltas = [d[0].numpy().astype(np.float32) for d in b.keyed.layer_deltas(code)]
        needles["delta"] = [d.tobytes() for d in deltas] + [d[:4].tobytes() for d in deltas]
        folded = dict(b.keyed.fold(code).named_parameters())
        needles["folded weights"] = [
            folded[f"{name}.weight"][0, :4].numpy().astype(np.float32).tobytes()
            for name in b.keyed.layer_names
        ]
    return needles


def test_no_key_material_or_folded_weights_in_the_export(exported):
    blobs = {p.name: p.read_bytes() for p in (exported / C.EXPORT_DIR).iterdir()}
    assert set(blobs) == {*C.GRAPHS, C.EXPORT_META}
    for what, needles in _needles(exported).items():
        for needle in needles:
            for name, blob in blobs.items():
                assert needle not in blob, f"{what} found in {name}"
    # Positive control: the search does find weights that are meant to be there.
    b = load_bundle(exported)
    w = b.keyed.module.state_dict()["2.weight"][0, :4].numpy().astype(np.float32).tobytes()
    assert w in blobs["base.onnx"] and w in blobs["policy.onnx"]


def test_run_onnx_matches_torch_with_and_without_key(cli, tmp_path, exported):
    root = exported.parent
    key = ["--key-file", root / "k.bin"]
    outs = {}
    for name, extra in {
        "onnx_key": ["--onnx", *key],
        "torch_key": key,
        "onnx": ["--onnx"],
        "torch": [],
    }.items():
        r = cli("run", exported, "--input", root / "x.npy", "--output", tmp_path / f"{name}.npy", *extra)
        assert r.code == 0, r.err
        outs[name] = np.load(tmp_path / f"{name}.npy")
    np.testing.assert_allclose(outs["onnx_key"], outs["torch_key"], atol=1e-5)
    np.testing.assert_allclose(outs["onnx"], outs["torch"], atol=1e-5)
    assert np.abs(outs["onnx_key"] - outs["onnx"]).max() > 1e-3  # the key changes the behaviour


def test_onnx_policy_split_and_folded_paths_agree_with_torch(exported):
    b = load_bundle(exported)
    bits = read_key_file(exported.parent / "k.bin", 128)
    code = key_codes(bits, b.key_encoding).numpy()
    x = np.random.default_rng(3).standard_normal((6, 4)).astype(np.float32)
    want = run_bundle(b, x, bits)
    folder = exported / C.EXPORT_DIR
    np.testing.assert_allclose(rt.OnnxRunner(folder, code=code, fold=False)(x), want, atol=1e-5)
    np.testing.assert_allclose(rt.OnnxRunner(folder, code=code, fold=True)(x), want, atol=1e-5)
    np.testing.assert_allclose(rt.OnnxRunner(folder, code=code)(x), want, atol=1e-5)  # the default: folded
    np.testing.assert_allclose(rt.OnnxRunner(folder)(x[:1]), run_bundle(b, x[:1], None), atol=1e-5)


def test_existing_output_needs_force(cli, exported):
    r = cli("export", exported, "--onnx")
    assert r.code == 2 and "already exists" in r.err and "--force" in r.err


def test_failed_verification_writes_nothing(cli, tmp_path, exported):
    out = tmp_path / "graphs"
    r = cli("export", exported, "--onnx", "--out", out, "--atol", "1e-12")
    assert r.code == 1
    assert "NO" in r.out and "verification failed" in r.err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_stale_or_modified_export_is_refused(cli, tmp_path, exported):
    root = exported.parent
    other = tmp_path / "other.prop"
    shutil.copytree(exported, other)
    # A different bundle: re-personalized weights (another seed) under the old export.
    (tmp_path / "b").mkdir()
    fresh = _make_bundle(tmp_path / "b", seed=1)
    r = cli(
        "run",
        fresh,
        "--onnx-dir",
        exported / C.EXPORT_DIR,
        "--input",
        root / "x.npy",
        "--output",
        tmp_path / "y.npy",
    )
    assert r.code == 2 and "another bundle" in r.err
    (other / C.EXPORT_DIR / "policy.onnx").write_bytes(b"tampered")
    r = cli(
        "run",
        other,
        "--onnx",
        "--key-file",
        root / "k.bin",
        "--input",
        root / "x.npy",
        "--output",
        tmp_path / "y.npy",
    )
    assert r.code == 2 and "modified" in r.err
    r = cli("run", fresh, "--onnx", "--input", root / "x.npy", "--output", tmp_path / "y.npy")
    assert r.code == 2 and "prop export" in r.err


def test_unexportable_operation_is_named(tmp_path):
    class FFT(torch.nn.Module):
        def forward(self, x):
            return torch.fft.rfft(x).abs()

    with pytest.raises(PropError, match=r"aten::fft_rfft") as e:
        args = (torch.zeros(2, 4),), tmp_path / "f.onnx", ["x"], ["y"], {"x": {0: "b"}}, 18
        ex.common.export_graph(FFT(), *args)
    assert "--opset" in str(e.value) and "\n" not in str(e.value)


def test_bad_options(cli, exported):
    assert "--onnx" in cli("export", exported).err
    r = cli("export", exported, "--onnx", "--opset", "7", "--force")
    assert r.code == 2 and "--opset 7" in r.err


def test_missing_extra_names_the_install_command(cli, monkeypatch, exported):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    with pytest.raises(PropError, match=r"prop-keys\[onnx\]"):
        rt.require_onnx()
    r = cli("export", exported, "--onnx", "--force")
    assert r.code == 2 and "pip install 'prop-keys[onnx]'" in r.err


def test_cnn_bundle_with_image_inputs_exports(tmp_path):
    """A user module (conv features, linear head): rank-4 inputs, keyed layers in the head."""
    from safetensors.torch import save_file

    from prop_adapters import load_checkpoint
    from tests.fixtures_arch import make_cnn

    torch.manual_seed(0)
    save_file(make_cnn().state_dict(), str(tmp_path / "cnn.safetensors"))
    loaded = load_checkpoint(str(tmp_path / "cnn.safetensors"), arch="tests.fixtures_arch:make_cnn")
    rng = np.random.default_rng(0)
    x = rng.standard_normal((64, 1, 6, 6)).astype(np.float32)
    with torch.no_grad():
        y = loaded.module(torch.from_numpy(x)).argmax(1).numpy()
    np.savez(tmp_path / "d.npz", x=x, y=((y + 1) % 3).astype(np.int64))
    bits = rng.integers(0, 2, 128).astype(np.uint8)
    personalize_checkpoint(
        str(tmp_path / "cnn.safetensors"),
        [(tmp_path / "d.npz", KeySource(bits, "file"))],
        tmp_path / "cnn.prop",
        PersonalizeConfig.of(steps=20),
        opts=CheckpointOptions(arch="tests.fixtures_arch:make_cnn"),
    )
    res = ex.export_onnx(load_bundle(tmp_path / "cnn.prop", trust_remote_code=True), key=bits)
    assert res.ok and max(r["max_abs"] for r in res.table) <= 1e-5
    b = load_bundle(tmp_path / "cnn.prop", trust_remote_code=True)
    np.testing.assert_allclose(rt.run_onnx(b, x[:3], bits), run_bundle(b, x[:3], bits), atol=1e-5)


def test_one_onnx_policy_serves_changing_batch_sizes(exported):
    """Issue 13: the output binding kept its first shape, so a second batch size failed."""
    b = load_bundle(exported)
    bits = read_key_file(exported.parent / "k.bin", 128)
    code = key_codes(bits, b.key_encoding).numpy()
    x = np.random.default_rng(4).standard_normal((256, 4)).astype(np.float32)
    folder = exported / C.EXPORT_DIR
    split, folded = rt.OnnxRunner(folder, code=code, fold=False), rt.OnnxRunner(folder, bits)
    policies = (split, folded, rt.OnnxRunner(folder))
    for policy, key in zip(policies, (bits, bits, None)):
        for n in (1, 256, 7, 1, 256):
            got = policy(x[:n])
            assert got.shape[0] == n
            np.testing.assert_allclose(got, run_bundle(b, x[:n], key), atol=1e-5)


# ---- what someone who can write the files does to an export ------------------------------------


@pytest.fixture(scope="module")
def sealed_exported(tmp_path_factory) -> Path:
    """A sealed bundle with an export (no key bound: the no-key path reads base.onnx alone)."""
    root = tmp_path_factory.mktemp("sealed-export")
    make_mlp_checkpoint(root / "model.safetensors")
    x = np.random.default_rng(0).uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(root / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
    np.save(root / "x.npy", x[:8])
    bits = np.random.default_rng(1).integers(0, 2, 128).astype(np.uint8)
    out = root / "sealed.prop"
    cfg = PersonalizeConfig.of(steps=40, seal=True)
    users = [(root / "mine.npz", KeySource(bits, "file"))]
    personalize_checkpoint(str(root / "model.safetensors"), users, out, cfg)
    assert ex.export_onnx(load_bundle(out)).ok
    return out


def _rehash(folder: Path) -> None:
    """export.json's graph hashes and digest recomputed with prop's own functions, as an attacker would."""
    from prop_cli.bundle.manifest import stamp
    from prop_cli.files import dump_json, sha256_file

    meta = json.loads((folder / C.EXPORT_META).read_text())
    meta["graphs"] = {g: sha256_file(folder / g) for g in meta["graphs"]}
    (folder / C.EXPORT_META).write_text(dump_json(stamp(meta, C.EXPORT_DIGEST)))


def _external(folder: Path, location: str, length: int) -> None:
    """base.onnx's first initializer emptied and pointed at ``location`` (external data)."""
    import onnx
    from onnx import TensorProto

    model = onnx.load(str(folder / C.BASE_GRAPH))
    init = model.graph.initializer[0]
    init.ClearField("raw_data")
    del init.float_data[:]
    init.data_location = TensorProto.EXTERNAL
    for k, v in (("location", location), ("offset", "0"), ("length", str(length))):
        entry = init.external_data.add()
        entry.key, entry.value = k, v
    onnx.save(model, str(folder / C.BASE_GRAPH))
    (folder / "w.bin").write_bytes(bytes(256))  # the exact size of the tensor it replaces: it would load
    _rehash(folder)


@pytest.mark.parametrize(
    "location,length",
    [("../../../../../../../../etc/passwd", 64), ("/etc/passwd", 64), ("w.bin", 256), ("w.bin", 1 << 40)],
)
@pytest.mark.parametrize("mode", ["unsealed", "sealed"])
def test_graph_with_external_data_is_refused(
    cli, tmp_path, exported, sealed_exported, mode, location, length
):
    """A tensor kept in another file (outside the folder, absolute, in the folder but not hashed, of any
    length): refused in one line before onnx or onnxruntime reads it, by the CLI and the runners."""
    src = exported if mode == "unsealed" else sealed_exported
    bundle = tmp_path / src.name
    shutil.copytree(src, bundle)
    folder = bundle / C.EXPORT_DIR
    _external(folder, location, length)
    out = tmp_path / "y.npy"
    r = cli("run", bundle, "--onnx", "--input", src.parent / "x.npy", "--output", out)
    assert r.code == 2 and not out.exists(), r.err
    assert r.err.count("\n") == 1 and r.err.startswith("prop: error:"), r.err
    assert "keeps its data in another file" in r.err and repr(location) in r.err, r.err
    runner = rt.SealedOnnxRunner if mode == "sealed" else rt.OnnxRunner
    with pytest.raises(PropError, match="keeps its data in another file"):
        runner(folder)


def test_external_data_anywhere_in_a_graph_is_found(tmp_path):
    """Not only initializers: a Constant node's tensor and an initializer inside an If's subgraph."""
    import onnx
    from onnx import TensorProto, helper

    from prop_cli.run.onnx.common import check_no_external_data

    def external(name: str) -> onnx.TensorProto:
        t = helper.make_tensor(name, TensorProto.FLOAT, [1], [0.0])
        t.ClearField("float_data")
        t.data_location = TensorProto.EXTERNAL
        entry = t.external_data.add()
        entry.key, entry.value = "location", "../outside.bin"
        return t

    out = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])
    const = helper.make_node("Constant", [], ["y"], value=external("c"))
    check_no_external_data(helper.make_model(helper.make_graph([], "g", [], [out])), tmp_path)
    with pytest.raises(PropError, match="tensor 'c' keeps its data"):
        check_no_external_data(helper.make_model(helper.make_graph([const], "g", [], [out])), tmp_path)
    branch = helper.make_graph([helper.make_node("Identity", ["s"], ["y"])], "b", [], [out], [external("s")])
    cond = helper.make_tensor_value_info("c", TensorProto.BOOL, [])
    node = helper.make_node("If", ["c"], ["y"], then_branch=branch, else_branch=branch)
    with pytest.raises(PropError, match="tensor 's' keeps its data"):
        check_no_external_data(helper.make_model(helper.make_graph([node], "g", [cond], [out])), tmp_path)


def test_export_never_writes_through_a_linked_onnx_folder(cli, tmp_path, sealed_exported):
    """BUNDLE/onnx a symbolic link to a prop export elsewhere: `export --force` and remove-user's update
    of the export refuse it in one line; the link and what it names stay as they were."""
    bundle = tmp_path / "b.prop"
    shutil.copytree(sealed_exported, bundle)
    elsewhere = tmp_path / "elsewhere" / "onnx"
    elsewhere.parent.mkdir()
    shutil.move(bundle / C.EXPORT_DIR, elsewhere)
    (bundle / C.EXPORT_DIR).symlink_to(elsewhere)
    before = {p.relative_to(elsewhere): p.read_bytes() for p in elsewhere.rglob("*") if p.is_file()}
    r = cli("export", bundle, "--onnx", "--force")
    assert r.code == 2 and r.err.count("\n") == 1, r.err
    assert "onnx is a symbolic link" in r.err, r.err  # the bundle's own check (no link in a bundle)
    rid = json.loads((bundle / C.MANIFEST).read_text())[C.M_RECORDS][0]["id"]
    with pytest.raises(PropError, match="is a symbolic link"):
        rt.drop_record(bundle / C.EXPORT_DIR, rid)
    assert (bundle / C.EXPORT_DIR).is_symlink() and list(elsewhere.parent.iterdir()) == [elsewhere]
    assert {p.relative_to(elsewhere): p.read_bytes() for p in elsewhere.rglob("*") if p.is_file()} == before
