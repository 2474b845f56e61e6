"""What every command writes (prop_cli/files.py): never over a file without --force, and --force
replaces only prop's own output (issue 28); an output that cannot be written fails before any work."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from prop_cli import constants as C
from tests.cli.shares import PNG_BY_MATPLOTLIB, assert_clean_error, personalize, refused_before_training


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


def test_unwritable_output_parent_missing(cli, workdir):
    res = personalize(cli, workdir, out="missing/dir/o.prop")
    assert_clean_error(res, "does not exist")


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


def test_an_existing_output_names_the_flag_and_the_parameter(tmp_path):
    from prop_cli.errors import PropError
    from prop_cli.files import check_output

    with pytest.raises(PropError, match=r"--force to replace it \(force=True in Python\)"):
        check_output(tmp_path, force=False)


def test_force_never_replaces_a_folder_that_is_not_a_bundle(cli, workdir, no_training):
    """The data loss of issue 28: `--out sub2 --force` deleted sub2/precious.txt and said "wrote sub2"."""
    sub2 = workdir / "sub2"
    sub2.mkdir()
    (sub2 / "precious.txt").write_text("mine")
    res = personalize(cli, workdir, "--force", out="sub2")
    refused_before_training(res, no_training, "--out", "sub2", "not a prop bundle", "precious.txt",
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
        refused_before_training(res, no_training, "notes.txt is a file, not a prop bundle")
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
    refused_before_training(res, no_training, "cannot write bundle /proc/x", "--out")


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
