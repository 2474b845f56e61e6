"""End-to-end CLI behaviour: the happy path, files, and every bad input the core issue lists."""

from __future__ import annotations

import hashlib
import json
import os
import re

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from prop_cli import constants as C
from tests.conftest import FAST, make_mlp_checkpoint


def personalize(cli, wd, *extra, out="mine.prop"):
    return cli(
        "personalize",
        wd / "model.safetensors",
        "--data",
        wd / "mine.npz",
        "--key-file",
        wd / "k.bin",
        "--out",
        wd / out,
        *FAST,
        *extra,
    )


# The start of a PNG that matplotlib wrote (its signature, then the "Software" text chunk it adds).
PNG_BY_MATPLOTLIB = b"\x89PNG\r\n\x1a\n\0\0\0\x28tEXtSoftware\0Matplotlib version3.9.0, https://matplotlib.org/"


def assert_clean_error(res, *words):
    assert res.code == 2, (res.code, res.err)
    lines = [ln for ln in res.err.strip().splitlines() if ln.startswith("prop: error:")]
    assert len(lines) == 1, res.err
    assert "Traceback" not in res.err
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_help_lists_commands(cli):
    res = cli("--help")
    assert res.code == 0
    for cmd in ("keygen", "inspect", "personalize", "run"):
        assert cmd in res.out


def test_version_names_the_distribution(cli):
    from importlib.metadata import version

    res = cli("--version")
    assert res.code == 0 and res.out.strip() == f"{C.DISTRIBUTION} {version(C.DISTRIBUTION)}"
    assert C.DISTRIBUTION != "prop-cli"  # someone else's package on the registry


def test_a_missing_key_file_names_the_flag(tmp_path):
    from prop_cli.core.key_files import read_key_file
    from prop_cli.errors import PropError

    for path in (tmp_path / "missing.bin", tmp_path):
        with pytest.raises(PropError, match="--key-file"):
            read_key_file(path)


def test_keygen_and_inspect(cli, workdir):
    res = cli("keygen", workdir / "new.bin", "--bits", "256")
    assert res.code == 0
    assert (workdir / "new.bin").stat().st_size == 32
    assert (workdir / "new.bin").stat().st_mode & 0o777 == 0o600
    res = cli("inspect", workdir / "model.safetensors", "--json")
    info = json.loads(res.out)
    assert [(la["name"], la["keyed"]) for la in info["layers"]] == [
        ("0", False),
        ("2", True),
        ("4", True),
    ]
    res = cli("inspect", workdir / "model.safetensors", "--layers", "4", "--json")
    assert [la["keyed"] for la in json.loads(res.out)["layers"]] == [False, False, True]


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


def test_no_overwrite_without_force(cli, workdir):
    assert personalize(cli, workdir).code == 0
    before = (workdir / "mine.prop" / C.MANIFEST).read_text()
    assert_clean_error(personalize(cli, workdir), "already exists", "--force")
    assert (workdir / "mine.prop" / C.MANIFEST).read_text() == before
    assert personalize(cli, workdir, "--force", "--seed", "1").code == 0
    assert not [p for p in workdir.iterdir() if p.name.startswith(".mine.prop")]
    np.save(workdir / "y.npy", np.zeros(1))
    res = cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, "y.npy", "--force")


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


# --- bad input: one line, exit 2, no traceback, nothing written --------------------------------


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


def test_unwritable_output_parent_missing(cli, workdir):
    res = personalize(cli, workdir, out="missing/dir/o.prop")
    assert_clean_error(res, "does not exist")


@pytest.fixture
def bundle(cli, workdir):
    assert personalize(cli, workdir).code == 0
    return workdir / "mine.prop"


def test_tampered_bundle(cli, workdir, bundle):
    f = bundle / C.BASE_WEIGHTS
    blob = bytearray(f.read_bytes())
    blob[-1] ^= 1
    f.write_bytes(bytes(blob))
    res = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, C.BASE_WEIGHTS, "sha256")
    assert not (workdir / "y.npy").exists()


