"""Issue 42, the items after the export (4-8, 10, 11): one writer of a bundle at a time, a rollback state
that fails closed, is bounded, keeps its record ids HMAC'd, leaves bundle_version room, remembers the
first signer, and never follows the working folder. Each hostile file is built as an attacker would
(digests recomputed with prop's own ``stamp``/``dump_json``); each test fails on prop 0.2.0."""

from __future__ import annotations

import builtins
import errno
import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from prop_cli import constants as C
from prop_cli.bundle import rollback
from prop_cli.bundle.manifest import MAX_BUNDLE_VERSION
from prop_cli.errors import PropError
from prop_cli.files import bundle_lock, put
from tests.bundle.test_rollback import (
    _manifest,
    _personalize,
    _refused,
    _restore,
    _run,
    _sealed,
    _sealed_with_second_user,
    _signing_keys,
    _write,
)

ROOT = Path(__file__).resolve().parents[2]


def _one_line(r, *words: str) -> None:
    assert r.code == 2, (r.code, r.out, r.err)
    assert r.err.count("\n") == 1 and r.err.startswith("prop: error:") and "Traceback" not in r.err, r.err
    for w in words:
        assert w in r.err, r.err


def _listing(b: Path) -> dict[str, bytes]:
    return {p.relative_to(b).as_posix(): p.read_bytes() for p in sorted(b.rglob("*")) if p.is_file()}


# ---- item 4: one writer at a time ----------------------------------------------------------------


def test_two_add_users_at_once_lose_no_user(cli, workdir, _own_state_dir):
    """Two `prop add-user` processes on one sealed bundle at once: both users enrolled (both keys run
    keyed), or one refused in one line naming who holds the bundle; never one lost (0.2.0: both exit 0
    and the manifest lists one new record)."""
    b = _sealed(cli, workdir)
    (workdir / "k3.bin").write_bytes(os.urandom(16))
    (workdir / "k3.bin").chmod(0o600)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *sys.path]), "OMP_NUM_THREADS": "1"}
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "prop_cli.cli.main",
                "add-user",
                str(b),
                "--data",
                str(workdir / "mine.npz"),
                "--key-file",
                str(workdir / key),
                "--steps",
                "20",
                "--device",
                "cpu",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=workdir,
        )  # fmt: skip
        for key in ("k2.bin", "k3.bin")
    ]
    results = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    ok = [key for key, (code, _, _) in zip(("k2.bin", "k3.bin"), results) if code == 0]
    for code, _, err in results:
        if code != 0:
            assert code == 2 and err.count("\n") == 1 and "prop: error:" in err, err
            assert "is being written by another prop command (pid " in err, err
    assert ok, results
    m = _manifest(b)
    assert len(m[C.M_RECORDS]) == 1 + len(ok)
    listed = {e["file"] for e in m[C.M_RECORDS]}
    assert {f"{C.RECORDS_DIR}/{p.name}" for p in (b / C.RECORDS_DIR).iterdir()} == listed  # none unlisted
    assert not (b / C.BUNDLE_LOCK).exists()  # released: removed
    for key in ("k.bin", *ok):
        r, keyed = _run(cli, b, workdir, key)
        assert r.code == 0 and keyed is True, (key, r.err)


