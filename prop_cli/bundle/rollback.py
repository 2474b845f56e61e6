"""Rollback and replay protection, in the manner of TUF: the bundle versions this machine has seen.

Every write of a format 5 bundle increases its version (``manifest.next_version``), and every enrolment
and sealed record carries, authenticated under its user's key, the bundle id (in its behaviour) and the
version it was written in (``enrol``, ``records``). prop remembers here, per bundle id, in one small
JSON file under ``state_dir()``:

- ``version``: the highest manifest version prop wrote here, a key opened here, or ``prop verify``
  accepted here from the bundle's first signer;
- ``users``: per enrolment id (unsealed) or record id (sealed), kept as its HMAC-SHA256 under a secret
  of this machine's state folder (``C.STATE_SECRET``: a backup of the file does not say which record is
  this machine's user), the highest version it was written or opened in, and the version whose write
  removed it (``prop remove-user`` here);
- ``signed``: per publisher (their public key's fingerprint, or the certificate chain's digest), the
  highest version ``prop verify`` accepted; ``signer``: the publisher ``prop verify`` first accepted
  the bundle from, the only one whose versions raise ``version``.

A key that opens a record removed here, an enrolment older than its id had here, or a copy of the
bundle older than one seen here is refused in one line; ``allow`` (``--allow-rollback``) runs it with a
warning and remembers nothing lower. The state fails closed: read, it is enforced whether or not it can
be written; damaged, or neither readable nor writable, a key is refused in one line naming the file or
folder and how to go on (``--allow-rollback``, ``PROP_STATE_DIR``). Nothing derived from a key is
stored: record and enrolment ids are random (and kept HMAC'd), versions and bundle ids public. What
this cannot see: a first use on a new machine, and an attacker who can also reset this state
(docs/threat-model.md). Format 1-4 bundles have no id: version 0, nothing remembered.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import hmac
import json
import os
import stat
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

from prop_cli import constants as C
from prop_cli.errors import PropError

from .manifest import bundle_version

# 2: record ids kept as HMAC-SHA256 under the machine's secret, and the bundle's first signer. A format 1
# file (ids in the clear) is migrated when read: its ids are HMAC'd, nothing else changes.
STATE_FORMAT = 2
STATE_FORMATS = (1, 2)
FIX = (
    "get the bundle's current copy from whoever you trust; to run this older one anyway, pass "
    "--allow-rollback (allow_rollback=True in Python)"
)
VERIFY_FIX = "get the publisher's current revision; to accept this older one anyway, pass --allow-rollback"
GO_ON = (
    f"set {C.ENV_STATE_DIR} to a folder of your own, or pass --allow-rollback (allow_rollback=True in "
    "Python) to go on without the check"
)
DAMAGED_FIX = (
    "move the file away (prop then starts what it remembers of this bundle again) or restore it from a "
    f"backup; or pass --allow-rollback to go on without the check, or set {C.ENV_STATE_DIR} to another folder"
)
_ID_LABEL = b"prop/state-id/v1"
_HEX = frozenset("0123456789abcdef")
_SAID: set[str] = set()  # warnings this process gave once already


class RollbackWarning(UserWarning):
    """An older copy accepted with --allow-rollback, or the state not written (or not used)."""


class _Damaged(Exception):
    """A state file prop will not use: why, in words."""


def _once(message: str, stacklevel: int) -> None:
    if message not in _SAID:
        _SAID.add(message)
        warnings.warn(message, RollbackWarning, stacklevel=stacklevel + 1)


def state_dir() -> Path:
    """Where the versions are kept: $PROP_STATE_DIR (an absolute path: a relative one would follow the
    working folder, a different state in each), else $XDG_STATE_HOME/prop, else ~/.local/state/prop."""
    env = os.environ.get(C.ENV_STATE_DIR)
    if env:
        if not os.path.isabs(env):
            raise PropError(
                f"{C.ENV_STATE_DIR}={env!r} is a relative path: the versions seen would depend on the "
                "working folder",
                f"set {C.ENV_STATE_DIR} to an absolute path, e.g. {C.ENV_STATE_DIR}=$PWD/{env}",
            )
        return Path(env)
    xdg = os.environ.get("XDG_STATE_HOME")
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".local" / "state"
    return base / "prop"


def _read_bounded(path: Path, limit: int) -> bytes:
    """A plain file's bytes, never through a link, at most ``limit``; _Damaged otherwise (OSError: it
    cannot be read at all)."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags)
    except OSError as e:
        if e.errno == errno.ELOOP or path.is_symlink():
            raise _Damaged("is a symbolic link (prop reads its state through no link)") from None
        raise
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise _Damaged("is not a plain file")
        if st.st_size > limit:
            raise _Damaged(f"is {st.st_size} bytes, over the {limit} a state file may be")
        raw = f.read(limit + 1)
    if len(raw) > limit:
        raise _Damaged(f"is over the {limit} bytes a state file may be")
    return raw


