"""Key enrolment: a key authenticates what it unlocks.

When a user is enrolled (``prop personalize``, ``prop add-user``, ``prop enrol``), the bundle gets an
enrolment for their key: AES-256-GCM under HKDF-SHA256(key bytes, a fresh salt, ``cipher.ENROL_INFO``)
whose plaintext is the bundle's **behaviour**: the digests of everything that shapes what a key runs
(``behaviour``: the model spec, mode, task, input shape, key layout, keyed layers, encoder or payload
layout, and the sha256 of every file the manifest lists: base weights, encoder, LeRobot
processors...). With a key, prop runs only what that key's holder enrolled:

- an enrolment opens and its behaviour is the bundle's current one: the key's behaviour runs;
- one opens but the behaviour differs: the bundle changed since this key was enrolled, and nothing
  runs (``check``);
- none opens: the key is enrolled in nothing: refused, unless the caller allows it and the bundle's
  base runs (``run.policy.key_opens_nothing``).

Unsealed bundles keep one enrolment per user in the manifest (``enrolments``); a sealed record carries
the behaviour inside its own plaintext (``records``), so it is its user's enrolment. Trying a key costs
one HKDF and one GCM open per enrolment without a lookup name (format 1-5), the cost of the sealed
records' trial decryption; since format 6 each enrolment is filed under its key's name (``lookup``) and
a key opens one. An unsealed bundle's encoder already answers any key, so an enrolment reveals no more
than it does.

Format 5 binds the bundle's identity and version too: the bundle id is part of the behaviour (a
record or enrolment moved from another bundle is "changed"), and each enrolment carries the bundle
version it was written in and a random enrolment id that re-enrolling the same key keeps (``ID``,
``VERSION``): what ``rollback`` compares with the versions this machine has seen.
"""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from prop_cli import constants as C
from prop_cli.errors import PropError

from .cipher import ENROL_INFO, decrypt, encrypt, lookup_name, pad, unpad
from .lookup import LOOKUP, Index, salt_of
from .manifest import canonical_json

ENROL_AD = b"prop/enrol/v1"
ENROL_BUCKET = 1024  # enrolment plaintexts are padded to a multiple of this
FILE = "file "  # behaviour entries of listed files: "file base.safetensors"
ID = "id"  # format 5 enrolments: a random id of the user's enrolment, kept when the key re-enrols
VERSION = "version"  # format 5 enrolments and records: the bundle version they were written in
ID_BYTES = 8
BUNDLE_ID = "bundle id"  # the behaviour entry of a format 5 bundle's id


def _sha(value) -> str:
    return hashlib.sha256(canonical_json(value)).hexdigest()


def behaviour(manifest: dict) -> dict[str, str]:
    """What shapes the behaviour a key runs, as named digests (the enrolled plaintext). Not in it: what
    running does not read (config, metrics, the audit summary, io.checkpoint, the records list, the
    format version, the bundle version: each enrolment carries its own), so add-user, remove-user and attack
    --record leave enrolments valid. In it since format 5: the bundle id."""
    key = manifest[C.M_KEY]
    parts = {
        "mode": manifest.get(C.M_MODE, C.MODE_UNSEALED),
        "model": manifest[C.M_MODEL],
        "task": manifest[C.M_TASK],
        "input shape": manifest[C.M_IO]["input_shape"],
        "key": {"bits": key["bits"], "encoding": key.get("encoding"), "kdf": key.get("kdf")},
        "keyed layers": manifest.get(C.M_KEYED_LAYERS),
        "encoder": manifest.get(C.M_ENCODER),
        "payload": manifest.get(C.M_PAYLOAD),
    }
    if C.M_BUNDLE_ID in manifest:  # format 5: enrolled in this bundle, not a copy of its files elsewhere
        parts[BUNDLE_ID] = manifest[C.M_BUNDLE_ID]
    out = {name: _sha(value) for name, value in parts.items()}
    out.update({FILE + name: digest for name, digest in manifest[C.M_FILES].items()})
    return out


def changed(enrolled: dict, current: dict) -> list[str]:
    """The parts that differ between an enrolled behaviour and the current one (file names plain). A
    format 4 enrolment, which `prop enrol` keeps when it makes the bundle format 5, predates bundle ids:
    it is not "changed" for want of one (a format 5 enrolment in a bundle without its id is)."""
    names = sorted(
        n
        for n in set(enrolled) | set(current)
        if enrolled.get(n) != current.get(n) and (n != BUNDLE_ID or n in enrolled)
    )
    return [n[len(FILE) :] if n.startswith(FILE) else n for n in names]


