"""The routing id of a key: what `prop serve-ray` routes a user's requests by (Ray Serve's multiplexed model
id), so they reach a replica that already holds that user's decrypted payload.

A routing id is not secret: Ray's routers, its controller and its logs see it (``ray_app``). It is 16
bytes of HKDF-SHA256 of the key bytes, salted with the bundle id, under its own label ``prop/serve/route/v1``:
a pseudo-random function of the key, so without the key it says nothing of it; never the key, nor a plain
hash of it (which anyone could test guesses against without the bundle), nor the bundle's own lookup name
(``bundle.lookup``), so a routing id seen in a log does not point at a record of the bundle. Under another
bundle id the same key routes under an unrelated id. A bundle older than format 5 has no id: its manifest's
SHA-256 salts instead.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from prop_cli import constants as C

ROUTE_INFO = b"prop/serve/route/v1"
ROUTE_BYTES = 16
NO_KEY = ""  # no key: not multiplexed (any replica runs the base)


def route_salt(manifest: dict) -> bytes:
    """What routing ids are derived under for this bundle: its id, or its manifest's SHA-256 without one."""
    bundle_id = manifest.get(C.M_BUNDLE_ID)
    if isinstance(bundle_id, str) and bundle_id:
        return bytes.fromhex(bundle_id)
    return hashlib.sha256(json.dumps(manifest, sort_keys=True, default=str).encode()).digest()


def routing_id(bits: np.ndarray | None, salt: bytes) -> str:
    """The multiplexed model id ``bits`` is routed by (hex); ``NO_KEY`` for no key."""
    if bits is None:
        return NO_KEY
    data = np.packbits(np.asarray(bits, dtype=np.uint8)).tobytes()
    kdf = HKDF(algorithm=hashes.SHA256(), length=ROUTE_BYTES, salt=salt, info=ROUTE_INFO)
    return kdf.derive(data).hex()
