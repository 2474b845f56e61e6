"""Issue 42, the last item: writes and reads go through descriptors (``dir_fd``), so a folder on the way
swapped for a symbolic link while a command runs, between prop's check and its write or read, is not
followed. Each test makes the swap at that moment (a hook wrapped around the step before, or a thread
racing the command for a bounded number of tries) and checks that nothing outside is written, read or
deleted, and that the command is refused in one line or writes only the folder it opened."""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from prop_cli import constants as C
from prop_cli.errors import PropError
from prop_cli.files import bundle_lock, put, read, sha256_inside, staged_dir
from tests.bundle.test_rollback import _personalize, _sealed, _sealed_with_second_user
from tests.bundle.test_writers_and_state import _listing, _one_line


def _swap_for_link(folder: Path, target: Path) -> Path:
    """What the attacker does: move ``folder`` aside and put a link to ``target`` at its name."""
    moved = folder.with_name(folder.name + ".moved")
    os.rename(folder, moved)
    os.symlink(target, folder)
    return moved


def _tree(folder: Path) -> dict[str, bytes | None]:
    """Every entry below ``folder`` (files with their bytes, folders as None)."""
    return {
        p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else None)
        for p in sorted(folder.rglob("*"))
    }


# ---- staged folders (personalize, export --onnx/--peft/--lerobot, eval --video) --------------------


def test_a_parent_swapped_for_a_link_mid_stage_is_refused_and_nothing_goes_outside(tmp_path):
    """The folder an output is staged in is swapped for a link to the attacker's folder while the
    command writes, and the attacker has made a folder of the stage's name there (the name can be
    seen in a listing): what the command writes still goes to the stage it made, the rename is refused
    in one line naming the folder, the stage is removed, and the user's old output is untouched."""
    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    (work / "b").mkdir(parents=True)
    (work / "b" / "mine.txt").write_bytes(b"the user's")
    elsewhere.mkdir()
    with pytest.raises(PropError) as e:
        with staged_dir(work / "b") as tmp:
            (tmp / "first").write_bytes(b"1")
            stage = next(n for n in os.listdir(work) if n.endswith(".tmp"))
            (elsewhere / stage).mkdir()  # the attacker's twin of the stage
            moved = _swap_for_link(work, elsewhere)
            (tmp / "second").write_bytes(b"2")  # by the path the block was given
            (tmp / "sub").mkdir()
            (tmp / "sub" / "third").write_bytes(b"3")
    assert f"folder {work} was replaced or moved while prop wrote it" in e.value.what
    assert f"now a symbolic link to {elsewhere}" in e.value.what and "\n" not in str(e.value)
    assert _tree(elsewhere) == {stage: None}  # the twin is empty: nothing written outside
    assert _tree(moved) == {"b": None, "b/mine.txt": b"the user's"}  # old output kept, stage removed


def test_a_parent_moved_after_the_check_still_gets_nothing_outside(tmp_path, monkeypatch):
    """The swap lands after prop's last check, between it and the renames: the renames go through the
    folder's descriptor, so the output goes to the folder that was opened (moved), never to the link's
    target; nothing outside is written or deleted."""
    from prop_cli.files import atomic

    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    (work / "b").mkdir(parents=True)
    (elsewhere / "b").mkdir(parents=True)
    (elsewhere / "b" / "theirs.txt").write_bytes(b"not prop's to delete")
    real = atomic._still_there
    moved = []

    def check_then_swap(*args):
        real(*args)
        moved.append(_swap_for_link(work, elsewhere))

    monkeypatch.setattr(atomic, "_still_there", check_then_swap)
    with staged_dir(work / "b") as tmp:
        (tmp / "new").write_bytes(b"new")
    assert _tree(elsewhere) == {"b": None, "b/theirs.txt": b"not prop's to delete"}
    assert _tree(moved[0]) == {"b": None, "b/new": b"new"}


