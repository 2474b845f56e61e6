"""The websocket server: openpi's policy protocol (server metadata first, then one msgpack-numpy reply per
observation), one ``Session`` per connection, the key checked once at connect and never logged.

Safe by default: the loopback only, unless TLS (wss) is given; messages capped (``max_size``); a client's
bad message gets a one-line text reply (openpi-client raises it as "Error in inference server"), never a
traceback, and the server keeps serving. A peer whose keys keep failing waits longer before each next try
(``Backoff``), while everyone else is served.

Inference runs on one worker thread. An array model's requests, from any connection, that arrive within
``batch_window_s`` run as one forward of the base, each row under its own user's behaviour (``batcher``,
``rows``); so do a LeRobot policy's whose chunk needs the frame alone (ACT, SmolVLA, pi0: ``chunks``).
Decrypted behaviours are kept in an LRU cache capped at ``cache_bytes`` (``cache``). A LeRobot policy with
an observation history (Diffusion) runs each connection on its own module and queues."""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import os
import signal
import ssl
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.core.key_files import key_from_text
from prop_cli.errors import PropError, brief

from .batcher import Batcher
from .cache import BehaviourCache
from .rows import run_requests
from .sessions import OBSERVATION, Session, chunk_runner, payload_table
from .wire import WireError, packb, unpackb

LOG = logging.getLogger("prop.serve")
# websockets logs request headers (the key among them) at DEBUG: its logger is held at WARNING whatever the
# root logger's level, so no setting of the host program's logging can print the Authorization header.
_WS_LOG = logging.getLogger("prop.serve.websockets")
_WS_LOG.setLevel(logging.WARNING)  # its INFO lines repeat ours

SCHEME = "Api-Key"  # openpi-client sends `Authorization: Api-Key <api_key>`
CLOSE_POLICY, CLOSE_ERROR, CLOSE_FULL = (
    1008,
    1011,
    1013,
)  # RFC 6455: policy violation, internal error, try later
LOOPBACK = ("localhost",)
# A message {"reset": True} (and an optional "seed") starts a new episode on this connection: a LeRobot
# policy's queues emptied. openpi-client's own reset() sends nothing: send it with infer({"reset": True}).
RESET = "reset"


def is_loopback(host: str) -> bool:
    if host in LOOPBACK:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def tls_context(host: str, tls_cert: Path | None, tls_key: Path | None) -> ssl.SSLContext | None:
    """TLS for wss, required off the loopback: the key travels in a header, so never in the clear."""
    if (tls_cert is None) != (tls_key is None):
        raise PropError("--tls-cert and --tls-key go together", "pass both (PEM certificate and its key)")
    if tls_cert is None:
        if not is_loopback(host):
            raise PropError(
                f"--host {host} is not the loopback, and keys would cross the network in the clear",
                "pass --tls-cert and --tls-key (wss), or serve on --host 127.0.0.1",
            )
        return None
    for flag, path in (("--tls-cert", tls_cert), ("--tls-key", tls_key)):
        if not Path(path).is_file():
            raise PropError(f"{flag} {path} is not a file", f"pass a PEM file to {flag}")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(str(tls_cert), str(tls_key))
    except (ssl.SSLError, OSError) as e:
        raise PropError(f"--tls-cert/--tls-key do not load ({brief(e, 80)})",
                        "pass a PEM certificate and its matching private key") from None  # fmt: skip
    return context


def _reason(text: str) -> str:
    """A close reason: RFC 6455 allows 123 bytes."""
    data = text.encode()[:120]
    return data.decode(errors="ignore")


class Backoff:
    """Wrong keys from one peer address: the n-th failure in a row makes that address's next connection
    wait ``min(cap_s, first_s * 2 ** (n - 1))`` before its key is tried; a key that opens resets it. The
    wait is the connection's own (asyncio), so other peers are not slowed. At most ``peers`` addresses
    are remembered (the oldest forgotten first)."""

    def __init__(self, first_s: float = 0.05, cap_s: float = 2.0, peers: int = 4096) -> None:
        self.first_s, self.cap_s, self.peers = first_s, cap_s, peers
        self.failures: dict[str, int] = {}

    def delay(self, host: str) -> float:
        n = self.failures.get(host, 0)
        return 0.0 if n == 0 else min(self.cap_s, self.first_s * 2 ** (n - 1))

    def failed(self, host: str) -> None:
        self.failures[host] = self.failures.pop(host, 0) + 1
        while len(self.failures) > self.peers:
            self.failures.pop(next(iter(self.failures)))

    def opened(self, host: str) -> None:
        self.failures.pop(host, None)


