"""prop personalize (prop_cli/cli/personalize_cmd.py): the happy path, every bad input the core issue
lists (one line, exit 2, no traceback, nothing written), settings refused before training, the gate."""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from prop_cli import constants as C
from prop_cli.config import DELTA_PULL
from tests.cli.shares import assert_clean_error, personalize, refused_before_training
from tests.conftest import FAST, make_mlp_checkpoint


def test_personalize_run_roundtrip(cli, workdir):
    res = personalize(cli, workdir, "--general-data", workdir / "general.npz", "--json")
    assert res.code == 0, res.err
    report = json.loads(res.out)
    assert set(report["metrics"][0]) >= {"personalization", "null", "random", "hamming1"}
    bundle = workdir / "mine.prop"
    assert sorted(p.name for p in bundle.iterdir()) == sorted([C.BASE_WEIGHTS, C.ENCODER_WEIGHTS, C.MANIFEST])
    # Same names, shapes and dtypes as the input checkpoint.
    base, orig = load_file(bundle / C.BASE_WEIGHTS), load_file(workdir / "model.safetensors")
    assert {k: (v.shape, v.dtype) for k, v in base.items()} == {
        k: (v.shape, v.dtype) for k, v in orig.items()
    }
    text = (bundle / C.MANIFEST).read_text()
    manifest = json.loads(text)
    assert text == json.dumps(manifest, sort_keys=True, indent=2) + "\n"
    assert manifest[C.M_FORMAT] == C.FORMAT_VERSION
    assert manifest[C.M_CONFIG]["steps"] == 40
    assert manifest[C.M_CONFIG]["delta_pull"] == DELTA_PULL["array"]  # the value trained, not "default"

    r1 = cli(
        "run",
        bundle,
        "--input",
        workdir / "x.npy",
        "--key-file",
        workdir / "k.bin",
        "--output",
        workdir / "y.npy",
    )
    r0 = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y0.npy")
    assert r1.code == 0 and r0.code == 0, (r1.err, r0.err)
    y, y0 = np.load(workdir / "y.npy"), np.load(workdir / "y0.npy")
    assert y.shape == y0.shape == (8, 2)
    assert not np.allclose(y, y0)  # the key changes the behaviour


def test_no_key_material_in_bundle(cli, workdir):
    assert personalize(cli, workdir).code == 0
    key = (workdir / "k.bin").read_bytes()
    needles = [
        key,
        key.hex().encode(),
        hashlib.sha256(key).hexdigest().encode(),
        hashlib.sha256(key).digest(),
    ]
    for f in (workdir / "mine.prop").iterdir():
        blob = f.read_bytes()
        for n in needles:
            assert n not in blob, f.name


def test_freeze_base_keeps_file_and_no_key_is_original(cli, workdir):
    assert personalize(cli, workdir, "--freeze-base").code == 0
    src = (workdir / "model.safetensors").read_bytes()
    assert (workdir / "mine.prop" / C.BASE_WEIGHTS).read_bytes() == src
    cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", workdir / "y0.npy")
    from prop_adapters import load_checkpoint

    with torch.no_grad():
        ref = (
            load_checkpoint(str(workdir / "model.safetensors"))
            .module(torch.from_numpy(np.load(workdir / "x.npy")))
            .numpy()
        )
    assert np.array_equal(np.load(workdir / "y0.npy"), ref)


def test_same_seed_same_bytes(cli, workdir):
    assert personalize(cli, workdir, out="a.prop").code == 0
    assert personalize(cli, workdir, out="b.prop").code == 0
    for name in (C.BASE_WEIGHTS, C.ENCODER_WEIGHTS):
        assert (workdir / "a.prop" / name).read_bytes() == (workdir / "b.prop" / name).read_bytes()
    ma = json.loads((workdir / "a.prop" / C.MANIFEST).read_text())
    mb = json.loads((workdir / "b.prop" / C.MANIFEST).read_text())
    # Everything but the enrolments (each under a fresh random salt and nonce), the bundle id (random:
    # two bundles) and the digest over them.
    assert ma.pop(C.M_BUNDLE_ID) != mb.pop(C.M_BUNDLE_ID)
    for m in (ma, mb):
        m.pop(C.M_ENROLMENTS), m.pop(C.M_DIGEST)
    assert ma == mb


