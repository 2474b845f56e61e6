"""`prop inspect BUNDLE`: what a bundle is, read from its manifest as data (nothing it names is imported,
no model is built, no key is needed): mode, users, keyed layers, the recorded audit, whether a signature
is present (not whether it verifies: that needs the publisher's key, ``prop verify``).

The manifest's schema, format version and digest are checked (``read_manifest``) and every listed file
against its sha256 (``check_files``, and a sealed bundle's user records: ``load_state``), so what this says
is what the bundle holds; a bundle missing any of them is a PropError naming how many. Key material is never
in a bundle, so nothing here can print it.
"""

from __future__ import annotations

from pathlib import Path

from prop_cli import constants as C

from .manifest import bundle_version
from .modes import mode_of
from .read import check_files, read_manifest
from .records import check_records

SIGNATURE_UNVERIFIED = f"present, not verified ({C.SIGNATURE_FILE}: prop verify checks it)"


def _audit(m: dict) -> dict | None:
    """The summary `prop attack --record` stored: when, by which prop, which probes ran (None: a record
    that does not say) and its --max-leak decision. Whether those were the default probes is the
    audit's to say (``api.describe_bundle``)."""
    a = m.get(C.M_AUDIT)
    if not a:
        return None
    leak = a.get("max_leak") or None
    probes = (a.get("settings") or {}).get("probes")
    return {
        "recorded_utc": a.get("recorded_utc"),
        "prop_version": a.get("prop_version"),
        "schema": a.get("schema"),
        "mode": a.get("mode"),
        "probes": list(probes) if isinstance(probes, list) else None,
        "max_leak": None if leak is None else {k: leak.get(k) for k in ("threshold", "passed", "failing")},
    }


def describe_bundle(path: Path) -> dict:
    """The bundle at ``path`` described from its manifest (checked) and its files (hashes checked)."""
    path = Path(path)
    m = read_manifest(path)
    check_files(path, m)
    mode = mode_of(m)
    records = mode.record_files(m)
    if records:
        check_records(path, m)  # the users/ records: present, and each against its sha256
    model = m[C.M_MODEL]
    return {
        "bundle": str(path),
        "format_version": m[C.M_FORMAT],
        "bundle_id": m.get(C.M_BUNDLE_ID),  # format 5 on; None before
        "bundle_version": bundle_version(m),  # 0: written before versions (no rollback protection)
        "prop_version": m.get(C.M_PROP_VERSION),
        "mode": m.get(C.M_MODE, C.MODE_UNSEALED),
        "model": {k: v for k, v in model.items() if k in ("adapter", "type", "arch", "family", "builder")},
        "task": m.get(C.M_TASK),
        "key_bits": m[C.M_KEY]["bits"],
        **mode.facts(m),
        "keyed_layers": [
            {"name": x["name"], "features": x["features"]} for x in m.get(C.M_KEYED_LAYERS, [])
        ],
        "files": len(m[C.M_FILES]) + len(records),  # every one checked
        "audit": _audit(m),
        # Present is all inspect can say: prop verify checks it against the publisher's key.
        "signature": SIGNATURE_UNVERIFIED if (path / C.SIGNATURE_FILE).is_file() else None,
        "onnx_export": (path / C.EXPORT_DIR).is_dir(),
    }