def bundle_stamp(path: Path) -> tuple | None:
    """What changes when a bundle is rewritten (prop writes a new folder and renames it into place; an edit
    in place rewrites its manifest): the folder's and its manifest's identity, size and time."""
    try:
        folder, manifest = os.stat(path), os.stat(Path(path) / C.MANIFEST)
    except OSError:
        return None
    return (folder.st_ino, folder.st_mtime_ns, manifest.st_ino, manifest.st_size, manifest.st_mtime_ns)


def _host(ws: ServerConnection) -> str:
    address = ws.remote_address
    return str(address[0]) if isinstance(address, tuple) else "peer"


def _peer(ws: ServerConnection) -> str:
    address = ws.remote_address
    return f"{address[0]}:{address[1]}" if isinstance(address, tuple) else "peer"


def check_batching(batch_window_ms: float, max_batch: int) -> None:
    """The batch options, checked alike by ``prop serve`` and ``prop serve-ray``."""
    if not 0 <= batch_window_ms <= 1000:
        raise PropError(f"--batch-window-ms {batch_window_ms}", "pass 0 to 1000 (0: no waiting)")
    if max_batch < 1:
        raise PropError(f"--max-batch {max_batch}", "pass 1 or more observations")


def server_metadata(bundle: Bundle, session: Session) -> dict:
    """What the server sends first (openpi's server metadata), for `prop serve` and `prop serve-ray` alike:
    nothing of the key, only whether it opened a behaviour."""
    policy = bundle.loaded.policy
    return {
        "server": "prop", "bundle": Path(str(bundle.path)).name,
        "kind": "lerobot" if policy is not None else "array",
        "observation": list(policy.input_features) if policy is not None else OBSERVATION,
        "input_shape": list(session.input_shape), "keyed": bool(session.keyed),
        # Steps per infer (openpi's ActionChunkBroker action_horizon): a LeRobot policy answers its
        # chunk (n_action_steps; ACT with temporal ensembling one step from its own queues); an
        # array model one action per observation.
        "action_horizon": session.chunk_steps or 1,
    }  # fmt: skip


def check_reset(obs) -> int | None:
    """The seed of a reset message, ``{"reset": True[, "seed": int]}``, checked (None: none given)."""
    seed = obs.get("seed")
    if seed is not None and not isinstance(seed, int):
        raise PropError(f"a reset's seed is an int, not {type(seed).__name__}", "send an int")
    return seed


