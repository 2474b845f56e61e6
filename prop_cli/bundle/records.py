"""The records of a sealed bundle: one user's payload each, encrypted under a key derived from their key.

A sealed bundle's base is the original checkpoint; each user's payload (``prop_cli.core.payload``)
is an AES-GCM record (``cipher``) that only their key opens, and a wrong key opens nothing. Since
format 4 a record is its user's enrolment (``enrol``): its plaintext carries the bundle's behaviour
as it was when the user was enrolled (base weights, model, payload layout, LeRobot processors...), so
with the user's key a changed bundle is reported ("changed since this key was enrolled") and nothing
runs; the associated data binds the record's id. Format 2-3 records bound the public fields in their
associated data instead (``binding``): an edit made every record fail to open, and the base ran.

Format 5 records also carry, in the same plaintext, the bundle version they were written in
(``enrol.VERSION``; the bundle id is part of the behaviour): the record's id and version are what
``rollback`` compares with the versions this machine has seen.

This module reads, opens, writes and rewrites records; training a payload is ``prop_cli.train``.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np

from prop_cli import constants as C
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.errors import PropError
from prop_cli.files import bundle_lock, delete, dump_json, no_links, put, read, sha256_inside, write_inside

from . import rollback
from .cipher import SealedRecord, decode_payload, encode_payload, open_record, pad, seal, unpad
from .enrol import VERSION, behaviour, changed
from .lookup import LOOKUP, Index, salt_of
from .manifest import bundle_version, next_version, restamp

# Format 2-3 records: the manifest fields that decide how a payload is applied, authenticated with
# every record as associated data (``binding``). Format 4 records carry ``enrol.behaviour`` inside.
_BOUND = (C.M_FORMAT, C.M_MODE, C.M_MODEL, C.M_PAYLOAD, C.M_TASK)
BEHAVIOUR = "behaviour"  # the key of the enrolled behaviour in a format 4 record's metadata


def enrolled_records(manifest: dict) -> bool:
    """Whether the bundle's records carry their enrolment (format 4 on), else bind by associated data."""
    return manifest[C.M_FORMAT] >= C.ENROL_SINCE


def public_part(manifest: dict) -> dict:
    """The manifest fields that opening a record and checking its enrolment need (an ONNX export
    carries them)."""
    part = {f: manifest.get(f) for f in _BOUND}
    for f in (C.M_IO, C.M_KEY, C.M_FILES, C.M_RECORDS, C.M_KEYED_LAYERS):
        part[f] = manifest.get(f)
    if C.M_BUNDLE_ID in manifest:  # part of the records' behaviour (format 5)
        part[C.M_BUNDLE_ID] = manifest[C.M_BUNDLE_ID]
    return part


def record_ad(manifest: dict, record_id: str) -> bytes:
    """A record's associated data: its id (format 4), or the bound public fields and its id (2-3)."""
    if enrolled_records(manifest):
        return hashlib.sha256(b"prop/seal/v2\0" + record_id.encode()).digest()
    return binding(manifest, record_id)