def test_a_single_file_output_follows_no_parent_swapped_mid_write(tmp_path):
    """write_file (run --output, audit JSON and plots, manifests of staged bundles): the output's folder
    swapped for a link while the file is written (a twin of the stage made at the link's target). The
    file is written in its stage by descriptor, with its suffix; the rename is refused in one line and
    the old output is kept; nothing outside is written."""
    import numpy as np

    from prop_cli.files import ARRAY, check_output, write_file

    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    work.mkdir()
    elsewhere.mkdir()
    np.save(work / "y.npy", np.zeros(1))
    old = (work / "y.npy").read_bytes()
    check_output(work / "y.npy", force=True, what="output", flag="--output", kind=ARRAY)
    moved = []

    def save(p: Path) -> None:
        assert p.suffix == ".npy"
        stage = next(n for n in os.listdir(work) if n.endswith(".tmp"))
        (elsewhere / stage).mkdir()
        moved.append(_swap_for_link(work, elsewhere))
        np.save(p, np.zeros(3))

    with pytest.raises(PropError, match="was replaced or moved while prop wrote it"):
        write_file(work / "y.npy", save)
    assert not any(p.is_file() for p in elsewhere.rglob("*"))
    assert _tree(moved[0]) == {"y.npy": old}
    os.unlink(work)
    os.rename(moved[0], work)
    write_file(work / "y.npy", lambda p: np.save(p, np.ones(3)))  # no swap: written, the stage gone
    assert np.load(work / "y.npy").tolist() == [1, 1, 1] and sorted(os.listdir(work)) == ["y.npy"]


def test_replacing_an_output_removes_no_file_a_link_in_it_names(tmp_path):
    """--force over an old output that holds links (to a folder and to a file outside): the links go,
    never what they name."""
    out, outside = tmp_path / "b", tmp_path / "outside"
    (outside / "deep").mkdir(parents=True)
    (outside / "deep" / "keep.txt").write_bytes(b"keep")
    (outside / "file.txt").write_bytes(b"keep too")
    (out / "sub").mkdir(parents=True)
    os.symlink(outside / "deep", out / "sub" / "linked-folder")
    os.symlink(outside / "file.txt", out / "linked-file")
    with staged_dir(out) as tmp:
        (tmp / "new").write_bytes(b"new")
    assert _tree(out) == {"new": b"new"}
    assert _tree(outside) == {"deep": None, "deep/keep.txt": b"keep", "file.txt": b"keep too"}


def test_a_thread_swapping_the_parent_at_a_random_moment_never_gets_a_byte_outside(tmp_path):
    """A thread swaps the output's folder for a link to the attacker's folder at a random moment after
    the command's check (40 tries, the moment spread over the whole write): each try either writes the
    output in the folder that was checked (wherever it was moved) or is refused in one line; the
    attacker's folder never receives anything."""
    import random

    from prop_cli.files import check_output

    rng = random.Random(0)
    refused = landed = 0
    start = time.perf_counter()
    with staged_dir(tmp_path / "timing") as tmp:
        for j in range(20):
            (tmp / f"part{j}").write_bytes(b"x" * 4096)
    span = 2 * (time.perf_counter() - start)  # the swap's moment: from the start to past the rename
    for i in range(40):
        work, elsewhere = tmp_path / f"work{i}", tmp_path / f"elsewhere{i}"
        work.mkdir()
        elsewhere.mkdir()
        check_output(work / "b", force=False)
        delay = rng.uniform(0, span)
        t = threading.Thread(
            target=lambda w=work, e=elsewhere, d=delay: (time.sleep(d), _swap_for_link(w, e))
        )
        t.start()
        try:
            with staged_dir(work / "b") as tmp:
                for j in range(20):
                    (tmp / f"part{j}").write_bytes(b"x" * 4096)
        except PropError as e:
            # A swap during the stage's own first check finds the folder gone: refused as unwritable.
            why = ("was replaced or moved while prop wrote it", "no file can be created in")
            assert any(w in e.what for w in why) and "\n" not in str(e), e.what
            refused += 1
        else:
            landed += 1
        t.join()
        assert _tree(elsewhere) == {}, (i, _tree(elsewhere))
        moved = tmp_path / f"work{i}.moved"
        assert set(_tree(moved)) <= {"b", *(f"b/part{j}" for j in range(20))}, _tree(moved)
    # Both outcomes are usually hit (the moments span a write's time here); under load most are refused.
    assert refused + landed == 40, (refused, landed)


def _swap_at_first_graph(monkeypatch, folder: Path, target: Path) -> list[Path]:
    """Swap ``folder`` for a link to ``target`` when the export writes its first graph (mid-command);
    returns the list that receives where ``folder`` was moved."""
    from prop_cli.run.onnx import unsealed

    real, moved = unsealed.export_graph, []

    def swap_then_export(*args, **kw):
        if not moved:
            moved.append(_swap_for_link(folder, target))
        return real(*args, **kw)

    monkeypatch.setattr(unsealed, "export_graph", swap_then_export)
    return moved