class PolicyServer:
    """``bundle`` served on ``host:port`` (0: a free port). ``max_connections``: more are closed at once
    (1013, try again later); ``max_message_bytes``: a bigger message closes its connection (1009).
    ``batch_no_key``: no-key requests share the batch's forward (faster; within float rounding of the
    original) instead of each running alone (the original's output bit for bit, the default)."""

    def __init__(
        self, bundle: Bundle, *, host: str = C.SERVE_HOST, port: int = C.SERVE_PORT,
        tls_cert: Path | None = None, tls_key: Path | None = None, allow_unenrolled: bool = False,
        max_connections: int = C.SERVE_MAX_CONNECTIONS,
        max_message_bytes: int = C.SERVE_MAX_MESSAGE_BYTES,
        batch_window_ms: float = C.SERVE_BATCH_WINDOW_MS, max_batch: int = C.SERVE_MAX_BATCH,
        cache_mb: float = C.SERVE_CACHE_MB, backoff: Backoff | None = None, batch_no_key: bool = False,
    ) -> None:  # fmt: skip
        if max_connections < 1:
            raise PropError(f"--max-connections {max_connections}", "pass 1 or more")
        check_batching(batch_window_ms, max_batch)
        if cache_mb < 0:
            raise PropError(f"--cache-mb {cache_mb}", "pass 0 (no cache) or more megabytes")
        self.ssl = tls_context(host, tls_cert, tls_key)
        self.bundle, self.host, self.port = bundle, host, port
        self.allow_unenrolled, self.max_connections = allow_unenrolled, max_connections
        self.max_message_bytes = max_message_bytes
        self.open = 0
        self.served = 0  # connections accepted since start
        self.in_flight = 0  # requests received and not yet answered
        self.stopping = False  # SIGTERM: no new request starts; those in flight are answered
        self.drain_s = C.SERVE_DRAIN_S
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="prop-serve")
        self.cache = BehaviourCache(int(cache_mb * 2**20))
        self.stamp = bundle_stamp(Path(str(bundle.path)))  # the bundle as loaded (and checked)
        self.backoff = backoff or Backoff()
        module, keyed = bundle.loaded.module.eval(), bundle.mode.keyed
        # A sealed bundle's payloads in use, each in a slot of one table per layer (S-LoRA's pool).
        self.table = table = payload_table(bundle)
        # A LeRobot policy whose chunk needs the frame alone: its connections share forwards too.
        # A no-key request runs alone (the original's output bit for bit) unless batch_no_key.
        self.runner = chunk_runner(bundle, table, batch_no_key)
        run = self.runner.run if self.runner is not None else (
            lambda rs: run_requests(module, keyed, rs, table, batch_no_key)
        )  # fmt: skip
        self.batcher = Batcher(run, self._pool, batch_window_ms / 1000, max_batch)

    @property
    def scheme(self) -> str:
        return "wss" if self.ssl is not None else "ws"

    def metadata(self, session: Session) -> dict:
        return server_metadata(self.bundle, session)

    def _key(self, ws: ServerConnection):
        """The key bits the connection's Authorization header carries; None without the header."""
        header = ws.request.headers.get("Authorization") if ws.request is not None else None
        if header is None:
            return None
        scheme, _, text = header.strip().partition(" ")
        if scheme != SCHEME or not text.strip():
            raise PropError(f"the Authorization header is not '{SCHEME} <key hex>'", "see docs/deploy.md")
        return key_from_text(text, int(self.bundle.manifest[C.M_KEY]["bits"]))

    async def _session(self, ws: ServerConnection) -> Session | None:
        """The connection's session, or None after closing it with a reason (the key is never in it)."""
        loop = asyncio.get_running_loop()
        host = _host(ws)
        try:
            key = self._key(ws)
            given = key is not None
            if given and (wait := self.backoff.delay(host)):
                await asyncio.sleep(wait)  # this peer's keys kept failing: its next try waits
            session = await loop.run_in_executor(
                self._pool, Session, self.bundle, key, self.allow_unenrolled, self.cache, self.runner
            )
            del key
            if given:
                self.backoff.opened(host)
        except PropError as e:
            self.backoff.failed(host)
            LOG.warning("%s: refused: %s", _peer(ws), e.what)
            # The client is told the bundle's name, not where it lies on this machine.
            what = e.what.replace(str(self.bundle.path), Path(str(self.bundle.path)).name)
            await ws.close(CLOSE_POLICY, _reason(f"refused: {what}"))
            return None
        except Exception as e:  # a bug: one line each side (no traceback, whose frames held the key)
            LOG.error("%s: the policy could not be made: %s", _peer(ws), type(e).__name__)
            await ws.close(CLOSE_ERROR, "internal error: the policy could not be made")
            return None
        how = (
            "keyed"
            if session.keyed
            else ("the base: key enrolled in nothing (allowed)" if given else "no key")
        )
        LOG.info("%s: connected (%s)", _peer(ws), how)
        return session

    async def _handle(self, ws: ServerConnection) -> None:
        if self.open >= self.max_connections:
            LOG.warning("%s: refused: %d connections open (--max-connections)", _peer(ws), self.open)
            await ws.close(CLOSE_FULL, "server full: try again later")
            return
        if bundle_stamp(Path(str(self.bundle.path))) != self.stamp:
            # Keys are checked against the bundle in memory; the one on disk may have lost a user
            # (remove-user) or changed: no new connection until a restart loads and checks it again.
            LOG.warning("%s: refused: the bundle changed on disk since the server started", _peer(ws))
            await ws.close(CLOSE_POLICY, "refused: the bundle changed on disk since the server started: "
                                         "restart prop serve")  # fmt: skip
            return
        self.open += 1
        try:
            session = await self._session(ws)
            if session is None:
                return
            self.served += 1
            await ws.send(packb(self.metadata(session)))
            async for message in ws:
                if self.stopping:  # draining: what is in flight is answered, nothing new starts
                    await ws.send("prop serve: error: the server is stopping: reconnect to another")
                    continue
                self.in_flight += 1
                try:
                    await ws.send(await self._answer(session, message))
                finally:
                    self.in_flight -= 1
        except ConnectionClosed:
            pass
        finally:
            self.open -= 1
        LOG.info("%s: closed", _peer(ws))

    async def _answer(self, session: Session, message) -> bytes | str:
        """One reply: msgpack-numpy bytes, or a one-line error as text (openpi's error convention)."""
        if isinstance(message, str):
            return "prop serve: error: send msgpack-numpy bytes (openpi-client's infer), not text"
        loop = asyncio.get_running_loop()
        try:
            obs = unpackb(message)
            if isinstance(obs, dict) and obs.get(RESET) is True:  # {"reset": True[, "seed": int]}
                seed = check_reset(obs)
                await loop.run_in_executor(self._pool, session.reset, seed)
                return packb({RESET: True})
            if session.runner is not None:  # a LeRobot chunk, batched with other connections'
                chunk = await self.batcher.submit(session.chunk_request(obs))
                return packb({"actions": chunk.astype("float32")})
            if session.controller is not None:
                return packb(await loop.run_in_executor(self._pool, session.infer, obs))
            x, single = session.observation(obs)
            return packb(session.answer(await self.batcher.submit(session.request(x)), single))
        except (WireError, PropError) as e:
            return f"prop serve: error: {e}"
        except Exception as e:  # a bug or a model failure: one line each side, the server goes on
            LOG.error("inference failed: %s", brief(e))
            if os.environ.get(C.ENV_DEBUG):
                LOG.exception("traceback")
            return f"prop serve: error: inference failed ({type(e).__name__})"

    async def run(
        self, ready: Callable[[str], None] | None = None, stop: asyncio.Event | None = None
    ) -> None:
        """Serve until ``stop`` is set (SIGINT/SIGTERM in the main thread set it too)."""
        stop = stop or asyncio.Event()
        loop = asyncio.get_running_loop()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
        try:
            async with serve(
                self._handle, self.host, self.port, ssl=self.ssl, max_size=self.max_message_bytes,
                compression=None, logger=_WS_LOG, server_header=None,
            ) as server:  # fmt: skip
                self.port = server.sockets[0].getsockname()[1]
                if ready is not None:
                    ready(self.url)
                await stop.wait()
                await self._drain(server)
        except OSError as e:
            raise PropError(f"cannot listen on {self.host}:{self.port} ({e.strerror or e})",
                            "pick another --port, or stop what holds this one") from None  # fmt: skip
        finally:
            self._pool.shutdown(wait=True)  # in-flight inferences finish before the process exits

    async def _drain(self, server) -> None:
        """Stop: no new connection, no new request; every request in flight (waiting in a batch window
        or running) answered, for up to ``drain_s``; then the connections close (1001, going away)."""
        self.stopping = True
        server.close(close_connections=False)  # stop listening; open connections stay for their answers
        waited = 0.0
        while self.in_flight and waited < self.drain_s:
            await asyncio.sleep(0.01)
            waited += 0.01
        if self.in_flight:
            LOG.warning("stopping with %d requests unanswered after %.0f s", self.in_flight, self.drain_s)
        LOG.info("drained: %d connections open, closing", self.open)
        # close() again is a no-op once called: the connections are closed here (1001, going away).
        await asyncio.gather(*(ws.close(1001, "the server is stopping") for ws in list(server.connections)),
                             return_exceptions=True)  # fmt: skip

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"


