"""The bundle manifest: its schema (one table), its digest, and the one function that reads it.

Every field has a rule: its JSON type, its range, and whether it is required (in which mode). Unknown
fields are refused, so a typo or a flipped bit in a key name cannot pass as "absent". Format 3 adds
``manifest_sha256``: the sha256 of the canonical JSON of every other field, and the file must be exactly
the text prop writes (sorted, indented), so any single flipped bit in ``manifest.json`` is caught, even
one JSON would read back as the same value ("1e-05" -> "1E-05"). Format 1 and 2 manifests have no
digest: they load with only their listed files checked, as before (and a digest, where present, is
always checked: one flipped bit turns version 3 into 2 or 1).

The digest is a corruption check, not a signature: anyone who edits the manifest can recompute it. For
sealed bundles the authenticated cipher's associated data binds the public fields to the user's key.
The rules are written in ``prop_cli.core.rules``' vocabulary; what each adapter's model spec holds
(``model``) is the adapter's own (``Adapter.manifest_fields``), handed in by the adapter registry: the
format names no adapter and imports no model code.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from typing import Any

from prop_cli import constants as C
from prop_cli.config import PAYLOAD_KINDS
from prop_cli.core.rules import (
    DIM,
    MAX_DIM,
    MAX_TEXT,
    MODEL_CHECKS,
    MODEL_FIELDS,
    RECORD,
    SHA256,
    Rule,
    choice,
    hex_string,
    integer,
    list_of,
    number,
    obj,
    optional,
    text,
)
from prop_cli.errors import PropError, brief
from prop_cli.files import dump_json

FIX = "the bundle is damaged or was edited; restore it from a trusted copy or write it again"
# The largest bundle version (issue 42, item 6): far below 2**53, where a JSON reader stops counting
# exactly, so no field can brick a bundle; a write that would pass it is refused before anything is
# written (``next_version``). A trillion writes: no bundle gets there by being written.
MAX_BUNDLE_VERSION = 1 << 40
BUNDLE_ID_BYTES = 16


def file_name(name: str) -> bool:
    """A plain file name inside the bundle folder: no folders, no hidden files, not the manifest."""
    return (
        0 < len(name) <= 255
        and not name.startswith(".")
        and "/" not in name
        and "\\" not in name
        and "\0" not in name
        and name != C.MANIFEST
    )


def bundle_path(name: str) -> bool:
    """A relative path inside the bundle folder (an adapter's files may sit in subfolders): never
    absolute, never through "..", never the manifest."""
    parts = name.split("/")
    return (
        0 < len(name) <= 1024
        and name != C.MANIFEST
        and all(p and p not in (".", "..") and "\\" not in p and "\0" not in p for p in parts)
    )


def record_file(name: str) -> bool:
    """Where a sealed bundle keeps a user's record: users/<plain file name>."""
    folder, sep, leaf = name.partition("/")
    return folder == C.RECORDS_DIR and bool(sep) and file_name(leaf)


RECORD_FILE = Rule((str,), f"a file name in the bundle's {C.RECORDS_DIR}/ folder", record_file)
NAME = text()  # a module path such as "actor.mu.0"
UNSEALED = ("unsealed",)


def _shape_ok(v: Any) -> bool:
    return isinstance(v, list) and 1 <= len(v) <= 16 and all(type(d) is int and 1 <= d <= MAX_DIM for d in v)


# Per-sample input shape: one list, or per named observation feature for policies (LeRobot).
INPUT_SHAPE = Rule(
    (list, dict),
    "a list of 1 to 16 sizes, or an object of feature name -> such a list",
    lambda v: _shape_ok(v) if isinstance(v, list)
    else 1 <= len(v) <= 256 and all(k and len(k) <= MAX_TEXT and _shape_ok(s) for k, s in v.items()),
)  # fmt: skip
SEALED = ("sealed",)

KDF_RECORD = obj({
    "name": choice(("scrypt",)),
    "n": integer(2, 1 << 20),
    "r": integer(1, 64),
    "p": integer(1, 64),
    "salt": hex_string(8, 64),
})  # fmt: skip

# One keyed layer of a sealed payload; a convolution's adds kernel and groups (core.layers.describe_layer).
PAYLOAD_LAYER = obj(
    {
        "name": NAME,
        "in_features": DIM,
        "out_features": DIM,
        "kernel": optional(list_of(DIM, 1, 3)),
        "groups": optional(DIM),
    }
)
# Format 6: the name a record or enrolment is filed under (``lookup``), 16 bytes of HKDF output.
LOOKUP = C.M_LOOKUP
LOOKUP_NAME = hex_string(16, 16)
# The manifest, field by field (keys in prop_cli.constants).
SCHEMA: dict[str, Rule] = {
    C.M_FORMAT: integer(min(C.FORMAT_VERSIONS), max(C.FORMAT_VERSIONS)),
    C.M_PROP_VERSION: text(),
    # Format 5 on (``_cross_check``): which bundle this is, and how many writes it has had.
    C.M_BUNDLE_ID: optional(hex_string(BUNDLE_ID_BYTES, BUNDLE_ID_BYTES)),
    C.M_BUNDLE_VERSION: optional(integer(1, MAX_BUNDLE_VERSION)),
    C.M_MODE: optional(choice(C.MODES)),
    # Each adapter's own fields: its ``manifest_fields``, handed in by the adapter registry (core.rules).
    C.M_MODEL: obj({"adapter": text()}, open=True, variants=("adapter", MODEL_FIELDS)),
    C.M_KEYED_LAYERS: optional(
        list_of(obj({"name": NAME, "features": DIM, C.M_BATCH_AXIS: optional(integer(0, 16))}), 1),
        UNSEALED,
    ),
    C.M_KEY: obj(
        {
            "bits": integer(C.KEY_BITS_MIN, C.KEY_BITS_MAX, 8),
            "encoding": optional(choice(C.KEY_ENCODINGS), UNSEALED),
            "users": optional(integer(1, 1 << 16)),
            "source": optional(choice(("file", "passphrase", "mixed"))),
            "kdf": optional(KDF_RECORD, nullable=True),
        }
    ),  # fmt: skip
    C.M_ENCODER: optional(
        obj(
            {
                "hidden": list_of(DIM, 0, 256),
                "scale": number(0, 1e6, open_lo=True),
                "activation": optional(choice(("tanh",))),
                "output": optional(text()),
            }
        ),
        UNSEALED,
    ),  # fmt: skip
    C.M_CONFIG: optional(RECORD),
    C.M_METRICS: optional(RECORD),
    C.M_TASK: choice(("classification", "regression")),
    C.M_IO: obj({"input_shape": INPUT_SHAPE, "checkpoint": optional(text(nonempty=False))}),
    C.M_FILES: Rule(
        (dict,), "an object of file path -> sha256", values=SHA256, key_ok=bundle_path, min_len=1
    ),
    C.M_AUDIT: optional(RECORD),
    C.M_PAYLOAD: optional(
        obj(
            {
                "kind": choice(PAYLOAD_KINDS),
                "rank": integer(0, MAX_DIM),
                "layers": list_of(PAYLOAD_LAYER, 1),
            }
        ),
        SEALED,
    ),  # fmt: skip
    C.M_RECORDS: optional(
        list_of(
            obj(
                {
                    "id": text(),
                    "file": RECORD_FILE,
                    "salt": hex_string(8, 64),
                    "nonce": hex_string(8, 64),
                    "sha256": SHA256,
                    LOOKUP: optional(LOOKUP_NAME),
                }
            ),
            1,
        ),
        SEALED,
    ),  # fmt: skip
    C.M_ENROLMENTS: optional(
        list_of(
            obj(
                {
                    "salt": hex_string(16, 16),
                    "nonce": hex_string(12, 12),
                    "box": hex_string(16, 1 << 16),
                    LOOKUP: optional(LOOKUP_NAME),
                }
            )
        )
    ),
    C.M_KDF: optional(
        obj(
            {
                "scrypt_salt": hex_string(8, 64),
                "n": integer(2, 1 << 20),
                "r": integer(1, 64),
                "p": integer(1, 64),
            }
        )
    ),  # fmt: skip
}


# ---- the digest -----------------------------------------------------------------------------------


def canonical_json(obj: Any) -> bytes:
    """The one byte form of a JSON value that digests (and a cipher's associated data) are taken over."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()


def digest(obj: dict, key: str = C.M_DIGEST) -> str:
    """sha256 of the canonical JSON of every field but the digest (``key``) itself."""
    return hashlib.sha256(canonical_json({k: v for k, v in obj.items() if k != key})).hexdigest()


def stamp(obj: dict, key: str = C.M_DIGEST) -> dict:
    """``obj`` with its digest (re)computed: what is written, after any change to a field."""
    return {**obj, key: digest(obj, key)}


def restamp(manifest: dict) -> dict:
    """After an edit: the digest recomputed where the manifest has one (older formats stay without)."""
    return stamp(manifest) if C.M_DIGEST in manifest else manifest


# ---- the bundle's identity and version (rollback protection: ``rollback``) ------------------------


def new_identity() -> dict:
    """What personalize writes: a random bundle id (not derived from any key or file) and version 1."""
    return {C.M_BUNDLE_ID: os.urandom(BUNDLE_ID_BYTES).hex(), C.M_BUNDLE_VERSION: 1}


def bundle_version(manifest: dict) -> int:
    """The manifest's bundle version; 0 for a format 1-4 bundle, which has none."""
    return int(manifest.get(C.M_BUNDLE_VERSION, 0))


def next_version(manifest: dict, source: str = "the bundle") -> dict:
    """The manifest of the bundle's next write: its version one higher (a format 1-4 manifest, which has
    none, as it is). Every rewrite of a manifest goes through here; what it seals or enrols for the new
    version (an added record) is sealed against this manifest. A version past ``MAX_BUNDLE_VERSION`` is
    refused in one line (``source``: how it names the bundle), before anything is written."""
    if C.M_BUNDLE_VERSION not in manifest:
        return dict(manifest)
    version = bundle_version(manifest)
    if version >= MAX_BUNDLE_VERSION:
        raise _doc(source, manifest.get(C.M_MODE, "unsealed")).bad(
            C.M_BUNDLE_VERSION,
            f"is {version}, the largest a bundle may have: it cannot be written again (nothing was written)",
            "personalize it again (a new bundle, version 1), or restore it from a trusted copy",
        )
    return {**manifest, C.M_BUNDLE_VERSION: version + 1}


# ---- reading --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Doc:
    """The JSON file being checked: how errors name it, its mode, and the fix they suggest."""

    name: str  # e.g. "bundle out.prop: manifest.json"
    mode: str = "unsealed"
    fix: str = FIX

    def bad(self, where: str, problem: str, fix: str | None = None) -> PropError:
        return PropError(f"{self.name} field '{where}' {problem}", fix or self.fix)


def _shown(value: Any) -> str:
    s = json.dumps(value) if not isinstance(value, float) or math.isfinite(value) else repr(value)
    return s if len(s) <= 40 else s[:37] + "..."


def quoted(value: Any) -> str:
    """A manifest value as one-line errors quote it (JSON, cut short)."""
    return _shown(value)


def _type_ok(rule: Rule, value: Any) -> bool:
    if isinstance(value, bool) and bool not in rule.kind:
        return False  # JSON true is not the integer 1
    return isinstance(value, rule.kind)


def check_value(rule: Rule, value: Any, where: str, doc: Doc) -> None:
    """Check one value against its rule, and its items, entries or fields against theirs."""
    if value is None and rule.nullable:
        return
    if not _type_ok(rule, value) or (rule.ok is not None and not rule.ok(value)):
        want = rule.want + (" or null" if rule.nullable else "")
        raise doc.bad(where, f"must be {want} (found {_shown(value)})")
    if isinstance(value, (list, dict)) and not rule.min_len <= len(value) <= rule.max_len:
        raise doc.bad(where, f"must hold {rule.min_len} to {rule.max_len} items (found {len(value)})")
    if rule.items is not None:
        for i, item in enumerate(value):
            check_value(rule.items, item, f"{where}[{i}]", doc)
    if rule.values is not None:
        for k, v in value.items():
            if rule.key_ok is not None and not rule.key_ok(k):
                raise doc.bad(where, f"has an invalid entry name {_shown(k)}")
            check_value(rule.values, v, f"{where}.{k}", doc)
    if rule.fields is not None:
        fields, known = dict(rule.fields), False
        if rule.variants is not None:
            tag, table = rule.variants
            variant = value.get(tag)
            known = isinstance(variant, str) and variant in table  # a wrong type is reported below
            fields.update(table[variant] if known else {})
        check_fields(fields, value, doc, where, open_=rule.open and not known)


def check_fields(
    fields: dict[str, Rule], value: dict, doc: Doc, where: str = "", open_: bool = False
) -> None:
    """Check an object against its field table: required present, unknown refused, each by its rule."""
    prefix = f"{where}." if where else ""
    for name, rule in fields.items():
        required = rule.required if isinstance(rule.required, bool) else doc.mode in rule.required
        if name not in value:
            if required:
                raise doc.bad(prefix + name, "is missing")
            continue
        check_value(rule, value[name], prefix + name, doc)
    if not open_:
        unknown = sorted(set(value) - set(fields))
        if unknown:
            known = ", ".join(sorted(fields))
            raise doc.bad(
                prefix + str(unknown[0]), f"is not a known field (known: {known})",
                "a newer prop may have written it (upgrade prop), else " + doc.fix,
            )  # fmt: skip


# Where each mode keeps its users' enrolments (format 4 on): an unsealed bundle's enrolments, a sealed
# bundle's records (each carries what its user was enrolled in).
ENROLLED_IN = {C.MODE_UNSEALED: C.M_ENROLMENTS, C.MODE_SEALED: C.M_RECORDS}


def _cross_check(m: dict, doc: Doc) -> None:
    """What one field's rule cannot say: how the fields fit together."""
    needed = (C.BASE_WEIGHTS, C.ENCODER_WEIGHTS) if doc.mode == "unsealed" else (C.BASE_WEIGHTS,)
    for name in needed:
        if name not in m[C.M_FILES]:
            raise doc.bad(f"{C.M_FILES}.{name}", "is missing")
    names = [layer["name"] for layer in m.get(C.M_KEYED_LAYERS, [])]
    if len(set(names)) != len(names):
        raise doc.bad(C.M_KEYED_LAYERS, "names a layer twice")
    key = m[C.M_KEY]
    if key.get("source") in ("passphrase", "mixed") and not key.get("kdf"):
        raise doc.bad(f"{C.M_KEY}.kdf", "is missing (a passphrase key needs its salt)")
    ids = [r["id"] for r in m.get(C.M_RECORDS, [])]
    if len(set(ids)) != len(ids):
        raise doc.bad(C.M_RECORDS, "holds two records with the same id")
    _check_names(m, doc)
    spec = m[C.M_MODEL]
    check = MODEL_CHECKS.get(spec["adapter"])
    wrong = check(spec) if check is not None and spec["adapter"] in MODEL_FIELDS else None
    if wrong is not None:
        raise doc.bad(f"{C.M_MODEL}.{wrong[0]}", wrong[1])
    for field in (C.M_BUNDLE_ID, C.M_BUNDLE_VERSION):
        if m[C.M_FORMAT] >= C.VERSIONED_SINCE and field not in m:
            raise doc.bad(field, "is missing")
        if m[C.M_FORMAT] < C.VERSIONED_SINCE and field in m:
            raise doc.bad(field, f"is not a field of format {m[C.M_FORMAT]} bundles (format 5 on)")
    if m[C.M_FORMAT] >= C.ENROL_SINCE:
        own = ENROLLED_IN[doc.mode]
        if own not in m:
            raise doc.bad(own, "is missing")
        for other in sorted(set(ENROLLED_IN.values()) - {own}):
            if other in m:
                raise doc.bad(other, f"is not a field of {doc.mode} bundles (their users are in {own})")
        checkpoint = m[C.M_IO].get("checkpoint")
        if checkpoint and not checkpoint.startswith("hf://") and ("/" in checkpoint or "\\" in checkpoint):
            raise doc.bad(f"{C.M_IO}.checkpoint", "must be a file name, not a path")


def _check_names(m: dict, doc: Doc) -> None:
    """Lookup names (format 6 on; in an older manifest they are ignored, as a format 5 reader would):
    no name twice in a list (a key opens one entry)."""
    for field in (C.M_RECORDS, C.M_ENROLMENTS):
        names = [e[LOOKUP] for e in m.get(field, []) if LOOKUP in e]
        if len(set(names)) != len(names):
            raise doc.bad(field, "files two entries under the same lookup name")


def _doc(source: str, mode: object = "unsealed") -> Doc:
    return Doc(f"bundle {source}: {C.MANIFEST}", mode if mode in C.MODES else "unsealed")


def field_error(source: str, where: str, problem: str, mode: str = "unsealed") -> PropError:
    """A one-line error naming a field of the manifest of bundle ``source`` (of ``mode``, for the fix it
    names) and what is wrong with it."""
    return _doc(source, mode).bad(where, problem)


def validate(manifest: dict, source: str) -> dict:
    """Check a parsed manifest against ``SCHEMA``; one-line PropError naming the first bad field."""
    doc = _doc(source, manifest.get(C.M_MODE, "unsealed"))
    check_fields(SCHEMA, {k: v for k, v in manifest.items() if k != C.M_DIGEST}, doc)
    _cross_check(manifest, doc)
    return manifest


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    d = dict(pairs)
    if len(d) != len(pairs):
        raise ValueError("a field appears twice")
    return d


def read_json(raw: bytes, name: str, fix: str) -> dict:
    """Bytes -> a JSON object (no field twice), or a one-line PropError naming ``name``."""
    try:
        obj = json.loads(raw.decode("utf-8"), object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise PropError(f"{name} is not valid JSON ({brief(e, 80)})", fix) from None
    if not isinstance(obj, dict):
        raise PropError(f"{name} is not a JSON object", fix)
    return obj


def check_version(obj: dict, key: str, known: tuple[int, ...], doc: Doc) -> int:
    """The format version: too new asks for an upgrade; anything else unknown is damage."""
    version = obj.get(key)
    if isinstance(version, int) and not isinstance(version, bool) and version > max(known):
        raise PropError(
            f"{doc.name} has format version {version}; this prop reads up to {max(known)}",
            "upgrade prop: pip install -U prop-keys",
        )
    check_value(integer(min(known), max(known)), version, key, doc)
    return version


def check_digest(obj: dict, raw: bytes, key: str, doc: Doc) -> None:
    """The stored digest matches the fields, and the file is exactly the text prop writes."""
    stored = obj.get(key)
    if not isinstance(stored, str):
        raise doc.bad(key, "is missing" if stored is None else "must be a sha256 in hex")
    if stored != digest(obj, key) or raw != dump_json(obj).encode():
        raise PropError(f"{doc.name} does not match its {key} (modified or corrupt)", doc.fix)


def parse(raw: bytes, source: str) -> dict:
    """``manifest.json``'s bytes -> the checked manifest: JSON, format version, digest, schema."""
    doc = _doc(source)
    manifest = read_json(raw, doc.name, FIX)
    version = check_version(manifest, C.M_FORMAT, C.FORMAT_VERSIONS, doc)
    # A digest is checked wherever there is one: a flipped bit can turn version 3 into 2 or 1.
    if version >= C.DIGEST_SINCE or C.M_DIGEST in manifest:
        check_digest(manifest, raw, C.M_DIGEST, doc)
    return validate(manifest, source)