def test_newer_format_version(cli, workdir, bundle):
    m = json.loads((bundle / C.MANIFEST).read_text())
    m[C.M_FORMAT] = C.FORMAT_VERSION + 1
    (bundle / C.MANIFEST).write_text(json.dumps(m))
    res = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, "format version", "upgrade")


def test_wrong_key_size_for_bundle(cli, workdir, bundle):
    (workdir / "short.bin").write_bytes(b"\x01" * 8)
    res = cli(
        "run",
        bundle,
        "--input",
        workdir / "x.npy",
        "--key-file",
        workdir / "short.bin",
        "--output",
        workdir / "y.npy",
    )
    assert_clean_error(res, "short.bin", "128")


def test_a_key_enrolled_in_nothing_fails_unless_allowed(cli, workdir, bundle):
    """Issue 31: `prop run` with a key that opens nothing exited 0 with one warning line (and the base's
    outputs); now it is exit 2, one line, nothing written, unless --allow-unenrolled-key, which every
    command that runs a key offers."""
    from prop_cli.cli.main import app

    (workdir / "other.bin").write_bytes(bytes(range(16)))
    (workdir / "other.bin").chmod(0o600)
    args = ["run", bundle, "--input", workdir / "x.npy", "--key-file", workdir / "other.bin", "--json"]
    res = cli(*args, "--output", workdir / "y.npy")
    assert_clean_error(res, f"the key is enrolled in nothing in {bundle}", "--allow-unenrolled-key")
    assert not res.out and not (workdir / "y.npy").exists()
    res = cli(*args, "--output", workdir / "y.npy", "--allow-unenrolled-key")
    assert res.code == 0 and json.loads(res.out)["keyed"] is False, res.err
    assert "prop: warning: the key is enrolled in nothing" in res.err
    assert cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y0.npy").code == 0
    np.testing.assert_array_equal(np.load(workdir / "y.npy"), np.load(workdir / "y0.npy"))
    takes = {c.name for c in app.registered_commands if "--allow-unenrolled-key" in cli(c.name, "--help").out}
    assert takes == {"run", "eval", "export", "attack"}


def test_wrong_input_shape_for_run(cli, workdir, bundle):
    np.save(workdir / "x5.npy", np.zeros((3, 5), np.float32))
    res = cli("run", bundle, "--input", workdir / "x5.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, "x5.npy", "(4,)")


def test_debug_env_shows_traceback(cli, workdir, monkeypatch):
    monkeypatch.setenv(C.ENV_DEBUG, "1")
    from prop_cli.errors import PropError

    with pytest.raises(PropError):
        cli("inspect", workdir / "nope.safetensors")


def test_missing_key_flags(cli, workdir):
    res = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", *FAST)
    assert_clean_error(res, "--key-file")


def test_make_checkpoint_prefix(workdir):
    # conftest helper sanity: prefixes are honoured (used by adapter tests elsewhere)
    p = make_mlp_checkpoint(workdir / "p.safetensors", prefix="net.")
    assert "net.0.weight" in load_file(p)


# ---- issue 10: what a new user hit ----------------------------------------------------------------


def test_overwrite_hints_name_the_commands_real_flag(cli, workdir):
    """Fix 4: run's hint said --out (its flag is --output); attack's named no flag."""
    assert personalize(cli, workdir).code == 0
    np.save(workdir / "y.npy", np.zeros(1))
    res = cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, "choose another --output or pass --force")
    (workdir / "a.json").write_text(json.dumps({"schema": C.AUDIT_SCHEMA}))  # a report, as prop writes
    (workdir / "a.png").write_bytes(PNG_BY_MATPLOTLIB)
    base = ["attack", workdir / "mine.prop", "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin"]
    assert_clean_error(cli(*base, "--json", workdir / "a.json"), "choose another --json or pass --force")
    assert_clean_error(cli(*base, "--plot", workdir / "a.png"), "choose another --plot or pass --force")


def test_hamming_radius_above_the_key_size_is_refused(cli, workdir):
    """Fix 5: --hamming-radius 200 was accepted for a 128-bit key."""
    res = personalize(cli, workdir, "--hamming-radius", "200")
    assert_clean_error(res, "--hamming-radius 200", "at most the key size (128 bits)")
    assert not (workdir / "mine.prop").exists()