def binding(manifest: dict, record_id: str) -> bytes:
    """Format 2-3: the associated data of one record, a digest of the bound public fields and its id."""
    key = manifest[C.M_KEY]
    bound = {f: manifest.get(f) for f in _BOUND}
    bound["input_shape"] = manifest[C.M_IO]["input_shape"]
    bound["key"] = {"bits": key["bits"], "kdf": key.get("kdf")}
    bound["base_sha256"] = manifest[C.M_FILES][C.BASE_WEIGHTS]
    bound["record"] = record_id
    text = json.dumps(bound, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(b"prop/seal/binding/v1\0" + text.encode()).digest()


@dataclass
class Opened:
    record_id: str
    payload: Payload
    meta: dict  # what was sealed beside the tensors: the user's metrics and training settings
    changed: list[str]  # what differs from what the record was enrolled in ([]: nothing, or format 2-3)
    version: int = 0  # the bundle version the record was written in (format 5; 0 before)


@dataclass
class SealedState:
    """A sealed bundle's public part beyond the base: the payload layout and the encrypted records.
    ``folder``: where the records whose ciphertext is not in memory (None) are read from, each when it is
    tried, checked against its sha256 in the manifest (format 6: a key tries one record, not all)."""

    manifest: dict
    spec: PayloadSpec
    records: Sequence[SealedRecord]  # a list, or ``Listed``: made from the manifest's entries when tried
    folder: Path | None = None

    def __post_init__(self) -> None:
        self.enrolled = enrolled_records(self.manifest)
        self.behaviour = behaviour(self.manifest) if self.enrolled else None
        names = self.records.entries if isinstance(self.records, Listed) else self.records
        self.index = Index([_name(r) for r in names], salt_of(self.manifest))
        # The associated data of each record, computed once when first tried: the audit tries a million
        # keys. Files read: the last READ_KEPT kept (the audit's keys on a small bundle read each once).
        self._bound: dict[int, bytes] = {}
        self._read: OrderedDict[int, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def _ciphertext(self, i: int) -> bytes:
        rec = self.records[i]
        if rec.ciphertext is not None:
            return rec.ciphertext
        with self._lock:  # a server opens keys from more than one thread
            data = self._read.pop(i, None)
        if data is None:
            data = read_record(self.folder, self.manifest[C.M_RECORDS][i])
        with self._lock:
            self._read[i] = data
            while len(self._read) > READ_KEPT:
                self._read.popitem(last=False)
        return data

    def _try(self, i: int, bits: np.ndarray) -> bytes | None:
        if i not in self._bound:
            self._bound[i] = record_ad(self.manifest, self.records[i].id)
        return open_record(self.records[i], bits, self._bound[i], self._ciphertext(i))

    def find(self, bits: np.ndarray) -> tuple[int, bytes] | None:
        """(position, plaintext) of the record ``bits`` opens, or None: the same work whichever record
        opens, or none (``lookup.Index.tries``). Format 6: the record filed under the key's name, or a
        stand-in of the same size that cannot count (read, checked, decrypted all the same); and every
        record without a name (format 2-5: all of them), whichever opens."""
        first, counts, rest = self.index.tries(bits)
        found = None
        if first is not None:
            try:
                data = self._try(first, bits)
            except PropError:
                if counts:
                    raise
                data = None  # a damaged stand-in: it was tried only for the time it takes
            found = (first, data) if counts and data is not None else None
        for i in rest:
            data = self._try(i, bits)
            if data is not None and found is None:
                found = i, data
        return found

    def open(self, bits: np.ndarray) -> Opened | None:
        """The user's payload if ``bits`` opens one of the records, else None (a wrong key), found as
        ``find`` finds it. ``changed`` says what differs from what the record was enrolled in: the caller
        decides (``modes``)."""
        found = self.find(bits)
        if found is None:
            return None
        i, data = found
        tensors, meta = decode_payload(unpad(data) if self.enrolled else data)
        enrolled = meta.pop(BEHAVIOUR, None)
        version = int(meta.pop(VERSION, 0))
        diff = changed(enrolled or {}, self.behaviour) if self.enrolled else []
        return Opened(
            self.records[i].id, Payload.from_tensors(self.spec, tensors).eval(), meta, diff, version
        )

    def holds(self, bits: np.ndarray) -> bool:
        """Whether ``bits`` opens a record here, or a record is filed under its name."""
        return self.index.holds(bits) or self.find(bits) is not None


READ_KEPT = 16  # record files a SealedState keeps in memory once read


def _name(record: SealedRecord | dict) -> str | None:
    return record.get(LOOKUP) if isinstance(record, dict) else record.lookup


def record_file(record_id: str) -> str:
    return f"{C.RECORDS_DIR}/{record_id}{C.RECORD_SUFFIX}"


def record_entry(rec: SealedRecord) -> dict:
    """A record's manifest entry: where its file is and what opening it needs besides the key (format 6:
    and the name it is filed under)."""
    entry = {
        "id": rec.id,
        "file": record_file(rec.id),
        "salt": rec.salt.hex(),
        "nonce": rec.nonce.hex(),
        "sha256": hashlib.sha256(rec.ciphertext).hexdigest(),
    }
    if rec.lookup is not None:
        entry[LOOKUP] = rec.lookup
    return entry


def _bad(path: Path, what: str) -> PropError:
    return PropError(f"bundle {path}: {what}", "restore the bundle from a trusted copy")


def _check_present(path: Path, entries: list[dict]) -> None:
    """Every record the manifest lists has its file in ``users/`` (one listing of the folder)."""
    try:
        with os.scandir(path / C.RECORDS_DIR) as it:
            there = {f"{C.RECORDS_DIR}/{e.name}" for e in it if e.is_file(follow_symlinks=False)}
    except (FileNotFoundError, NotADirectoryError):
        there = set()
    missing = [e["file"] for e in entries if e["file"] not in there]  # the schema: users/<file name>
    if missing:  # e.g. the folder was copied without users/: say how much is gone, not only the first
        shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
        raise PropError(
            f"bundle {path} is incomplete: {len(missing)} of {len(entries)} user "
            f"record{'' if len(entries) == 1 else 's'} missing ({shown})",
            f"copy the whole bundle folder, {C.RECORDS_DIR}/ included, or restore it from a trusted copy",
        )


def read_record(path: Path, entry: dict) -> bytes:
    """A record's ciphertext, checked against its sha256 in the manifest; read from a descriptor of the
    bundle folder, no part below it followed if it is a link (``files.read``)."""
    try:
        data = read(path, entry["file"])
    except FileNotFoundError:
        raise _bad(path, f"{entry['file']} is missing") from None
    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise _bad(path, f"{entry['file']} does not match its sha256 in {C.MANIFEST} (modified or corrupt)")
    return data


def check_records(path: Path, manifest: dict) -> None:
    """Every record of a sealed bundle present and matching its sha256 (inspect, verify, push)."""
    entries = manifest[C.M_RECORDS]
    _check_present(path, entries)
    for entry in entries:
        if sha256_inside(path, entry["file"]) != entry["sha256"]:
            raise _bad(
                path, f"{entry['file']} does not match its sha256 in {C.MANIFEST} (modified or corrupt)"
            )


def load_state(path: Path, manifest: dict) -> SealedState:
    """The records of a sealed bundle, each present. Format 6 (records filed by name): each file is read
    and checked against its sha256 when a key tries it, one per key; before: all read and checked now
    (every key tries every record)."""
    spec = PayloadSpec.from_dict(manifest[C.M_PAYLOAD])
    entries = manifest[C.M_RECORDS]
    _check_present(path, entries)
    if salt_of(manifest) is not None:
        return SealedState(manifest, spec, Listed(entries), path)
    records = [
        SealedRecord(e["id"], bytes.fromhex(e["salt"]), bytes.fromhex(e["nonce"]), read_record(path, e))
        for e in entries
    ]
    return SealedState(manifest, spec, records, path)


class Listed(Sequence[SealedRecord]):
    """The records of manifest entries, each made when asked for, its ciphertext left in its file (None):
    a key asks for one of 10,000."""

    def __init__(self, entries: list[dict]) -> None:
        self.entries = entries

    def __len__(self) -> int:
        return len(self.entries)

    @overload
    def __getitem__(self, i: int) -> SealedRecord: ...
    @overload
    def __getitem__(self, i: slice) -> list[SealedRecord]: ...
    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(len(self))[i]]
        e = self.entries[i]
        return SealedRecord(e["id"], bytes.fromhex(e["salt"]), bytes.fromhex(e["nonce"]), None, e.get(LOOKUP))


def seal_payload(manifest: dict, private: dict, payload: Payload, bits: np.ndarray) -> SealedRecord:
    """Encrypt one user's payload (and ``private``: their metrics and settings, sealed too) for their key.
    Format 4: with the bundle's behaviour (the user's enrolment), padded to a fixed bucket of sizes;
    format 5: and the bundle version of ``manifest``, the manifest the record is written in; format 6:
    filed under the key's lookup name."""
    if not enrolled_records(manifest):
        return seal(encode_payload(payload.tensors(), private), bits, lambda rid: binding(manifest, rid))
    sealed_meta = {**private, BEHAVIOUR: behaviour(manifest)}
    if C.M_BUNDLE_VERSION in manifest:
        sealed_meta[VERSION] = manifest[C.M_BUNDLE_VERSION]
    plaintext = pad(encode_payload(payload.tensors(), sealed_meta))
    return seal(plaintext, bits, lambda rid: record_ad(manifest, rid), salt_of(manifest))


def write_record(folder: Path, rec: SealedRecord) -> None:
    """Write a record's ciphertext under ``folder``, never through a link (``users/`` linked elsewhere)."""
    write_inside(folder, record_file(rec.id), rec.ciphertext)


def with_records(manifest: dict, add: list[SealedRecord], drop: list[str]) -> dict:
    """The manifest with records added and removed (and the removed users' public metrics, which format
    2-3 bundles kept), not written."""
    new = dict(manifest)
    new[C.M_RECORDS] = [e for e in manifest[C.M_RECORDS] if e["id"] not in drop] + [
        record_entry(rec) for rec in add
    ]
    if new.get(C.M_METRICS):
        users = [u for u in new[C.M_METRICS].get("users", []) if u.get("record") not in drop]
        new[C.M_METRICS] = {**new[C.M_METRICS], "users": users}
    return new


def rewrite_records(bundle: Path, old: dict, new: dict, add: list[SealedRecord]) -> dict:
    """Commit ``new`` (from ``with_records``) to a sealed bundle in place, as the bundle's next version
    (records in ``add`` sealed against ``next_version(old)``): the added records' files first, then the
    manifest, swapped atomically, then the dropped records' files are deleted; this machine remembers
    the version and the records removed (``rollback``). An interruption leaves a bundle that loads.
    Under the bundle's write lock (``files.bundle_lock``; the caller should hold it from before it read
    ``old``), every file written and deleted through the folder it locked, never through a link."""
    kept = {e["id"] for e in new[C.M_RECORDS]}
    dropped = [e for e in old[C.M_RECORDS] if e["id"] not in kept]
    if C.M_BUNDLE_VERSION in old:
        new = {**new, C.M_BUNDLE_VERSION: next_version(old, str(bundle))[C.M_BUNDLE_VERSION]}
    new = restamp(new)
    with bundle_lock(bundle):
        for e in dropped:
            no_links(bundle, e["file"])  # before anything is written
        for rec in add:
            put(bundle, record_file(rec.id), rec.ciphertext)
        put(bundle, C.MANIFEST, dump_json(new).encode(), output=True)
        added = {rec.id: bundle_version(new) for rec in add}
        rollback.wrote(new, users=added, removed=[e["id"] for e in dropped])
        for e in dropped:
            delete(bundle, e["file"])
    return new


def copy_records(src: Path, dst: Path, manifest: dict) -> None:
    """Copy a sealed bundle's record files (for exports: the ONNX runtime opens them too): the bytes read
    (no link followed) and checked against their sha256 are the bytes written."""
    (dst / C.RECORDS_DIR).mkdir(parents=True, exist_ok=True)
    for e in manifest[C.M_RECORDS]:
        (dst / e["file"]).write_bytes(read_record(src, e))


def record_to_remove(
    manifest: dict, state: SealedState, bits: np.ndarray | None, record: str | None, where: str
) -> str:
    """Which record `prop remove-user` deletes, by the rules of ownership: exactly one of the user's key
    (it must open the record it removes) and a record id (``record``: for a bundle's maintainer when a
    user lost their key; whoever can write the files can delete a record anyway, and no one can add or
    change one without its key); never the last user (a sealed bundle keeps at least one)."""
    if (bits is None) == (record is None):
        raise PropError("remove-user needs exactly one of --key-file/--passphrase and --record", "pass one")
    ids = [e["id"] for e in manifest[C.M_RECORDS]]
    if bits is not None:
        opened = state.open(bits)
        if opened is None:
            raise PropError(
                f"the key is enrolled in nothing in {where} (it opens no user's record)",
                "pass the key of the user to remove, or --record ID",
            )
        record = opened.record_id
    elif record not in ids:
        raise PropError(f"--record {record!r} is not in {where}", "records: " + (", ".join(ids) or "none"))
    if len(ids) == 1:
        raise PropError(
            f"{record} is the last user of {where}: a sealed bundle keeps at least one",
            "delete the bundle folder instead",
        )
    return record


def check_new_key(state: SealedState, bits: np.ndarray) -> None:
    """A new user's key must not open a user of the bundle already, nor have its name taken (`prop
    add-user`)."""
    if state.holds(bits):
        raise PropError(
            "this key already opens a user of the bundle",
            "use prop remove-user first to replace that user, or give the new user their own key",
        )