def test_a_held_bundle_is_refused_in_one_line_naming_the_holder(cli, workdir, monkeypatch):
    """Another writer holds the bundle (here: another thread, its own lock file handle, as another
    process has): add-user, remove-user, enrol and `attack --record`'s update wait, then are refused
    naming the pid; the bundle is unchanged."""
    b = _sealed(cli, workdir)
    u = workdir / "u.prop"
    _personalize(cli, workdir, u)
    monkeypatch.setattr(C, "BUNDLE_LOCK_WAIT_S", 0.3)
    held, release = threading.Event(), threading.Event()

    def hold(folder: Path) -> None:
        with bundle_lock(folder):
            held.set()
            release.wait(30)

    for folder, args in (
        (
            b,
            ("add-user", b, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin", "--steps", "5"),
        ),
        (b, ("remove-user", b, "--key-file", workdir / "k.bin")),
        (u, ("enrol", u, "--key-file", workdir / "k2.bin")),
    ):
        before = _listing(folder)
        held.clear(), release.clear()
        t = threading.Thread(target=hold, args=(folder,))
        t.start()
        assert held.wait(10)
        try:
            r = cli(*args)
            from prop_cli.bundle import update_manifest

            with pytest.raises(
                PropError, match=f"being written by another prop command \\(pid {os.getpid()}\\)"
            ):
                update_manifest(folder, C.M_AUDIT, {"note": 1})
        finally:
            release.set()
            t.join()
        _one_line(r, f"is being written by another prop command (pid {os.getpid()})", "nothing was written")
        assert _listing(folder) == before
    r = cli("enrol", u, "--key-file", workdir / "k2.bin")  # released: it goes through
    assert r.code == 0 and _manifest(u)[C.M_BUNDLE_VERSION] == 2, r.err


def test_a_link_swapped_in_mid_command_is_not_followed(workdir, tmp_path):
    """Writes go through the folder that was locked (``dir_fd``): the bundle path swapped for a link to
    another folder after the lock, or its users/ swapped for a link, is not written through."""
    b, elsewhere = tmp_path / "b", tmp_path / "elsewhere"
    (b / C.RECORDS_DIR).mkdir(parents=True)
    (elsewhere / C.RECORDS_DIR).mkdir(parents=True)
    with bundle_lock(b):
        os.rename(b, tmp_path / "moved")
        os.symlink(elsewhere, b)  # the bundle path now names another folder
        put(b, f"{C.RECORDS_DIR}/r.sealed", b"record")
        put(b, C.MANIFEST, b"{}")
    assert (tmp_path / "moved" / C.RECORDS_DIR / "r.sealed").read_bytes() == b"record"
    assert not any(elsewhere.rglob("*.sealed")) and not (elsewhere / C.MANIFEST).exists()
    os.unlink(b)
    os.rename(tmp_path / "moved", b)
    with bundle_lock(b):
        shutil.rmtree(b / C.RECORDS_DIR)
        os.symlink(elsewhere / C.RECORDS_DIR, b / C.RECORDS_DIR)
        with pytest.raises(PropError, match=r"users is a symbolic link .*tampered"):
            put(b, f"{C.RECORDS_DIR}/r2.sealed", b"record")
    assert not any(elsewhere.rglob("*.sealed"))


@pytest.mark.parametrize("kind", ["hard link to the manifest", "hard link outside", "fifo"])
def test_a_lock_file_planted_in_the_bundle_is_not_written_through(tmp_path, kind):
    """Whoever made the bundle plants its lock file as a hard link (to the manifest, or to a file of the
    receiver's outside the bundle, e.g. a tar entry) or a FIFO: taking the lock would truncate that file.
    Refused in one line, and the linked file keeps its bytes."""
    b = tmp_path / "b"
    b.mkdir()
    victim = (b / C.MANIFEST) if kind == "hard link to the manifest" else tmp_path / "k.bin"
    victim.write_bytes(b"precious")
    if kind == "fifo":
        os.mkfifo(b / C.BUNDLE_LOCK)
    else:
        os.link(victim, b / C.BUNDLE_LOCK)
    with pytest.raises(PropError, match=r"not a plain file of its own .*tampered"):
        with bundle_lock(b):
            pass
    assert victim.read_bytes() == b"precious"


# ---- items 5, 8, 11: the state fails closed, is bounded, is absolute ------------------------------


def _read_only(monkeypatch, root: Path) -> None:
    """``root`` read-only, as a read-only mount or home is: chmod, and (root ignores modes) every open
    for writing, folder made and temporary file under it refused with EROFS."""
    for p in [root, *root.rglob("*")]:
        p.chmod(0o500 if p.is_dir() else 0o400)
    if os.geteuid() != 0:
        return
    inside = str(root.resolve()) + os.sep
    real_open, real_os_open, real_mkdir = builtins.open, os.open, os.mkdir

    def under(path) -> bool:
        return isinstance(path, (str, Path)) and os.path.abspath(path).startswith(inside)

    def deny():
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    def os_open(path, flags, *a, **kw):
        if under(path) and kw.get("dir_fd") is None and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            deny()
        return real_os_open(path, flags, *a, **kw)

    def open_(file, mode="r", *a, **kw):
        if under(file) and any(c in mode for c in "wax+"):
            deny()
        return real_open(file, mode, *a, **kw)

    def mkdir(path, *a, **kw):
        if under(path):
            deny()
        return real_mkdir(path, *a, **kw)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(builtins, "open", open_)
    monkeypatch.setattr(os, "mkdir", mkdir)


def test_a_read_only_state_is_still_enforced(cli, workdir, _own_state_dir, monkeypatch):
    """The state can be read but not written (a read-only home): a removed user's key on the older copy
    is refused, not warned (0.2.0: one warning, and the removed user's record ran)."""
    from prop_cli.bundle import update_manifest

    b = _sealed_with_second_user(cli, workdir)
    old, cur = workdir / "copy.prop", workdir / "current.prop"
    shutil.copytree(b, old)
    assert cli("remove-user", b, "--key-file", workdir / "k2.bin").code == 0
    shutil.copytree(b, cur)
    _restore(old, b)
    _read_only(monkeypatch, _own_state_dir)
    try:
        _refused(_run(cli, b, workdir, "k2.bin")[0], "removed from it at version 3")
        _refused(_run(cli, b, workdir, "k.bin")[0], "older copy", "version 2")
        assert _run(cli, cur, workdir, "k.bin")[1] is True  # the current copy runs
        # A write the state cannot remember: the bundle is written, and that is said once.
        with pytest.warns(rollback.RollbackWarning, match=f"cannot be written .*{C.ENV_STATE_DIR}"):
            update_manifest(cur, C.M_AUDIT, {"note": 1})
        assert _manifest(cur)[C.M_BUNDLE_VERSION] == 4
    finally:
        monkeypatch.undo()
        for p in [_own_state_dir, *_own_state_dir.rglob("*")]:
            p.chmod(0o700)


def test_a_state_neither_readable_nor_writable_stops_and_names_the_way_on(cli, workdir, monkeypatch):
    """Neither read nor written (0.2.0: a warning, and the key ran unchecked): refused in one line naming
    PROP_STATE_DIR and --allow-rollback; --allow-rollback runs with one warning."""
    b = _sealed_with_second_user(cli, workdir)
    (workdir / "a-file").write_text("")
    monkeypatch.setenv(C.ENV_STATE_DIR, str(workdir / "a-file" / "state"))
    r, _ = _run(cli, b, workdir, "k2.bin")
    _one_line(r, "can be neither read nor written", C.ENV_STATE_DIR, "--allow-rollback")
    r, keyed = _run(cli, b, workdir, "k2.bin", "--allow-rollback")
    assert r.code == 0 and keyed and r.err.count("prop: warning:") == 1, r.err
    assert "rollback protection is off" in r.err


def test_a_relative_state_dir_is_refused(cli, workdir, monkeypatch):
    """A relative PROP_STATE_DIR would keep a different state in every working folder (0.2.0: it did)."""
    b = _sealed_with_second_user(cli, workdir)
    monkeypatch.chdir(workdir)
    monkeypatch.setenv(C.ENV_STATE_DIR, "state")
    r, _ = _run(cli, b, workdir, "k2.bin")
    _one_line(r, f"{C.ENV_STATE_DIR}='state' is a relative path", "absolute path")
    assert not (workdir / "state").exists()


def _state_file(state_dir: Path, b: Path) -> Path:
    return state_dir / "bundles" / f"{_manifest(b)[C.M_BUNDLE_ID]}.json"


@pytest.mark.parametrize(
    "hostile, words",
    [
        ("deep", "is not a prop state file (RecursionError)"),
        ("zero", "is a symbolic link"),
        ("huge", f"over the {C.STATE_MAX_BYTES}"),
        ("fifo", "is not a plain file"),
        ("fields", "its fields are wrong"),
    ],
)
def test_a_hostile_state_file_is_refused_in_one_line(cli, workdir, _own_state_dir, hostile, words):
    """A state file nested 100,000 deep (0.2.0: RecursionError), linked to /dev/zero (0.2.0: read until
    MemoryError), 5 MiB of valid JSON, a FIFO, or the wrong fields: one line naming the file and the
    fix, nothing ran; --allow-rollback goes on with a warning."""
    b = _sealed_with_second_user(cli, workdir)
    f = _state_file(_own_state_dir, b)
    before = f.read_text()
    f.unlink()
    if hostile == "deep":
        f.write_text("[" * 100_000 + "]" * 100_000)
    elif hostile == "zero":
        os.symlink("/dev/zero", f)
    elif hostile == "huge":
        f.write_text(before + " " * C.STATE_MAX_BYTES)  # valid JSON, 4 MiB of trailing spaces
    elif hostile == "fifo":
        os.mkfifo(f)
    else:
        f.write_text(json.dumps({**json.loads(before), "users": {"x": {"version": "1"}}}))
    r, _ = _run(cli, b, workdir, "k2.bin")
    _one_line(r, str(f), words, "move the file away", "--allow-rollback")
    r, keyed = _run(cli, b, workdir, "k2.bin", "--allow-rollback")
    assert r.code == 0 and keyed and "prop: warning:" in r.err, r.err


# ---- item 10: the record ids are not readable ------------------------------------------------------


def test_the_state_keeps_record_ids_hmacd_under_a_machine_secret(cli, workdir, _own_state_dir):
    """A backup of the state file does not say which record is this machine's user (0.2.0: the ids in
    the clear); the secret is made once, 32 bytes, mode 0600; a format 1 state (ids in the clear) is
    migrated on read, and its removed record stays refused."""
    b = _sealed_with_second_user(cli, workdir)
    assert _run(cli, b, workdir, "k2.bin")[1] is True
    text = _state_file(_own_state_dir, b).read_text()
    ids = [e["id"] for e in _manifest(b)[C.M_RECORDS]]
    assert not any(i in text for i in ids) and len(json.loads(text)["users"]) == 2
    secret = _own_state_dir / C.STATE_SECRET
    assert len(secret.read_bytes()) == 32 and secret.stat().st_mode & 0o777 == 0o600
    first = secret.read_bytes()
    assert _run(cli, b, workdir, "k.bin")[1] is True and secret.read_bytes() == first  # made once
    # A format 1 state, as 0.2.0 wrote it: k2's record removed at version 3.
    m = _manifest(b)
    old = {"format": 1, "bundle": m[C.M_BUNDLE_ID], "version": 2, "signed": {},
           "users": {ids[1]: {"version": 2, "removed": 3}}}  # fmt: skip
    _state_file(_own_state_dir, b).write_text(json.dumps(old))
    _refused(_run(cli, b, workdir, "k2.bin")[0], "removed from it at version 3")
    assert _run(cli, b, workdir, "k.bin")[1] is True  # written back as format 2
    state = json.loads(_state_file(_own_state_dir, b).read_text())
    assert state["format"] == 2 and not any(i in json.dumps(state) for i in ids)
    # The secret gone: the ids cannot be matched, and that is said, not ignored.
    secret.unlink()
    _one_line(_run(cli, b, workdir, "k.bin")[0], C.STATE_SECRET, "is gone")


# ---- item 6: bundle_version room -----------------------------------------------------------------


def test_a_bundle_at_the_largest_version_is_refused_before_anything_is_written(cli, workdir):
    """bundle_version at the schema's maximum (2**40; 0.2.0: 2**53, whose next write no prop read
    again): add-user and remove-user refuse in one line, the bundle unchanged; one more is refused
    by the schema."""
    b = _sealed_with_second_user(cli, workdir)
    (workdir / "k3.bin").write_bytes(os.urandom(16))
    (workdir / "k3.bin").chmod(0o600)
    m = _manifest(b)
    m[C.M_BUNDLE_VERSION] = MAX_BUNDLE_VERSION
    _write(b, m)
    before = _listing(b)
    r = cli("add-user", b, "--data", workdir / "mine.npz", "--key-file", workdir / "k3.bin", "--steps", "5")
    _one_line(r, "'bundle_version' is 1099511627776, the largest a bundle may have", "nothing was written")
    r = cli("remove-user", b, "--record", m[C.M_RECORDS][1]["id"])
    _one_line(r, "the largest a bundle may have")
    assert _listing(b) == before
    m[C.M_BUNDLE_VERSION] = MAX_BUNDLE_VERSION + 1
    _write(b, m)
    _one_line(cli("inspect", b), "'bundle_version' must be")


# ---- item 7: verify and signers ------------------------------------------------------------------


def test_another_signers_copy_does_not_raise_the_version(cli, workdir, tmp_path):
    """The bundle is first verified from its publisher (A). A copy carrying the real bundle id and
    version 10**6, signed by another accepted signer (B): verify accepts the signature, says in one
    warning that the version is not remembered, and the publisher's bundle still runs with the user's
    key (0.2.0: the version was raised, and the real bundle refused the key)."""
    pytest.importorskip("model_signing")
    from prop_cli.deploy.sign import sign_folder

    a, bee = tmp_path / "a", tmp_path / "b"
    a.mkdir(), bee.mkdir()
    _signing_keys(a), _signing_keys(bee)
    u = workdir / "u.prop"
    _personalize(cli, workdir, u)
    real = workdir / "real"
    shutil.copytree(u, real)
    sign_folder(real, a / "priv.pem")
    r = cli("verify", real, "--public-key", a / "pub.pem")
    assert r.code == 0 and "warning" not in r.err, r.err
    forged = workdir / "forged"
    shutil.copytree(u, forged)
    m = _manifest(forged)
    m[C.M_BUNDLE_VERSION] = 10**6
    _write(forged, m)
    sign_folder(forged, bee / "priv.pem")
    r = cli("verify", forged, "--public-key", bee / "pub.pem")
    assert r.code == 0 and r.err.count("prop: warning:") == 1, r.err
    assert "not by" in r.err and "is not remembered" in r.err
    r, keyed = _run(cli, real, workdir, "k.bin")
    assert r.code == 0 and keyed is True, r.err