def test_output_that_is_not_a_terminal_is_neither_wrapped_nor_split(cli, workdir):
    """Fix 9: piped output wrapped at 80 columns and split table cells; personalize showed no progress."""
    deep = workdir / ("a_directory_name_long_enough_to_push_the_title_past_eighty_columns_" * 2)
    deep.mkdir()
    res = personalize(cli, workdir, "--steps", "20", out=deep / "b.prop")
    assert res.code == 0, res.err
    steps = [ln for ln in res.err.splitlines() if ln.startswith("personalize: step ")]
    assert steps[0].startswith("personalize: step 2/20") and steps[-1].startswith("personalize: step 20/20")
    assert any(str(deep / "b.prop") in ln for ln in res.out.splitlines())  # the path on one line
    res = cli("attack", deep / "b.prop", "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin",
              "--hamming", "1", "--random", "16", "--restarts", "2", "--search-steps", "5",
              "--blackbox", "256")  # fmt: skip
    assert res.code == 0, res.err
    lines = res.out.splitlines()
    assert any(f"audit of {deep / 'b.prop'} (regression" in ln for ln in lines)
    rows = [ln.split() for ln in lines if ln.strip().startswith(("T0 ", "T1 ", "T2 "))]
    assert [r[:2] for r in rows[:3]] == [["T0", "null"], ["T0", "random"], ["T0", "hamming"]]
    assert all(len(r) >= 5 for r in rows)  # every cell of a row on the row's line


@pytest.mark.parametrize("command", ["run", "personalize"])
def test_no_temp_file_possible_is_one_line(cli, workdir, command, monkeypatch):
    """Fix 11: where no temporary file can be created, a traceback and exit 1."""
    import tempfile

    def refuse(*a, **kw):
        raise PermissionError(13, "Permission denied")

    if command == "run":
        assert personalize(cli, workdir).code == 0
        monkeypatch.setattr(tempfile, "mkstemp", refuse)
        res = cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", workdir / "y.npy")
        assert_clean_error(res, "cannot write output", "no file can be created", "--output")
        assert not (workdir / "y.npy").exists()
    else:
        monkeypatch.setattr(tempfile, "mkdtemp", refuse)
        assert_clean_error(personalize(cli, workdir), "cannot write bundle", "Permission denied", "--out")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test_output_under_proc_is_one_line(cli, workdir):
    assert personalize(cli, workdir).code == 0
    res = cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", "/proc/y.npy")
    assert_clean_error(res, "/proc/y.npy")


def test_every_command_has_json(cli):
    """Fix 12: the README says every command has --json; run and keygen had none."""
    from prop_cli.cli.main import app

    for cmd in app.registered_commands:
        res = cli(cmd.name, "--help")
        assert "--json" in res.out, cmd.name


def test_every_help_reads_as_a_user_types_it(cli):
    """No typer artefacts: {checkpoint}, <list[Path]>, a count's "[default: 0]"; arguments by the
    upper-case names the help texts use (CHECKPOINT, BUNDLE)."""
    from prop_cli.cli.main import app

    # 0 says something there (--hard-negatives 0: off)
    meaningful_zero = {"--threads", "--seed", "--noise-seed", "--max-steps", "--hard-negatives"}
    for cmd in app.registered_commands:
        res = cli(cmd.name, "--help")
        assert res.code == 0, cmd.name
        usage = res.out.splitlines()[0]
        assert "{" not in res.out and "<list" not in res.out, (cmd.name, res.out)
        assert "[default: None]" not in res.out and "[default: False]" not in res.out, cmd.name
        options = re.split(r"\n  (?=-)", res.out.split("\nOptions:\n")[-1])  # one entry per option
        for entry in options:
            if "[default: 0]" in " ".join(entry.split()):
                assert entry.split()[0] in meaningful_zero, (cmd.name, entry)
        words = usage.split()[3:]  # Usage: prop CMD [OPTIONS] ARGS...
        assert all(w.isupper() for w in words), usage
    personalize_help = cli("personalize", "--help").out
    assert personalize_help.startswith("Usage: prop personalize [OPTIONS] CHECKPOINT\n")
    assert "--data <path>..." in personalize_help and "--key-file <path>..." in personalize_help
    assert "Usage: prop push [OPTIONS] BUNDLE REPO" in cli("push", "--help").out
    assert "Missing argument 'CHECKPOINT'" in cli("inspect").err