def serve_bundle(server: PolicyServer, ready: Callable[[str], None] | None = None) -> int:
    """Run ``server`` in this thread until SIGINT or SIGTERM; returns the connections it served."""
    asyncio.run(server.run(ready))
    return server.served


@dataclass
class Running:
    """A server running on a thread of its own (tests, benchmarks, a notebook): ``stop()`` ends it."""

    server: PolicyServer
    url: str
    port: int
    _loop: asyncio.AbstractEventLoop
    _stop: asyncio.Event
    _thread: threading.Thread

    def stop(self, timeout: float = 10.0) -> None:
        if not self._thread.is_alive():
            return
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout)


def start_in_thread(server: PolicyServer, timeout: float = 30.0) -> Running:
    """Start ``server`` on a daemon thread and return once it listens (its port: ``Running.port``)."""
    started = threading.Event()
    box: dict = {}

    def main() -> None:
        loop = asyncio.new_event_loop()
        box["loop"], box["stop"] = loop, asyncio.Event()
        try:
            loop.run_until_complete(server.run(lambda url: started.set(), box["stop"]))
        except BaseException as e:  # noqa: BLE001 - handed to the caller below
            box["error"] = e
            started.set()
        finally:
            loop.close()

    thread = threading.Thread(target=main, name="prop-serve", daemon=True)
    thread.start()
    if not started.wait(timeout):
        raise PropError(f"the server did not start within {timeout:.0f} s", "see its log")
    if "error" in box:
        raise box["error"]
    return Running(server, server.url, server.port, box["loop"], box["stop"], thread)