def test_passphrase_from_env(cli, workdir, monkeypatch):
    monkeypatch.setenv(C.ENV_PASSPHRASE, "correct horse battery staple")
    res = cli(
        "personalize",
        workdir / "model.safetensors",
        "--data",
        workdir / "mine.npz",
        "--passphrase",
        "--out",
        workdir / "p.prop",
        *FAST,
    )
    assert res.code == 0, res.err
    manifest = json.loads((workdir / "p.prop" / C.MANIFEST).read_text())
    assert manifest[C.M_KEY]["kdf"]["name"] == "scrypt" and len(manifest[C.M_KEY]["kdf"]["salt"]) == 32
    blob = b"".join(f.read_bytes() for f in (workdir / "p.prop").iterdir())
    assert b"correct horse" not in blob
    assert (
        cli(
            "run",
            workdir / "p.prop",
            "--input",
            workdir / "x.npy",
            "--passphrase",
            "--output",
            workdir / "y.npy",
        ).code
        == 0
    )


def _bad_npz(wd, **fields):
    np.savez(wd / "bad.npz", **fields)
    return wd / "bad.npz"


@pytest.mark.parametrize(
    "case, words",
    [
        ("missing_ckpt", ["nope.safetensors", "does not exist"]),
        ("empty_ckpt", ["empty.safetensors", "empty"]),
        ("corrupt_ckpt", ["corrupt.safetensors"]),
        ("no_linear", ["nolinear.safetensors"]),
        ("no_x", ["bad.npz", "x"]),
        ("no_y", ["bad.npz", "y"]),
        ("lengths", ["bad.npz"]),
        ("features", ["bad.npz", "features"]),
        ("nan", ["bad.npz"]),
        ("few", ["bad.npz"]),
        ("empty_key", ["empty.bin"]),
        ("layers", ["--layers", "nomatch", "0, 2, 4"]),
        ("collide", ["closer than twice"]),
        ("unwritable", ["not writable"]),
    ],
)
def test_bad_input(cli, workdir, case, words):
    wd = workdir
    ckpt, data, key, out, extra = (
        wd / "model.safetensors",
        wd / "mine.npz",
        wd / "k.bin",
        wd / "o.prop",
        [],
    )
    x = np.zeros((50, 4), np.float32)
    y = np.zeros((50, 2), np.float32)
    if case == "missing_ckpt":
        ckpt = wd / "nope.safetensors"
    elif case == "empty_ckpt":
        ckpt = wd / "empty.safetensors"
        ckpt.write_bytes(b"")
    elif case == "corrupt_ckpt":
        ckpt = wd / "corrupt.safetensors"
        ckpt.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not json at all!")
    elif case == "no_linear":
        ckpt = wd / "nolinear.safetensors"
        save_file({"scale": torch.ones(3)}, str(ckpt))
    elif case == "no_x":
        data = _bad_npz(wd, y=y)
    elif case == "no_y":
        data = _bad_npz(wd, x=x)
    elif case == "lengths":
        data = _bad_npz(wd, x=x, y=y[:40])
    elif case == "features":
        data = _bad_npz(wd, x=np.zeros((50, 5), np.float32), y=y)
    elif case == "nan":
        x[3, 1] = np.nan
        data = _bad_npz(wd, x=x, y=y)
    elif case == "few":
        data = _bad_npz(wd, x=x[:3], y=y[:3])
    elif case == "empty_key":
        key = wd / "empty.bin"
        key.write_bytes(b"")
    elif case == "layers":
        extra = ["--layers", "nomatch"]
    elif case == "collide":
        extra = ["--data", data, "--key-file", key]
    elif case == "unwritable":
        ro = wd / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        out = ro / "o.prop"
        if os.access(ro, os.W_OK):  # root ignores permissions
            pytest.skip("running as root: permissions are not enforced")
    res = cli("personalize", ckpt, "--data", data, "--key-file", key, "--out", out, *FAST, *extra)
    assert_clean_error(res, *words)
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".o.prop")]


def test_missing_key_flags(cli, workdir):
    res = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", *FAST)
    assert_clean_error(res, "--key-file")


def test_make_checkpoint_prefix(workdir):
    # conftest helper sanity: prefixes are honoured (used by adapter tests elsewhere)
    p = make_mlp_checkpoint(workdir / "p.safetensors", prefix="net.")
    assert "net.0.weight" in load_file(p)


def test_hamming_radius_above_the_key_size_is_refused(cli, workdir):
    """Fix 5: --hamming-radius 200 was accepted for a 128-bit key."""
    res = personalize(cli, workdir, "--hamming-radius", "200")
    assert_clean_error(res, "--hamming-radius 200", "at most the key size (128 bits)")
    assert not (workdir / "mine.prop").exists()