def test_run_and_keygen_json(cli, workdir):
    res = cli("keygen", workdir / "new.bin", "--json")
    assert res.code == 0 and json.loads(res.out) == {
        "bits": 128,
        "mode": "0600",
        "path": str(workdir / "new.bin"),
    }
    assert personalize(cli, workdir).code == 0
    res = cli(
        "run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", workdir / "y.npy", "--json"
    )
    assert res.code == 0 and json.loads(res.out)["shape"] == [8, 2]


@pytest.mark.parametrize(
    "args, words",
    [
        (["run", "b.prop", "--input", "x.npy"], "Missing option '--output'; see prop run --help"),
        (["personalize", "m.safetensors", "--bogus"], "No such option: --bogus"),
    ],
)
def test_usage_errors_are_one_prop_error_line(cli, args, words):
    res = cli(*args)
    assert_clean_error(res, words)
    assert "Usage:" not in res.err and "Try '" not in res.err


def test_an_existing_output_names_the_flag_and_the_parameter(tmp_path):
    from prop_cli.errors import PropError
    from prop_cli.files import check_output

    with pytest.raises(PropError, match=r"--force to replace it \(force=True in Python\)"):
        check_output(tmp_path, force=False)


# ---- issue 28: --force replaces only prop's own output; every output checked before any work -------


def _refused_before_training(res, monkeypatch_calls: list, *words: str) -> None:
    assert_clean_error(res, *words)
    assert "personalize: step" not in res.err and not monkeypatch_calls  # no data read, no step trained


@pytest.fixture
def no_training(monkeypatch) -> list:
    """Record any call to personalize's data loading and trainer: a refusal must come before both."""
    import prop_cli.api as api

    calls: list = []
    monkeypatch.setattr(api, "load_data", lambda *a, **kw: calls.append("load_data"))
    monkeypatch.setattr(api, "personalize", lambda *a, **kw: calls.append("personalize"))
    return calls


def test_force_never_replaces_a_folder_that_is_not_a_bundle(cli, workdir, no_training):
    """The data loss of issue 28: `--out sub2 --force` deleted sub2/precious.txt and said "wrote sub2"."""
    sub2 = workdir / "sub2"
    sub2.mkdir()
    (sub2 / "precious.txt").write_text("mine")
    res = personalize(cli, workdir, "--force", out="sub2")
    _refused_before_training(res, no_training, "--out", "sub2", "not a prop bundle", "precious.txt",
                             "--force replaces only a prop bundle")  # fmt: skip
    assert sorted(p.name for p in sub2.iterdir()) == ["precious.txt"]
    assert (sub2 / "precious.txt").read_text() == "mine"
    assert "wrote" not in res.out
    assert sorted(p.name for p in workdir.iterdir() if p.name.startswith(".")) == []  # no temp left


def test_the_api_refuses_it_with_force_true(workdir):
    from prop_cli.api import KeySource, PersonalizeConfig, personalize_checkpoint
    from prop_cli.errors import PropError

    sub2 = workdir / "sub2"
    (sub2 / "notes").mkdir(parents=True)
    key = KeySource(np.zeros(128, np.uint8), "file")
    with pytest.raises(PropError, match=r"sub2 is a folder that is not a prop bundle \(it holds notes/\)"):
        personalize_checkpoint(str(workdir / "model.safetensors"), [(workdir / "mine.npz", key)], sub2,
                               PersonalizeConfig.of(steps=1), force=True)  # fmt: skip
    assert (sub2 / "notes").is_dir()


def test_an_existing_file_as_out_is_called_a_file(cli, workdir, no_training):
    (workdir / "notes.txt").write_text("mine")
    for extra in ([], ["--force"]):
        res = personalize(cli, workdir, *extra, out="notes.txt")
        _refused_before_training(res, no_training, "notes.txt is a file, not a prop bundle")
        assert "bundle " + str(workdir / "notes.txt") not in res.err
    assert (workdir / "notes.txt").read_text() == "mine"


