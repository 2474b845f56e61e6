"""`prop serve-ray`: the `prop serve` policy server as a Ray Serve application, past one machine.

Two deployments (docs/serving.md, "Past one machine"):

- ``Gateway`` (the ingress, behind Ray Serve's HTTP proxy): speaks openpi's websocket protocol as `prop
  serve` does, so ``openpi_client.websocket_client_policy.WebsocketClientPolicy`` connects unchanged. It
  reads the connection's key once (``Authorization: Api-Key <key hex>``), computes the key's **routing
  id** (``route``: HKDF of the key under the bundle id; never the key or a plain hash of it), and hands
  each message to the policy deployment under that id as Ray Serve's multiplexed model id.
- ``PolicyReplica`` (``--replicas`` of them): each loads the bundle once. Ray Serve's model multiplexing
  routes a routing id to a replica that already holds it (``serve.multiplexed``); that replica keeps the
  user's checked, decrypted behaviour in the id's slot (prop's ``BehaviourCache``, found by an HMAC of the
  key: a request whose key is not the one that filled the slot is checked again, so a forged routing id
  opens nothing). A replica keeps at most ``--users-per-replica`` users; the least recently used go first.
  Within a replica, requests of any users that arrive within ``--batch-window-ms`` run as one forward of
  the base (``batcher``, ``rows``), as in `prop serve`.

The key crosses from the gateway to a replica inside each request (Ray's RPC between the two actors);
see docs/serving.md for what that means on a cluster.

A LeRobot policy whose chunk needs the frame alone (ACT, SmolVLA, pi0: ``chunks.batchable``) is served as
`prop serve` serves it (``ChunkRunner``: users' frames share forwards, a no-key frame runs alone, the
original's chunk bit for bit). Its episode state per connection is two numbers: the episode's seed and the
calls made in it, which seed each call's noise (``Controller.call_noise_seed``); the client takes the
whole chunk per infer (openpi's ActionChunkBroker), so the replica's action queues are never used. The
gateway keeps them with the connection and sends them with each request; the replica answers with them
advanced (a chunk: one call more; ``{"reset": True, "seed": s}``: ``(s, 0)``). So a connection's requests
may land on any replica (a user evicted and reloaded elsewhere, a replica lost) and its episode goes on,
and one connection's reset touches no other's. A policy that keeps state on its module between calls
(Diffusion's observation history, ACT with temporal ensembling) would have to pin each connection to one
replica: refused, `prop serve` serves it.

Imported only by `prop serve-ray` and Ray (``serve run prop_cli.serve.ray_app:build bundle=...``): the
default install does not need ray (the ``ray`` extra).
"""

# No `from __future__ import annotations` here: Ray Serve's class-based FastAPI routes rewrite the
# endpoint's signature, and a string annotation ("WebSocket") would no longer resolve (a 403 on connect).
import asyncio
import contextlib
import logging
import os
import signal
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from ray import serve

from prop_cli import constants as C
from prop_cli.bundle import Bundle, load_bundle
from prop_cli.core.key_files import key_from_text
from prop_cli.errors import PropError, brief

from .batcher import Batcher
from .cache import BehaviourCache
from .route import NO_KEY, route_salt, routing_id
from .rows import run_requests
from .server import (
    CLOSE_ERROR,
    CLOSE_POLICY,
    RESET,
    SCHEME,
    Backoff,
    bundle_stamp,
    check_batching,
    check_reset,
    server_metadata,
)
from .sessions import Session, any_replica_answers, chunk_runner, payload_table
from .wire import WireError, packb, unpackb

LOG = logging.getLogger("prop.serve")
APP_NAME = "prop"
CLOSE_TOO_BIG = 1009  # RFC 6455: message too big
USERS_PER_REPLICA = 64  # decrypted users a replica keeps (Ray Serve's max_num_models_per_replica)
# Any one user's slot holds one behaviour: no cap of its own (the replica's cap is in users).
_SLOT_BYTES = 2**62
# A connection's episode state, kept by the gateway: (the episode's seed, the calls made in it).
Episode = tuple[int, int]
NEW_EPISODE: Episode = (0, 0)


def check_servable(bundle: Bundle) -> None:
    """An array model, or a LeRobot policy whose chunk needs the frame alone: its episode state is then
    the gateway's (``Episode``), so any replica can answer a connection. A policy with state on its module
    between calls would need each connection pinned to one replica's module: refused."""
    if not any_replica_answers(bundle):
        kind = getattr(bundle.loaded.policy.config, "type", "LeRobot")
        raise PropError(
            f"the {kind} policy in {bundle.path} keeps state on its module between calls (an observation "
            "history, or one action at a time); prop serve-ray serves those whose chunk needs the frame "
            "alone (ACT, SmolVLA, pi0)",
            "serve it with prop serve",
        )