def _secret(root: Path, create: bool) -> tuple[bytes | None, bool]:
    """This machine's state secret (32 random bytes, mode 0600), created once if ``create``, and
    whether this call made it; None if it is absent and not made. _Damaged: not such a file."""
    path = root / C.STATE_SECRET
    try:
        return _check_secret(_read_bounded(path, C.STATE_SECRET_BYTES)), False
    except FileNotFoundError:
        if not create:
            return None, False
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{C.STATE_SECRET}.", suffix=".tmp", dir=root)  # 0600
        except OSError:  # a read-only folder: ids cannot be kept, and none were (a state needs it)
            return None, False
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(os.urandom(C.STATE_SECRET_BYTES))
                f.flush()
                os.fsync(f.fileno())
            made = True
            try:
                os.link(tmp, path)
            except FileExistsError:  # another process made it first: theirs
                made = False
        finally:
            os.unlink(tmp)
        return _check_secret(_read_bounded(path, C.STATE_SECRET_BYTES)), made


def _check_secret(raw: bytes) -> bytes:
    if len(raw) != C.STATE_SECRET_BYTES:
        raise _Damaged(f"(its folder's {C.STATE_SECRET}) is not {C.STATE_SECRET_BYTES} bytes")
    return raw


def _hid(secret: bytes, bundle_id: str, uid: str) -> str:
    """How the state names record or enrolment ``uid``: HMAC-SHA256 under the machine's secret."""
    msg = _ID_LABEL + b"\0" + bundle_id.encode() + b"\0" + uid.encode()
    return hmac.new(secret, msg, hashlib.sha256).hexdigest()


def _empty(bundle_id: str) -> dict:
    return {"format": STATE_FORMAT, "bundle": bundle_id, "version": 0, "users": {}, "signed": {}}


def _valid(state: object, bundle_id: str) -> bool:
    def count(v: object) -> bool:
        return type(v) is int and 0 <= v <= 1 << 53

    if not isinstance(state, dict) or state.get("bundle") != bundle_id or not count(state.get("version")):
        return False
    if state.get("format") not in STATE_FORMATS or not set(state) <= {*_empty(""), "signer"}:
        return False
    users, signed, signer = state.get("users"), state.get("signed"), state.get("signer", "")
    return (
        isinstance(users, dict)
        and all(isinstance(k, str) and 0 < len(k) <= 256 for k in users)
        and all(isinstance(u, dict) and set(u) <= {"version", "removed"} for u in users.values())
        and all(count(v) for u in users.values() for v in u.values())
        and isinstance(signed, dict)
        and all(isinstance(k, str) and len(k) <= 256 and count(v) for k, v in signed.items())
        and isinstance(signer, str)
        and len(signer) <= 256
    )


def _read(path: Path, bundle_id: str, secret: bytes | None, fresh: bool = False) -> dict:
    """The state of ``bundle_id`` (empty if there is none); _Damaged when it is not one prop wrote
    (too big, a link, not a plain file, not JSON, nested too deep, fields wrong), or holds ids HMAC'd
    under a secret that is gone (``fresh``: the secret was made just now); OSError when it cannot be
    read. A format 1 state is migrated: its ids HMAC'd under ``secret``."""
    try:
        raw = _read_bounded(path, C.STATE_MAX_BYTES)
    except FileNotFoundError:
        return _empty(bundle_id)
    try:
        state = json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError) as e:  # UnicodeDecodeError is a ValueError
        raise _Damaged(f"is not a prop state file ({type(e).__name__})") from None
    if not _valid(state, bundle_id):
        raise _Damaged("is not a prop state file of this bundle (its fields are wrong)")
    ids = state["users"]
    if state["format"] == 1:
        if ids and secret is None:
            raise _Damaged("holds record ids, and the state folder's secret cannot be made")
        state["users"] = {_hid(secret, bundle_id, k): v for k, v in ids.items()} if ids else {}
        state["format"] = STATE_FORMAT
    elif ids and (secret is None or fresh):
        raise _Damaged(
            f"holds record ids, and its folder's {C.STATE_SECRET} is gone (they cannot be matched)"
        )
    elif not all(len(k) == 64 and set(k) <= _HEX for k in ids):
        raise _Damaged("holds a record id that is not an HMAC-SHA256")
    return state