def test_a_bundle_holding_a_file_prop_did_not_write_is_kept(cli, workdir, bundle):
    (bundle / "mine.key").write_bytes(b"\1" * 16)  # the user's key, put beside the bundle's files
    before = {p.name: p.read_bytes() for p in bundle.iterdir()}
    res = personalize(cli, workdir, "--force")
    assert_clean_error(res, "a prop bundle that also holds files prop did not write (mine.key)")
    assert {p.name: p.read_bytes() for p in bundle.iterdir()} == before


def test_force_replaces_a_bundle_of_an_older_format(cli, workdir, bundle):
    from prop_cli.files import dump_json

    m = json.loads((bundle / C.MANIFEST).read_text())
    del m[C.M_DIGEST], m[C.M_ENROLMENTS]
    m[C.M_FORMAT] = 1
    (bundle / C.MANIFEST).write_text(dump_json(m))
    res = personalize(cli, workdir, "--force", "--steps", "5")
    assert res.code == 0, res.err
    assert json.loads((bundle / C.MANIFEST).read_text())[C.M_FORMAT] == C.FORMAT_VERSION


def test_what_force_may_replace_of_each_kind(workdir, bundle):
    """files.check_output, per kind: prop's own output of any version is replaced, nothing else."""
    import shutil

    from prop_cli.errors import PropError
    from prop_cli.files import ARRAY, AUDIT_REPORT, BUNDLE, EXPORT, KEY, PEFT, PLOT, check_output

    def replaced(path, kind) -> bool:
        try:
            check_output(path, force=True, kind=kind)
            return True
        except PropError:
            return False

    def variant(name: str, edit) -> object:
        copy = workdir / name
        shutil.copytree(bundle, copy)
        m = json.loads((copy / C.MANIFEST).read_text())
        edit(copy, m)
        (copy / C.MANIFEST).write_text(json.dumps(m))
        return copy

    newer = variant("newer.prop", lambda d, m: m.update({C.M_FORMAT: C.FORMAT_VERSION + 1}))
    pushed = variant("pushed.prop", lambda d, m: [
        (d / "README.md").write_text("---\nlibrary_name: prop-keys\n---\n# card\n"),
        (d / C.SIGNATURE_FILE).write_text("{}"),
        (d / ".cache" / "huggingface").mkdir(parents=True),
        (d / ".cache" / "huggingface" / ".gitignore").write_text("*"),
        (d / C.EXPORT_DIR).mkdir(),
        (d / C.EXPORT_DIR / C.EXPORT_META).write_text(json.dumps({"format": 3, "graphs": {C.BASE_GRAPH: 0}})),
        (d / C.EXPORT_DIR / C.BASE_GRAPH).write_bytes(b"graph"),
    ])  # fmt: skip
    readme = variant("readme.prop", lambda d, m: (d / "README.md").write_text("my notes"))
    stray_export = variant("stray.prop", lambda d, m: [
        (d / C.EXPORT_DIR).mkdir(),
        (d / C.EXPORT_DIR / C.EXPORT_META).write_text(json.dumps({"format": 3, "graphs": {}})),
        (d / C.EXPORT_DIR / "notes.txt").write_text("mine"),
    ])  # fmt: skip
    (workdir / "empty").mkdir()
    (workdir / "user.json").write_text("{}")
    (workdir / "report.json").write_text(json.dumps({"schema": C.AUDIT_SCHEMA}))
    (workdir / "plot.png").write_bytes(PNG_BY_MATPLOTLIB)
    (workdir / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)
    (workdir / "text.key").write_text("not a key\n")
    (workdir / "peft").mkdir()
    (workdir / "peft" / C.PEFT_CONFIG).write_text(json.dumps({"peft_type": "LORA"}))
    (workdir / "peft" / C.PEFT_WEIGHTS).write_bytes(b"")
    (workdir / "peft_with_card").mkdir()
    (workdir / "peft_with_card" / C.PEFT_CONFIG).write_text(json.dumps({"peft_type": "LORA"}))
    (workdir / "peft_with_card" / "README.md").write_text("my adapter")
    w = workdir
    cases = [
        (bundle, BUNDLE, True), (newer, BUNDLE, True), (pushed, BUNDLE, True), (w / "empty", BUNDLE, True),
        (readme, BUNDLE, False), (stray_export, BUNDLE, False), (w / "notes", BUNDLE, False),
        (w / "x.npy", ARRAY, True), (w / "mine.npz", ARRAY, False), (bundle, ARRAY, False),
        (w / "k.bin", KEY, True), (w / "text.key", KEY, False), (w / "mine.npz", KEY, False),
        (workdir / "report.json", AUDIT_REPORT, True), (workdir / "user.json", AUDIT_REPORT, False),
        (workdir / "plot.png", PLOT, True), (workdir / "photo.png", PLOT, False),
        (workdir / "peft", PEFT, True), (workdir / "peft_with_card", PEFT, False),
        (pushed / C.EXPORT_DIR, EXPORT, True), (stray_export / C.EXPORT_DIR, EXPORT, False),
        (bundle, EXPORT, False),
    ]  # fmt: skip
    (w / "notes").write_text("a file")
    for path, kind, ok in cases:
        assert replaced(path, kind) == ok, (path, kind)