def changed_error(where: str, parts: list[str], fix: str | None = None) -> PropError:
    shown = ", ".join(parts[:6]) + (f" and {len(parts) - 6} more" if len(parts) > 6 else "")
    return PropError(
        f"{where} changed since this key was enrolled ({shown} differ); nothing ran",
        fix or "get the bundle again from whoever you trust, or run it without your key",
    )


def enrolment(bits: np.ndarray, what: dict, bundle_id: str | None = None) -> dict:
    """One user's enrolment entry: ``what`` (JSON) sealed under their key, padded to a fixed size;
    ``bundle_id`` (format 6): filed under the key's lookup name in that bundle (``lookup``)."""
    body = pad(json.dumps(what, sort_keys=True).encode(), ENROL_BUCKET)
    salt, nonce, box = encrypt(body, np.asarray(bits, np.uint8), ENROL_AD, ENROL_INFO)
    entry = {"salt": salt.hex(), "nonce": nonce.hex(), "box": box.hex()}
    if bundle_id is not None:
        entry[LOOKUP] = lookup_name(bits, bundle_id)
    return entry


def _open_one(e: dict, bits: np.ndarray) -> bytes | None:
    return decrypt(bytes.fromhex(e["salt"]), bytes.fromhex(e["nonce"]), bytes.fromhex(e["box"]), bits,
                   ENROL_AD, ENROL_INFO)  # fmt: skip


def _find(entries: list[dict], bits: np.ndarray, index: Index | None) -> tuple[int, bytes] | None:
    """(position, plaintext) of the entry ``bits`` opens, or None. The same work for every key
    (``lookup.Index.tries``): the entry filed under its name (or a stand-in that cannot count), and
    every entry without a name, whichever opens. ``index`` None: every entry is tried."""
    bits = np.asarray(bits, np.uint8)
    index = index or Index([None] * len(entries), None)
    first, counts, rest = index.tries(bits)
    found = None
    if first is not None:
        data = _open_one(entries[first], bits)
        found = (first, data) if counts and data is not None else None
    for i in rest:
        data = _open_one(entries[i], bits)
        found = (i, data) if found is None and data is not None else found
    return found


def open_enrolment(entries: list[dict], bits: np.ndarray, index: Index | None = None) -> dict | None:
    """What the entry ``bits`` opens was enrolled with, or None (enrolled in nothing). ``index``: where
    ``entries`` are filed (``lookup.Index.of``; None: every entry is tried). The time says nothing of
    which entry opens."""
    found = _find(entries, bits, index)
    return None if found is None else json.loads(unpad(found[1]))


def split(
    entries: list[dict], bits: np.ndarray, index: Index | None = None
) -> tuple[list[dict], dict | None]:
    """(the entries ``bits`` does not open, what the one it opens holds or None)."""
    found = _find(entries, bits, index)
    if found is None:
        return list(entries), None
    return [e for i, e in enumerate(entries) if i != found[0]], json.loads(unpad(found[1]))


def new_id() -> str:
    """A fresh enrolment id: random, not derived from the key."""
    return os.urandom(ID_BYTES).hex()


def enrol(manifest: dict, keys: list[np.ndarray], ids: list[str | None] | None = None) -> list[dict]:
    """Enrolments of ``keys`` in the bundle ``manifest`` describes (its files already hashed). Format 5:
    each with the manifest's bundle version and an enrolment id (``ids``: an id to keep per key, None:
    a new one); format 6: filed under the key's lookup name."""
    now = behaviour(manifest)
    if C.M_BUNDLE_VERSION not in manifest:
        return [enrolment(k, {"behaviour": now}) for k in keys]
    ids = ids or [None] * len(keys)
    version, salt = manifest[C.M_BUNDLE_VERSION], salt_of(manifest)
    return [
        enrolment(k, {"behaviour": now, ID: i or new_id(), VERSION: version}, salt) for k, i in zip(keys, ids)
    ]


def check(
    entries: list[dict], bits: np.ndarray, current: dict, where: str, index: Index | None = None
) -> dict | None:
    """What ``bits`` opens if it is enrolled in the bundle as it is now (its enrolment's plaintext); None
    if enrolled in nothing; a PropError ("changed since this key was enrolled") if it was enrolled in
    something else. ``index``: as ``open_enrolment``."""
    opened = open_enrolment(entries, bits, index)
    if opened is None:
        return None
    diff = changed(opened.get("behaviour", {}), current)
    if diff:
        raise changed_error(where, diff)
    return opened