def _write(path: Path, state: dict) -> None:
    """Atomically: a temporary sibling, flushed to disk, renamed over the old file."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(state, f, sort_keys=True, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[bool]:
    """Hold an exclusive lock on ``path``'s lock file: two prop processes never lose each other's write.
    Yields False when the lock file cannot be opened (a read-only state folder: nothing is written)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: the rename alone keeps the file whole
        yield True
        return
    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path.with_suffix(".lock"), flags, 0o600)
    except OSError:
        yield False
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield True
    finally:
        os.close(fd)  # releases the lock


class _Ids:
    """Record and enrolment ids as this state keeps them (``_hid``), for one bundle."""

    def __init__(self, secret: bytes | None, bundle_id: str) -> None:
        self.secret, self.bundle_id = secret, bundle_id

    def __call__(self, uid: str) -> str:
        if self.secret is None:  # no secret, no ids held (``_read``), and nothing is written (``_update``)
            return "-" + uid
        return _hid(self.secret, self.bundle_id, uid)


def _update(
    bundle_id: str, change: Callable[[dict, _Ids], None], *, allow: bool = False, written: bool = False
) -> None:
    """Read this bundle's state, ``change`` it (a PropError there refuses and writes nothing), write it.

    Fails closed: a state that is read is enforced, written or not (a read-only folder: a warning that
    nothing was remembered); one that is damaged, or a folder that can be neither read nor written,
    refuses in one line naming it and how to go on, unless ``allow`` (--allow-rollback: a warning, and
    nothing is checked or written) or ``written`` (after a bundle write: a warning, the bundle stands)."""
    try:
        folder = state_dir() / "bundles"
    except PropError as e:
        if not (allow or written):
            raise
        return _once(f"rollback protection is off for this command: {e.line()}", 4)
    path = folder / f"{bundle_id}.json"
    with contextlib.suppress(OSError):
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    checked = False  # the state was read (a folder that is there) and ``change`` ran on it
    try:
        with _locked(path) as writable:
            try:
                secret, fresh = _secret(folder.parent, create=writable)
                state = _read(path, bundle_id, secret, fresh)
            except _Damaged as e:
                problem = f"the rollback state file {path} {e}"
                if not (allow or written):
                    raise PropError(f"{problem}; nothing ran", DAMAGED_FIX) from None
                return _once(f"{problem}: rollback protection is off for this command", 5)
            before = json.dumps(state, sort_keys=True)
            change(state, _Ids(secret, bundle_id))
            checked = True
            if json.dumps(state, sort_keys=True) == before:
                return None
            if not writable or secret is None:  # no ids are ever written in the clear
                raise PermissionError(errno.EACCES, "the lock file or the secret cannot be made")
            _write(path, state)
    except OSError as e:
        why = e.strerror or type(e).__name__
        if checked and os.access(folder, os.R_OK | os.X_OK):  # the check ran; its versions are not kept
            return _once(
                f"the rollback state in {folder} cannot be written ({why}): the check ran, but this "
                f"command's versions are not remembered; set {C.ENV_STATE_DIR} to a folder of your own",
                4,
            )
        message = f"the rollback state in {folder} can be neither read nor written ({why})"
        if not (allow or written):
            raise PropError(f"{message}; nothing ran", GO_ON) from None
        return _once(f"{message}: rollback protection is off for this command", 4)
    return None


def _raise(state: dict, key: str, version: int) -> None:
    state[key] = max(state[key], version)


def _user(state: dict, hid: str) -> dict:
    return state["users"].setdefault(hid, {})