def test_replacing_a_link_to_a_bundle_replaces_the_link(workdir, bundle):
    from prop_cli.files import staged_dir

    link = workdir / "link.prop"
    link.symlink_to(bundle)
    before = sorted(p.name for p in bundle.iterdir())
    with staged_dir(link) as tmp:
        (tmp / "new").write_text("x")
    assert not link.is_symlink() and sorted(p.name for p in link.iterdir()) == ["new"]
    assert sorted(p.name for p in bundle.iterdir()) == before


def test_each_command_refuses_to_force_over_what_is_not_its_own(cli, workdir, bundle):
    (workdir / "notes.txt").write_text("mine")
    (workdir / "folder").mkdir()
    (workdir / "folder" / "precious.txt").write_text("mine")
    (workdir / "user.json").write_text('{"mine": 1}')
    run = ["run", bundle, "--input", workdir / "x.npy", "--force", "--output"]
    attack = ["attack", bundle, "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin", "--force"]
    for args, words in [
        ([*run, workdir / "notes.txt"], ["--output", "a file, not a .npy array"]),
        ([*run, workdir / "folder"], ["--output", "precious.txt"]),
        (["keygen", workdir / "notes.txt", "--force"], ["notes.txt", "not a key file"]),
        (["keygen", workdir / "folder", "--force"], ["folder", "precious.txt"]),
        ([*attack, "--json", workdir / "user.json"], ["--json", "not a prop audit report"]),
        ([*attack, "--plot", workdir / "notes.txt"], ["--plot", "not a PNG plot"]),
        (["export", bundle, "--onnx", "--out", workdir / "folder", "--force"], ["not a prop ONNX export"]),
        (["export", bundle, "--peft", workdir / "folder", "--key-file", workdir / "k.bin", "--force"],
         ["--peft", "precious.txt"]),
    ]:  # fmt: skip
        assert_clean_error(cli(*args), *words)
    assert (workdir / "notes.txt").read_text() == "mine"
    assert (workdir / "user.json").read_text() == '{"mine": 1}'
    assert [p.name for p in (workdir / "folder").iterdir()] == ["precious.txt"]
    # ...and replaces its own: a .npy array, a key file
    np.save(workdir / "y.npy", np.zeros(3))
    assert cli(*run, workdir / "y.npy").code == 0 and np.load(workdir / "y.npy").shape == (8, 2)
    assert cli("keygen", workdir / "k2.bin", "--force").code == 0


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test_an_output_that_cannot_be_written_fails_before_training(cli, workdir, no_training):
    """Issue 28: `personalize --out /proc/x` trained, then failed to write (as root, /proc passes
    os.access): a temporary entry is created there first."""
    res = personalize(cli, workdir, out="/proc/x")
    _refused_before_training(res, no_training, "cannot write bundle /proc/x", "--out")


