"""Rollback and replay protection, in the manner of TUF: the bundle versions this machine has seen.

Every write of a format 5 bundle increases its version (``manifest.next_version``), and every enrolment
and sealed record carries, authenticated under its user's key, the bundle id (in its behaviour) and the
version it was written in (``enrol``, ``records``). prop remembers here, per bundle id, in one small
JSON file under ``state_dir()``:

- ``version``: the highest manifest version prop wrote here, a key opened here, or ``prop verify``
  accepted here;
- ``users``: per enrolment id (unsealed) or record id (sealed), the highest version it was written or
  opened in, and the version whose write removed it (``prop remove-user`` here);
- ``signed``: per publisher (their public key's fingerprint, or the certificate chain's digest), the
  highest version ``prop verify`` accepted.

A key that opens a record removed here, an enrolment older than its id had here, or a copy of the
bundle older than one seen here is refused in one line; ``allow`` (``--allow-rollback``) runs it with a
warning and remembers nothing lower. Nothing derived from a key is stored: record and enrolment ids
are random, versions and bundle ids public. What this cannot see: a first use on a new machine, and an
attacker who can also reset this state (docs/threat-model.md). Format 1-4 bundles have no id: version
0, nothing remembered.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

from prop_cli import constants as C
from prop_cli.errors import PropError

from .manifest import bundle_version

STATE_FORMAT = 1
FIX = (
    "get the bundle's current copy from whoever you trust; to run this older one anyway, pass "
    "--allow-rollback (allow_rollback=True in Python)"
)
VERIFY_FIX = (
    "get the publisher's current revision; to accept this older one anyway, pass --allow-rollback"
)


class RollbackWarning(UserWarning):
    """An older copy accepted with --allow-rollback, or rollback protection off (state not writable)."""


def state_dir() -> Path:
    """Where the versions are kept: $PROP_STATE_DIR, else $XDG_STATE_HOME/prop, else ~/.local/state/prop."""
    env = os.environ.get(C.ENV_STATE_DIR)
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_STATE_HOME")
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".local" / "state"
    return base / "prop"


def _empty(bundle_id: str) -> dict:
    return {"format": STATE_FORMAT, "bundle": bundle_id, "version": 0, "users": {}, "signed": {}}


def _valid(state: object, bundle_id: str) -> bool:
    def count(v: object) -> bool:
        return type(v) is int and v >= 0

    if not isinstance(state, dict) or state.get("bundle") != bundle_id or not count(state.get("version")):
        return False
    users, signed = state.get("users"), state.get("signed")
    return (
        isinstance(users, dict)
        and all(isinstance(u, dict) and all(count(v) for v in u.values()) for u in users.values())
        and isinstance(signed, dict)
        and all(count(v) for v in signed.values())
    )


def _read(path: Path, bundle_id: str) -> dict:
    try:
        state = json.loads(path.read_text())
    except FileNotFoundError:
        return _empty(bundle_id)
    except ValueError:  # not JSON (UnicodeDecodeError is a ValueError): start again, and say so
        state = None
    if not _valid(state, bundle_id):
        warnings.warn(
            f"{path} is damaged: the versions seen of this bundle start again", RollbackWarning, stacklevel=4
        )
        return _empty(bundle_id)
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
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path``'s lock file: two prop processes never lose each other's write."""
    try:
        import fcntl
    except ImportError:  # not POSIX: the rename alone keeps the file whole
        yield
        return
    with open(path.with_suffix(".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield  # closing the file releases the lock


def _update(bundle_id: str, change: Callable[[dict], None]) -> None:
    """Read this bundle's state, ``change`` it (a PropError there refuses and writes nothing), write it."""
    folder = state_dir() / "bundles"
    path = folder / f"{bundle_id}.json"
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        with _locked(path):
            state = _read(path, bundle_id)
            before = json.dumps(state, sort_keys=True)
            change(state)
            if json.dumps(state, sort_keys=True) != before:
                _write(path, state)
    except OSError as e:
        warnings.warn(
            f"rollback protection is off for this command: {folder} cannot be used "
            f"({e.strerror or type(e).__name__}); set {C.ENV_STATE_DIR} to a folder of your own",
            RollbackWarning,
            stacklevel=3,
        )


def _raise(state: dict, key: str, version: int) -> None:
    state[key] = max(state[key], version)


def _user(state: dict, uid: str) -> dict:
    return state["users"].setdefault(uid, {})


def wrote(manifest: dict, *, users: dict[str, int] | None = None, removed: list[str] = ()) -> None:
    """After prop wrote ``manifest`` here: remember its version, the ids it enrolled (``users``: id ->
    the version they were written in) and the record ids it removed."""
    bundle_id = manifest.get(C.M_BUNDLE_ID)
    if bundle_id is None:
        return
    version = bundle_version(manifest)

    def change(state: dict) -> None:
        _raise(state, "version", version)
        for uid, v in (users or {}).items():
            entry = _user(state, uid)
            entry["version"] = max(entry.get("version", 0), v)
        for uid in removed:
            _user(state, uid).setdefault("removed", version)

    _update(bundle_id, change)


def _problem(state: dict, manifest: dict, uid: str | None, enrolled: int) -> str | None:
    """Why what a key opened is older than what this machine has seen (None: it is not)."""
    version = bundle_version(manifest)
    entry = state["users"].get(uid, {}) if uid else {}
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

    def change(state: dict) -> None:
        problem = _problem(state, manifest, uid, enrolled)
        if problem is not None:
            if not allow:
                raise PropError(f"{where} {problem}; nothing ran", FIX)
            message = f"{where} {problem}: running it anyway (--allow-rollback)"
            warnings.warn(message, RollbackWarning, stacklevel=4)
        _raise(state, "version", bundle_version(manifest))
        if uid is not None:
            entry = _user(state, uid)
            entry["version"] = max(entry.get("version", 0), enrolled)

    _update(bundle_id, change)


def verified(manifest: dict, signer: str, where: str, allow: bool = False) -> bool:
    """``prop verify`` accepted a signature of ``signer`` over the bundle ``manifest`` describes: refuse
    a version older than one this machine verified from the same signer (``allow``: a warning), then
    remember it. False: a format 1-4 bundle, which has no version to compare."""
    bundle_id = manifest.get(C.M_BUNDLE_ID)
    if bundle_id is None:
        return False
    version = bundle_version(manifest)

    def change(state: dict) -> None:
        best = state["signed"].get(signer, 0)
        if best > version:
            problem = (
                f"is an older signed revision: version {version}, and this machine verified version "
                f"{best} of this bundle signed by {signer}"
            )
            if not allow:
                raise PropError(f"{where} {problem}", VERIFY_FIX)
            warnings.warn(f"{where} {problem}: accepted (--allow-rollback)", RollbackWarning, stacklevel=4)
        state["signed"][signer] = max(best, version)
        _raise(state, "version", version)  # the publisher's version: a key's older copy is refused too

    _update(bundle_id, change)
    return True