def close_reason(text: str) -> str:
    """A close reason: RFC 6455 allows 123 bytes."""
    return text.encode()[:120].decode(errors="ignore")


class PolicyReplica:
    """One replica: the bundle, a slot per routing id (multiplexed), one batcher for all its users."""

    def __init__(self, bundle_path: str, options: dict) -> None:
        self.path = Path(bundle_path)
        self.bundle = load_bundle(
            self.path, trust_remote_code=options.get("trust_remote_code", False), arch=options.get("arch"),
            allow_rollback=options.get("allow_rollback", False),
        )  # fmt: skip
        check_servable(self.bundle)
        self.stamp = bundle_stamp(self.path)
        self.allow = bool(options.get("allow_unenrolled", False))
        self.bits = int(self.bundle.manifest[C.M_KEY]["bits"])
        self.salt = route_salt(self.bundle.manifest)
        self.replica = serve.get_replica_context().replica_id.unique_id
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="prop-serve-ray")
        module, keyed = self.bundle.loaded.module.eval(), self.bundle.mode.keyed
        window = float(options.get("batch_window_ms", C.SERVE_BATCH_WINDOW_MS)) / 1000
        # A LeRobot policy: `prop serve`'s runner (users' frames in one forward, a no-key frame alone).
        self.runner = chunk_runner(self.bundle, payload_table(self.bundle))
        run = self.runner.run if self.runner is not None else (
            lambda requests: run_requests(module, keyed, requests)
        )  # fmt: skip
        self.batcher = Batcher(run, self.pool, window, int(options.get("max_batch", C.SERVE_MAX_BATCH)))
        self.base = Session(self.bundle, None, False, None, self.runner)
        self.decrypted = 0  # behaviours checked and made here (a figure for tests)

        async def slot(route: str) -> BehaviourCache:  # what this replica holds for one routing id
            return BehaviourCache(_SLOT_BYTES)

        users = int(options.get("users_per_replica", USERS_PER_REPLICA))
        self.slot = serve.multiplexed(max_num_models_per_replica=users)(slot)

    def _unchanged(self) -> None:
        if bundle_stamp(self.path) != self.stamp:
            raise PropError("the bundle changed on disk since the server started", "redeploy prop serve-ray")

    async def _session(self, key_text: str | None) -> tuple[Session, bool]:
        """(the request's session, whether this replica already held its user: no check, no decryption)."""
        if key_text is None:
            return self.base, False
        bits = key_from_text(key_text, self.bits)
        route = serve.get_multiplexed_model_id()
        if route != routing_id(bits, self.salt):  # a caller that routed by another id: not this key's
            raise PropError("the request's routing id is not its key's", "connect through the gateway")
        cache = await self.slot(route)
        held, _ = cache.get(bits)
        if not held:
            self._unchanged()  # a key is checked only against the bundle this replica loaded
            self.decrypted += 1
        return Session(self.bundle, bits, self.allow, cache, self.runner), held

    async def open(self, key_text: str | None) -> tuple[dict | None, str | None]:
        """A connection's key checked: (openpi's server metadata, None), or (None, the refusal's line).
        The metadata says which replica answers and whether it already held this user (routing's work)."""
        try:
            self._unchanged()  # as prop serve: no new connection once the bundle changed on disk
            session, held = await self._session(key_text)
        except PropError as e:
            return None, e.what.replace(str(self.path), self.path.name)
        return server_metadata(self.bundle, session) | {"replica": self.replica, "held": held}, None

    async def infer(
        self, key_text: str | None, message: bytes, episode: Episode = NEW_EPISODE
    ) -> tuple[bytes | str, Episode]:
        """One openpi message of a connection at ``episode`` -> (msgpack-numpy reply bytes, or a one-line
        error as text; the connection's episode after it)."""
        try:
            obs = unpackb(message)
            if isinstance(obs, dict) and obs.get(RESET) is True:  # {"reset": True[, "seed": int]}
                seed = check_reset(obs)  # an array model has nothing to reset; a policy a new episode
                return packb({RESET: True}), (int(seed or 0), 0)
            session, _ = await self._session(key_text)
            if self.runner is not None:  # a LeRobot chunk, batched with other users'
                controller = session.controller
                controller.episode, controller.calls = int(episode[0]), int(episode[1])
                request = session.chunk_request(obs)  # checked; this call's noise seed counted
                episode = (controller.episode, controller.calls)
                chunk = await self.batcher.submit(request)
                return packb({"actions": chunk.astype("float32")}), episode
            x, single = session.observation(obs)
            return packb(session.answer(await self.batcher.submit(session.request(x)), single)), episode
        except (WireError, PropError) as e:
            return f"prop serve: error: {e}", episode
        except Exception as e:  # a bug or a model failure: one line, the replica goes on
            LOG.error("inference failed: %s", brief(e))
            if os.environ.get(C.ENV_DEBUG):
                LOG.exception("traceback")
            return f"prop serve: error: inference failed ({type(e).__name__})", episode

    def stats(self) -> dict:
        return {"replica": self.replica, "decrypted": self.decrypted, "batches": self.batcher.batches}