def test_export_into_the_bundle_goes_to_the_locked_bundle_only(cli, workdir, monkeypatch):
    """`prop export --onnx` into the bundle (its onnx/): the bundle path swapped for a link to another
    folder mid-export. The export is renamed through the locked bundle's descriptor: the other folder
    gets nothing."""
    b, elsewhere = workdir / "u.prop", workdir / "elsewhere"
    _personalize(cli, workdir, b)
    elsewhere.mkdir()
    moved = _swap_at_first_graph(monkeypatch, b, elsewhere)
    r = cli("export", b, "--onnx")
    assert r.code == 0, r.err
    assert _tree(elsewhere) == {}
    assert (moved[0] / C.EXPORT_DIR / C.EXPORT_META).is_file()


def test_export_to_a_folder_swapped_mid_export_is_refused_in_one_line(cli, workdir, monkeypatch):
    """`prop export --onnx --out work/x`: work/ swapped for a link to the attacker's folder while the
    graphs are written. Refused in one line naming work/; nothing in the attacker's folder, nothing
    left in work/."""
    b, work, elsewhere = workdir / "u.prop", workdir / "work", workdir / "elsewhere"
    _personalize(cli, workdir, b)
    work.mkdir()
    elsewhere.mkdir()
    moved = _swap_at_first_graph(monkeypatch, work, elsewhere)
    r = cli("export", b, "--onnx", "--out", work / "x")
    _one_line(r, f"folder {work} was replaced or moved while prop wrote it", "nothing was written there")
    assert _tree(elsewhere) == {} and _tree(moved[0]) == {}


# ---- the export's users/ (add-user, remove-user keep it the bundle's) ------------------------------


def _sealed_with_export(cli, workdir) -> Path:
    pytest.importorskip("onnxruntime")
    b = _sealed_with_second_user(cli, workdir)
    r = cli("export", b, "--onnx", "--key-file", workdir / "k.bin")
    assert r.code == 0, r.err
    return b


def test_remove_user_deletes_nothing_through_an_export_folder_swapped_after_the_check(
    cli, workdir, monkeypatch
):
    """remove-user checks <bundle>/onnx/users/ and then deletes the user's record from it: the folder
    swapped for a link to a copy elsewhere (the attacker's, or the user's backup) between the two. The
    delete goes through the bundle's descriptor, each part O_NOFOLLOW: refused in one line naming the
    link; the copy elsewhere keeps its file and the bundle keeps the user."""
    from prop_cli.run.onnx import sealed

    b = _sealed_with_export(cli, workdir)
    backup = workdir / "backup-users"
    shutil.copytree(b / C.EXPORT_DIR / C.RECORDS_DIR, backup)
    before, bundle_before = _tree(backup), _listing(b)
    real = sealed.no_links

    def check_then_swap(folder, rel, what="bundle"):
        path = real(folder, rel, what)
        if rel.startswith(C.RECORDS_DIR + "/") and not (b / C.EXPORT_DIR / C.RECORDS_DIR).is_symlink():
            _swap_for_link(b / C.EXPORT_DIR / C.RECORDS_DIR, backup)
        return path

    monkeypatch.setattr(sealed, "no_links", check_then_swap)
    r = cli("remove-user", b, "--key-file", workdir / "k2.bin")
    _one_line(r, f"{C.EXPORT_DIR}/{C.RECORDS_DIR} is a symbolic link", "tampered")
    assert _tree(backup) == before
    after = _listing(b)
    assert {k: v for k, v in after.items() if not k.startswith(C.EXPORT_DIR)} == {
        k: v for k, v in bundle_before.items() if not k.startswith(C.EXPORT_DIR)
    }