def test_no_file_creatable_fails_before_any_work(cli, workdir, bundle, monkeypatch):
    """Read-only places, as a test running as root can make them: no temporary entry can be created."""
    import tempfile

    import prop_cli.api as api

    def refuse(*a, **kw):
        raise PermissionError(13, "Permission denied")

    calls: list = []
    monkeypatch.setattr(api, "audit_bundle", lambda *a, **kw: calls.append("audit"))
    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    res = cli("attack", bundle, "--data", workdir / "mine.npz", "--record")
    assert_clean_error(res, "--record", "cannot be written in place", "Permission denied")
    res = cli("attack", bundle, "--data", workdir / "mine.npz", "--json", workdir / "r.json")
    assert_clean_error(res, "cannot write --json file", "Permission denied")
    assert not calls
    res = cli("keygen", workdir / "new.bin")
    assert_clean_error(res, "cannot write key file", "Permission denied")
    assert not (workdir / "new.bin").exists()


def test_add_user_checks_the_bundle_is_writable_before_training(cli, workdir, monkeypatch):
    import tempfile

    import prop_cli.api as api

    out = workdir / "sealed.prop"
    assert personalize(cli, workdir, "--seal", "--steps", "5", out="sealed.prop").code == 0
    calls: list = []
    monkeypatch.setattr(api, "train_added_user", lambda *a, **kw: calls.append("train"))

    def refuse(*a, **kw):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    res = cli("add-user", out, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin")
    assert_clean_error(res, "cannot be written in place")
    assert not calls


PAYLOAD_FLAGS = [["--payload", "peft-lora"], ["--payload-rank", "2"], ["--payload-lr", "1"]]


@pytest.mark.parametrize("extra", PAYLOAD_FLAGS)
def test_payload_settings_without_seal_are_refused(cli, workdir, no_training, extra):
    """Issue 28: `--payload peft-lora` without --seal was ignored until `prop export --peft` refused."""
    res = personalize(cli, workdir, *extra)
    _refused_before_training(res, no_training, extra[0], "sealed bundles only", "--seal")
    assert not (workdir / "mine.prop").exists()


def test_harden_with_seal_is_refused(cli, workdir, no_training):
    """A sealed recipe trains none of --harden's measures; the manifest had recorded harden: true, 64
    code-space negatives and 16 antipode codes for a bundle that had none of them."""
    res = personalize(cli, workdir, "--seal", "--harden")
    _refused_before_training(res, no_training, "--harden", "sealed bundle trains none", "--seal")
    assert not (workdir / "mine.prop").exists()


@pytest.mark.parametrize("flags", [["--code-negatives", "8"], ["--antipode-codes", "4"],
                                   ["--encoder-init", "os"]])
def test_hardening_settings_with_seal_are_refused(cli, workdir, no_training, flags):
    res = personalize(cli, workdir, "--seal", *flags)
    _refused_before_training(res, no_training, flags[0], "sealed bundle trains none", "--seal")


def test_a_sealed_bundles_recorded_harden_is_dropped_for_add_user(cli, workdir):
    """Sealed bundles written before --seal --harden was refused recorded --harden's settings untrained;
    add-user reads them without them instead of refusing its own bundle."""
    from types import SimpleNamespace

    from prop_cli.config import PersonalizeConfig
    from prop_cli.errors import PropError
    from prop_cli.train.added_user import added_user_config

    out = workdir / "sealed.prop"
    assert personalize(cli, workdir, "--seal", "--steps", "5", out="sealed.prop").code == 0
    m = json.loads((out / "manifest.json").read_text())
    m["config"] |= {"harden": True, "code_negatives": 64, "encoder_init": "os", "antipode_codes": 16}
    cfg = added_user_config(SimpleNamespace(manifest=m, key_bits=128), None)
    assert cfg.sealed and "harden" not in cfg.to_dict() and "code_negatives" not in cfg.to_dict()
    with pytest.raises(PropError, match="sealed bundle trains none"):  # the same settings, given anew
        PersonalizeConfig.of(**m["config"])


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
