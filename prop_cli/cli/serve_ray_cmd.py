"""`prop serve-ray`: `prop serve` as a Ray Serve application, users routed to the replica holding them."""

from __future__ import annotations

import json
from typing import Annotated

from prop_cli.constants import SERVE_BATCH_WINDOW_MS, SERVE_HOST, SERVE_MAX_BATCH, SERVE_PORT

from .common import err
from .options import AllowRollback, AllowUnenrolledKey, BundleArch, BundleArg, TrustRemoteCode, opt
from .serve_cmd import BatchWindow, Host, JsonLines, MaxBatch, TlsCert, TlsKey

Port = Annotated[int, opt("--port", "Port of Ray Serve's HTTP proxy.", min=1, max=65535)]
Replicas = Annotated[int, opt("--replicas", "Policy replicas, each with the bundle loaded.", min=1)]
UsersPerReplica = Annotated[
    int, opt("--users-per-replica", "Decrypted users a replica keeps (least recently used go).", min=1)
]
Address = Annotated[
    str | None,
    opt("--address", "A running Ray cluster (`ray start --head`; 'auto' finds it); default: a local one."),
]
NumCpus = Annotated[int | None, opt("--num-cpus", "CPUs of the local Ray instance (default: all).", min=1)]
ReplicaCpus = Annotated[float, opt("--replica-cpus", "CPUs Ray reserves for each replica.", min=0)]


def serve_ray(
    bundle: BundleArg, replicas: Replicas = 2, users_per_replica: UsersPerReplica = 64,
    address: Address = None, num_cpus: NumCpus = None, replica_cpus: ReplicaCpus = 1.0,
    host: Host = SERVE_HOST, port: Port = SERVE_PORT, tls_cert: TlsCert = None, tls_key: TlsKey = None,
    allow_unenrolled_key: AllowUnenrolledKey = False, batch_window_ms: BatchWindow = SERVE_BATCH_WINDOW_MS,
    max_batch: MaxBatch = SERVE_MAX_BATCH, trust_remote_code: TrustRemoteCode = False,
    arch: BundleArch = None, allow_rollback: AllowRollback = False, as_json: JsonLines = False,
) -> None:  # fmt: skip
    """Serve BUNDLE (an array model, or a LeRobot ACT, SmolVLA or pi0 policy) to openpi-client on Ray
    Serve until Ctrl-C or SIGTERM: each connection's key (Authorization: Api-Key <key hex>) is routed to a
    replica that already holds that user (Ray Serve's model multiplexing, by an id derived from the key);
    no key, the base."""
    from prop_cli.api import serve_ray as run

    def ready(url: str) -> None:
        print(json.dumps({"url": url, "bundle": str(bundle), "replicas": replicas}) if as_json else url,
              flush=True)  # fmt: skip
        err.print(f"serving {bundle} on Ray Serve at {url}, {replicas} replicas (Ctrl-C or SIGTERM stops it)")

    run(
        bundle, replicas=replicas, users_per_replica=users_per_replica, address=address, num_cpus=num_cpus,
        replica_cpus=replica_cpus, host=host, port=port, tls_cert=tls_cert, tls_key=tls_key,
        allow_unenrolled_key=allow_unenrolled_key, batch_window_ms=batch_window_ms, max_batch=max_batch,
        trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback, ready=ready,
    )  # fmt: skip
    err.print("stopped")