def test_add_user_writes_no_record_through_an_export_folder_swapped_after_its_check(
    cli, workdir, monkeypatch
):
    """add-user copies the new record into <bundle>/onnx/users/ after checking the export; the folder is
    swapped for a link to another folder between the check and the write. The copy goes through the
    bundle's descriptor, each part O_NOFOLLOW: refused in one line, nothing written in the other
    folder (the bundle has the new user; the export, left as it was, says it is not current)."""
    from prop_cli.run.onnx import sealed

    pytest.importorskip("onnxruntime")
    b = _sealed(cli, workdir)
    assert cli("export", b, "--onnx", "--key-file", workdir / "k.bin").code == 0
    elsewhere = workdir / "elsewhere"
    elsewhere.mkdir()
    real = sealed.read_record

    def read_then_swap(*args, **kw):
        data = real(*args, **kw)
        _swap_for_link(b / C.EXPORT_DIR / C.RECORDS_DIR, elsewhere)
        return data

    monkeypatch.setattr(sealed, "read_record", read_then_swap)
    r = cli("add-user", b, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin", "--steps", "5")
    progress, last = r.err.rstrip("\n").rsplit("\n", 1)  # the training's progress lines, then the error
    assert r.code == 2 and "Traceback" not in r.err and last.startswith("prop: error:"), r.err
    assert f"{C.EXPORT_DIR}/{C.RECORDS_DIR} is a symbolic link" in last and "tampered" in last, last
    assert _tree(elsewhere) == {}


# ---- reads ----------------------------------------------------------------------------------------


def test_a_record_folder_swapped_after_the_check_is_not_read(cli, workdir, monkeypatch):
    """A sealed bundle's users/ swapped, after the bundle's checks, for a link to a folder holding the
    genuine record (an older copy kept elsewhere on the machine): the record is read from the bundle
    folder's descriptor with O_NOFOLLOW, so the key is refused in one line, not run from the copy."""
    from prop_cli.bundle import records

    b = _sealed(cli, workdir)
    copy = workdir / "copy-users"
    shutil.copytree(b / C.RECORDS_DIR, copy)
    real = records._check_present

    def check_then_swap(path, entries):
        real(path, entries)
        if not (b / C.RECORDS_DIR).is_symlink():
            _swap_for_link(b / C.RECORDS_DIR, copy)

    monkeypatch.setattr(records, "_check_present", check_then_swap)
    r = cli(
        "run", b, "--input", workdir / "x.npy", "--output", workdir / "y.npy", "--key-file", workdir / "k.bin"
    )
    _one_line(r, f"{C.RECORDS_DIR} is a symbolic link", "tampered")
    assert not (workdir / "y.npy").exists()


@pytest.mark.parametrize("where", ["folder", "file"])
def test_a_listed_file_swapped_for_a_link_after_the_tree_check_is_refused(tmp_path, where):
    """check_files hashes every listed file from the bundle folder's descriptor, each part O_NOFOLLOW:
    a carried folder (or a file) swapped for a link to a copy with the same bytes after check_tree is
    refused in one line; the copy is not read."""
    from prop_cli.bundle import check_files

    b, copy = tmp_path / "b", tmp_path / "copy"
    (b / "lerobot").mkdir(parents=True)
    (b / "lerobot" / "config.json").write_bytes(b"{}")
    shutil.copytree(b / "lerobot", copy)
    manifest = {C.M_FILES: {"lerobot/config.json": sha256_inside(b, "lerobot/config.json")}}
    check_files(b, manifest)
    if where == "folder":
        _swap_for_link(b / "lerobot", copy)
    else:
        _swap_for_link(b / "lerobot" / "config.json", copy / "config.json")
    with pytest.raises(PropError, match=r"lerobot(/config\.json)? is a symbolic link; .*tampered"):
        check_files(b, manifest)


def test_reads_under_a_lock_go_through_the_locked_folder(tmp_path):
    """Under a bundle's lock, a read of <bundle>/onnx/... is reached from the locked folder: the bundle
    path swapped for a link to another folder with the same names is not read."""
    b, elsewhere = tmp_path / "b", tmp_path / "elsewhere"
    (b / C.EXPORT_DIR).mkdir(parents=True)
    (elsewhere / C.EXPORT_DIR).mkdir(parents=True)
    (b / C.EXPORT_DIR / C.EXPORT_META).write_bytes(b"genuine")
    (elsewhere / C.EXPORT_DIR / C.EXPORT_META).write_bytes(b"planted")
    with bundle_lock(b):
        _swap_for_link(b, elsewhere)
        assert read(b / C.EXPORT_DIR, C.EXPORT_META) == b"genuine"
        put(b / C.EXPORT_DIR, C.EXPORT_META, b"updated")
    assert (elsewhere / C.EXPORT_DIR / C.EXPORT_META).read_bytes() == b"planted"
    assert (tmp_path / "b.moved" / C.EXPORT_DIR / C.EXPORT_META).read_bytes() == b"updated"


def test_a_fifo_swapped_in_for_a_listed_file_is_refused_not_waited_on(tmp_path):
    """A FIFO put in place of a listed file after check_tree would block a plain open for ever (no
    writer comes): opened non-blocking and refused in one line as not a plain file. A path that
    leaves the folder is refused before anything is opened."""
    from prop_cli.bundle import check_files

    b = tmp_path / "b"
    b.mkdir()
    (b / "base.safetensors").write_bytes(b"weights")
    manifest = {C.M_FILES: {"base.safetensors": sha256_inside(b, "base.safetensors")}}
    os.unlink(b / "base.safetensors")
    os.mkfifo(b / "base.safetensors")
    with pytest.raises(PropError, match=r"base\.safetensors is not a plain file: .*tampered"):
        check_files(b, manifest)
    (tmp_path / "secret").write_bytes(b"not the bundle's")
    with pytest.raises(PropError, match=r"\.\./secret leaves the folder"):
        read(b, "../secret")
