"""`prop serve`: a bundle as a policy server for openpi-client (openpi's websocket protocol)."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Annotated

from prop_cli.constants import (
    SERVE_BATCH_WINDOW_MS,
    SERVE_CACHE_MB,
    SERVE_HOST,
    SERVE_MAX_BATCH,
    SERVE_MAX_CONNECTIONS,
    SERVE_PORT,
)

from .common import err
from .options import AllowRollback, AllowUnenrolledKey, BundleArch, BundleArg, TrustRemoteCode, opt

Host = Annotated[
    str, opt("--host", "Address to listen on; anything but the loopback needs --tls-cert/--tls-key.")
]
Port = Annotated[int, opt("--port", "Port to listen on (0: a free one, printed).", min=0, max=65535)]
TlsCert = Annotated[Path | None, opt("--tls-cert", "PEM certificate: serve wss (needed off the loopback).")]
TlsKey = Annotated[Path | None, opt("--tls-key", "PEM private key of --tls-cert.")]
JsonLines = Annotated[
    bool, opt("--json", "Print JSON lines: the url and bundle once listening, the connections when stopped.")
]
MaxConnections = Annotated[
    int, opt("--max-connections", "Connections open at once; more are closed (try again later).", min=1)
]
BatchWindow = Annotated[
    float,
    opt("--batch-window-ms", "Requests (any users) arriving within this window run as one forward.", min=0),
]
MaxBatch = Annotated[int, opt("--max-batch", "Observations per forward at most.", min=1)]
BatchNoKey = Annotated[
    bool,
    opt(
        "--batch-no-key",
        "No-key requests share the batch's forward: faster, but within float rounding "
        "(~1e-7) of the original instead of bit for bit (default: each runs alone).",
    ),
]
CacheMb = Annotated[
    float, opt("--cache-mb", "Memory for decrypted users' payloads kept between connections (LRU).", min=0)
]


def serve(
    bundle: BundleArg, host: Host = SERVE_HOST, port: Port = SERVE_PORT, tls_cert: TlsCert = None,
    tls_key: TlsKey = None, allow_unenrolled_key: AllowUnenrolledKey = False,
    max_connections: MaxConnections = SERVE_MAX_CONNECTIONS, trust_remote_code: TrustRemoteCode = False,
    arch: BundleArch = None, allow_rollback: AllowRollback = False, as_json: JsonLines = False,
    batch_window_ms: BatchWindow = SERVE_BATCH_WINDOW_MS, max_batch: MaxBatch = SERVE_MAX_BATCH,
    cache_mb: CacheMb = SERVE_CACHE_MB, batch_no_key: BatchNoKey = False,
) -> None:  # fmt: skip
    """Serve BUNDLE to openpi-client's WebsocketClientPolicy until Ctrl-C or SIGTERM: each connection's key
    (Authorization: Api-Key <key file bytes in hex>) runs its holder's behaviour; no key, the base."""
    from prop_cli.api import serve_bundle

    handler = logging.StreamHandler(sys.stderr)  # one line per connection, on stderr; never the key
    handler.setFormatter(logging.Formatter("prop serve: %(message)s"))
    log = logging.getLogger("prop.serve")
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False

    def ready(url: str) -> None:
        # The result, on stdout as soon as it is known: where clients connect (a server runs until stopped).
        print(json.dumps({"url": url, "bundle": str(bundle)}) if as_json else url, flush=True)
        err.print(f"serving {bundle} on {url} (Ctrl-C or SIGTERM stops it)")

    try:
        served = serve_bundle(
            bundle, host=host, port=port, tls_cert=tls_cert, tls_key=tls_key,
            allow_unenrolled_key=allow_unenrolled_key, max_connections=max_connections,
            trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback, ready=ready,
            batch_window_ms=batch_window_ms, max_batch=max_batch, cache_mb=cache_mb,
            batch_no_key=batch_no_key,
        )  # fmt: skip
    finally:
        log.removeHandler(handler)
    if as_json:
        print(json.dumps({"connections": served}), flush=True)
    err.print(f"stopped after {served} connection{'s' if served != 1 else ''}")