def wrote(manifest: dict, *, users: dict[str, int] | None = None, removed: list[str] = ()) -> None:
    """After prop wrote ``manifest`` here: remember its version, the ids it enrolled (``users``: id ->
    the version they were written in) and the record ids it removed."""
    bundle_id = manifest.get(C.M_BUNDLE_ID)
    if bundle_id is None:
        return
    version = bundle_version(manifest)

    def change(state: dict, ids: _Ids) -> None:
        _raise(state, "version", version)
        for uid, v in (users or {}).items():
            entry = _user(state, ids(uid))
            entry["version"] = max(entry.get("version", 0), v)
        for uid in removed:
            _user(state, ids(uid)).setdefault("removed", version)

    _update(bundle_id, change, written=True)


def _problem(state: dict, manifest: dict, hid: str | None, enrolled: int) -> str | None:
    """Why what a key opened is older than what this machine has seen (None: it is not)."""
    version = bundle_version(manifest)
    entry = state["users"].get(hid, {}) if hid else {}
    if "removed" in entry:
        return (
            f"is an older copy: the record this key opens was removed from it at version "
            f"{entry['removed']} on this machine (this copy says version {version})"
        )
    if entry.get("version", 0) > enrolled:
        return (
            f"is an older copy: it gives this key its enrolment of version {enrolled}, and this machine "
            f"has seen its enrolment of version {entry['version']}"
        )
    if enrolled > version:
        return f"says version {version} but holds this key's enrolment of version {enrolled} (edited)"
    if state["version"] > version:
        return f"is an older copy: version {version}, and this machine has seen version {state['version']}"
    return None


def opened(manifest: dict, uid: str | None, enrolled: int, where: str, allow: bool = False) -> None:
    """A key opened enrolment or record ``uid`` (None: a format 4 enrolment, without an id), written at
    bundle version ``enrolled``, in the bundle ``manifest`` describes: refuse it if this machine has seen
    newer (``allow``: a warning instead), then remember it."""
    bundle_id = manifest.get(C.M_BUNDLE_ID)
    if bundle_id is None:
        return

    def change(state: dict, ids: _Ids) -> None:
        hid = ids(uid) if uid is not None else None
        problem = _problem(state, manifest, hid, enrolled)
        if problem is not None:
            if not allow:
                raise PropError(f"{where} {problem}; nothing ran", FIX)
            message = f"{where} {problem}: running it anyway (--allow-rollback)"
            warnings.warn(message, RollbackWarning, stacklevel=5)
        _raise(state, "version", bundle_version(manifest))
        if hid is not None:
            entry = _user(state, hid)
            entry["version"] = max(entry.get("version", 0), enrolled)

    _update(bundle_id, change, allow=allow)


def verified(manifest: dict, signer: str, where: str, allow: bool = False) -> bool:
    """``prop verify`` accepted a signature of ``signer`` over the bundle ``manifest`` describes: refuse
    a version older than one this machine verified from the same signer (``allow``: a warning), then
    remember it. The version remembered for keys (``version``) is raised only for the signer the bundle
    was first verified from here: another accepted signer's copy does not raise it (a warning says so).
    False: a format 1-4 bundle, which has no version to compare."""
    bundle_id = manifest.get(C.M_BUNDLE_ID)
    if bundle_id is None:
        return False
    version = bundle_version(manifest)

    def change(state: dict, ids: _Ids) -> None:
        best = state["signed"].get(signer, 0)
        if best > version:
            problem = (
                f"is an older signed revision: version {version}, and this machine verified version "
                f"{best} of this bundle signed by {signer}"
            )
            if not allow:
                raise PropError(f"{where} {problem}", VERIFY_FIX)
            warnings.warn(f"{where} {problem}: accepted (--allow-rollback)", RollbackWarning, stacklevel=5)
        state["signed"][signer] = max(best, version)
        first = state.setdefault("signer", signer)
        if first == signer:
            _raise(state, "version", version)  # the publisher's version: a key's older copy is refused too
        elif version > state["version"]:
            warnings.warn(
                f"{where} is signed by {signer}, not by {first}, who signed this bundle when it was first "
                f"verified here: its version {version} is not remembered for the bundle's keys",
                RollbackWarning,
                stacklevel=5,
            )

    _update(bundle_id, change, allow=allow)
    return True