ws_app = FastAPI()


@serve.deployment(name="Gateway", ray_actor_options={"num_cpus": 0})
@serve.ingress(ws_app)
class Gateway:
    """The websocket ingress: one connection's key read once, its routing id computed, every message sent
    to the replica that holds that id (``PolicyReplica``)."""

    def __init__(self, policy, bits: int, salt: str, max_message_bytes: int) -> None:
        self.policy, self.bits, self.salt = policy, bits, bytes.fromhex(salt)
        self.max_message_bytes = max_message_bytes
        self.backoff = Backoff()

    def _route(self, ws: WebSocket) -> tuple[str | None, str]:
        """(the key's text or None, its routing id); the key's form checked here, the key by the replica."""
        header = ws.headers.get("authorization")
        if header is None:
            return None, NO_KEY
        scheme, _, text = header.strip().partition(" ")
        if scheme != SCHEME or not text.strip():
            raise PropError(f"the Authorization header is not '{SCHEME} <key hex>'", "see docs/deploy.md")
        return text.strip(), routing_id(key_from_text(text, self.bits), self.salt)

    @ws_app.websocket("/")
    async def connect(self, ws: WebSocket) -> None:
        await ws.accept()
        host = ws.client.host if ws.client is not None else "peer"
        try:
            key_text, route = self._route(ws)
            if key_text is not None and (wait := self.backoff.delay(host)):
                await asyncio.sleep(wait)  # this peer's keys kept failing: its next try waits
            handle = self.policy.options(multiplexed_model_id=route)
            metadata, refused = await handle.open.remote(key_text)
        except PropError as e:
            metadata, refused = None, e.what
        except Exception as e:  # a replica lost or a bug: one line, never the key
            LOG.error("%s: the policy could not be reached: %s", host, type(e).__name__)
            await ws.close(CLOSE_ERROR, "internal error: the policy could not be reached")
            return
        if refused is not None:
            self.backoff.failed(host)
            LOG.warning("%s: refused: %s", host, refused)
            await ws.close(CLOSE_POLICY, close_reason(f"refused: {refused}"))
            return
        if key_text is not None:
            self.backoff.opened(host)
        await ws.send_bytes(packb(metadata))
        episode = NEW_EPISODE  # this connection's episode state (a LeRobot policy's noise seeds)
        try:
            while True:
                message = await ws.receive()
                if message["type"] == "websocket.disconnect":
                    return
                data = message.get("bytes")
                if data is None:
                    await ws.send_text("prop serve: error: send msgpack-numpy bytes (openpi-client's infer), "
                                       "not text")  # fmt: skip
                    continue
                if len(data) > self.max_message_bytes:
                    await ws.close(CLOSE_TOO_BIG, f"message over {self.max_message_bytes} bytes")
                    return
                reply, episode = await handle.infer.remote(key_text, data, episode)
                await (ws.send_bytes(reply) if isinstance(reply, bytes) else ws.send_text(reply))
        except WebSocketDisconnect:
            return
        except Exception as e:  # a replica lost mid-request: one line, this connection closed, others go on
            LOG.error("%s: the policy failed: %s", host, type(e).__name__)
            with contextlib.suppress(Exception):
                await ws.close(CLOSE_ERROR, "internal error: the policy failed; connect again")