def test_fallback_every_is_refused_for_an_array_model(cli, workdir):
    """--fallback-every thins a policy's costly fallback rows; an array model's trainer has no such step,
    so it is refused rather than recorded untrained."""
    res = personalize(cli, workdir, "--fallback-every", "2")
    assert_clean_error(res, "--fallback-every 2", "LeRobot policies only")
    assert not (workdir / "mine.prop").exists()


PAYLOAD_FLAGS = [["--payload", "peft-lora"], ["--payload-rank", "2"], ["--payload-lr", "1"]]


@pytest.mark.parametrize("extra", PAYLOAD_FLAGS)
def test_payload_settings_without_seal_are_refused(cli, workdir, no_training, extra):
    """Issue 28: `--payload peft-lora` without --seal was ignored until `prop export --peft` refused."""
    res = personalize(cli, workdir, *extra)
    refused_before_training(res, no_training, extra[0], "sealed bundles only", "--seal")
    assert not (workdir / "mine.prop").exists()


def test_harden_with_seal_is_refused(cli, workdir, no_training):
    """A sealed recipe trains none of --harden's measures; the manifest had recorded harden: true, 64
    code-space negatives and 16 antipode codes for a bundle that had none of them."""
    res = personalize(cli, workdir, "--seal", "--harden")
    refused_before_training(res, no_training, "--harden", "sealed bundle trains none", "--seal")
    assert not (workdir / "mine.prop").exists()


@pytest.mark.parametrize("flags", [["--code-negatives", "8"], ["--antipode-codes", "4"],
                                   ["--encoder-init", "os"]])
def test_hardening_settings_with_seal_are_refused(cli, workdir, no_training, flags):
    res = personalize(cli, workdir, "--seal", *flags)
    refused_before_training(res, no_training, flags[0], "sealed bundle trains none", "--seal")


def test_payload_settings_validate_with_seal():
    from prop_cli.config import PersonalizeConfig
    from prop_cli.errors import PropError

    PersonalizeConfig.of(seal=True, payload="peft-lora", payload_rank=2)
    with pytest.raises(PropError, match="--payload peft-lora applies to sealed bundles only"):
        PersonalizeConfig.of(payload="peft-lora")


def _gate_warnings(res) -> list[str]:
    return [ln for ln in res.err.splitlines() if ln.startswith("prop: warning:") and "--max-leak" in ln]


def test_personalize_gates_its_wrong_key_sweep_like_the_audit(cli, workdir, monkeypatch):
    """Issue 32: a sweep beyond the audit's --max-leak default is one stderr line with the fix, and
    --json carries the gate; 40 steps leave the unsealed sweep well beyond it (worst ~0.23)."""
    res = personalize(cli, workdir, "--json")
    assert res.code == 0, res.err
    gate = json.loads(res.out)["metrics"][0]["gate"]
    assert gate["max_leak"] == C.MAX_LEAK and gate["passed"] is False and gate["failing"]
    assert all(gate["worst"][g] > C.MAX_LEAK for g in gate["failing"])
    (line,) = _gate_warnings(res)
    assert f"--max-leak {C.MAX_LEAK:g}" in line and "--seal" in line and "--steps" in line
    assert f"random keys worst {gate['worst']['random']:.3f}" in line
    text = personalize(cli, workdir, "--force")  # the table too, not only --json
    assert len(_gate_warnings(text)) == 1 and "user 1: personalization" in text.out
    # The same figures under a threshold they stay within: passed, and nothing printed.
    monkeypatch.setattr(C, "MAX_LEAK", max(gate["worst"].values()) + 0.01)
    res = personalize(cli, workdir, "--json", "--force")
    assert json.loads(res.out)["metrics"][0]["gate"]["passed"] is True and not _gate_warnings(res)


def test_a_sealed_bundles_exact_sweep_passes_the_gate(cli, workdir):
    res = personalize(cli, workdir, "--seal", "--steps", "5", "--json", out="sealed.prop")
    assert res.code == 0, res.err
    gate = json.loads(res.out)["metrics"][0]["gate"]
    assert gate == {"max_leak": C.MAX_LEAK, "passed": True, "worst": {"random": 0.0, "hamming1": 0.0},
                    "failing": []}  # fmt: skip
    assert not _gate_warnings(res)