def application(
    bundle_path: Path, *, replicas: int = 2, users_per_replica: int = USERS_PER_REPLICA,
    allow_unenrolled: bool = False, batch_window_ms: float = C.SERVE_BATCH_WINDOW_MS,
    max_batch: int = C.SERVE_MAX_BATCH, max_message_bytes: int = C.SERVE_MAX_MESSAGE_BYTES,
    replica_cpus: float = 1.0, trust_remote_code: bool = False, arch: str | None = None,
    allow_rollback: bool = False, bundle: Bundle | None = None,
):  # fmt: skip
    """The Ray Serve application (gateway and replicas) for ``bundle_path``, checked here first: a bad
    bundle or option is one PropError before anything is deployed."""
    if replicas < 1:
        raise PropError(f"--replicas {replicas}", "pass 1 or more")
    if users_per_replica < 1:
        raise PropError(f"--users-per-replica {users_per_replica}", "pass 1 or more")
    check_batching(batch_window_ms, max_batch)
    if bundle is None:
        bundle = load_bundle(bundle_path, trust_remote_code=trust_remote_code, arch=arch,
                             allow_rollback=allow_rollback)  # fmt: skip
    check_servable(bundle)
    path = str(Path(bundle_path).resolve())
    options = {
        "allow_unenrolled": allow_unenrolled, "batch_window_ms": batch_window_ms, "max_batch": max_batch,
        "users_per_replica": users_per_replica, "trust_remote_code": trust_remote_code, "arch": arch,
        "allow_rollback": allow_rollback,
    }  # fmt: skip
    policy = serve.deployment(PolicyReplica, name="PolicyReplica", num_replicas=replicas,
                              ray_actor_options={"num_cpus": replica_cpus}).bind(path, options)  # fmt: skip
    bits = int(bundle.manifest[C.M_KEY]["bits"])
    return Gateway.bind(policy, bits, route_salt(bundle.manifest).hex(), max_message_bytes)


def build(args: dict):
    """``serve run prop_cli.serve.ray_app:build bundle=mine.prop replicas=2 users_per_replica=64``
    (and in a ``serve deploy`` config's ``import_path`` with ``args``)."""
    known = {"bundle", "replicas", "users_per_replica", "allow_unenrolled", "batch_window_ms", "max_batch",
             "replica_cpus"}  # fmt: skip
    unknown = sorted(set(args) - known)
    if unknown or "bundle" not in args:
        raise PropError(
            f"serve run args {unknown or 'without bundle'}", f"pass bundle=PATH and any of {sorted(known)}"
        )
    flag = str(args.get("allow_unenrolled", "false")).lower() in ("1", "true", "yes")
    return application(
        Path(args["bundle"]), replicas=int(args.get("replicas", 2)),
        users_per_replica=int(args.get("users_per_replica", USERS_PER_REPLICA)), allow_unenrolled=flag,
        batch_window_ms=float(args.get("batch_window_ms", C.SERVE_BATCH_WINDOW_MS)),
        max_batch=int(args.get("max_batch", C.SERVE_MAX_BATCH)),
        replica_cpus=float(args.get("replica_cpus", 1.0)),
    )  # fmt: skip


def run_app(
    app, *, address: str | None = None, host: str = C.SERVE_HOST, port: int = C.SERVE_PORT,
    tls_cert: Path | None = None, tls_key: Path | None = None, num_cpus: int | None = None,
    ready: Callable[[str], None] | None = None, stop: threading.Event | None = None,
) -> None:  # fmt: skip
    """Deploy ``app`` on Ray (a local instance, or the cluster at ``address``) behind Ray Serve's HTTP
    proxy on ``host:port`` (TLS needed off the loopback, as for `prop serve`), then wait for SIGINT,
    SIGTERM or ``stop``; the application is deleted (and a local instance shut down) on the way out."""
    import ray

    from .server import tls_context

    tls_context(host, tls_cert, tls_key)  # a refused address or TLS pair says so before Ray starts
    ray.init(address=address or "local", include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING, num_cpus=num_cpus if address is None else None)  # fmt: skip
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    try:
        http = {"host": host, "port": port}
        if tls_cert is not None:
            http.update(ssl_certfile=str(tls_cert), ssl_keyfile=str(tls_key))
        serve.start(http_options=http)
        serve.run(app, name=APP_NAME, route_prefix="/", blocking=False)
        scheme = "wss" if tls_cert is not None else "ws"
        if ready is not None:
            ready(f"{scheme}://{f'[{host}]' if ':' in host else host}:{port}")
        while not stop.wait(0.5):
            pass
    finally:
        if address is None:
            serve.shutdown()
        else:
            serve.delete(APP_NAME)
        ray.shutdown()
