"""prop serve's batching across users: many users' rows in one forward of the base equal each user's own
folded run (within float rounding, measured here), no-key rows stay the base's; the behaviour cache."""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import os
import time

import numpy as np
import pytest
import torch
from torch import nn

from prop_cli.bundle import load_bundle
from prop_cli.core.key_files import key_text, read_key_file
from prop_cli.core.layers import describe_layer
from prop_cli.core.payload import KINDS, Payload, PayloadSpec
from prop_cli.errors import PropError
from prop_cli.run import KeyedPolicy
from prop_cli.serve.batcher import Batcher
from prop_cli.serve.cache import BehaviourCache, behaviour_bytes
from prop_cli.serve.rows import Deltas, Folded, Request, run_requests
from prop_cli.serve.sessions import Session
from tests.serve.shares import OPENPI_CONNECT, personalize_here

client_policy = pytest.importorskip("openpi_client.websocket_client_policy")

# Batched rows against each user's folded weights: (W diag d) x + b against W (d x) + b, and W x + B (A x)
# against (W + B A) x. Measured on these models (float32, CPU): at most 1.2e-7. A no-key request runs
# alone (its own forward of the base), so it is the original's output bit for bit however many others
# share its batch; with batch_no_key (prop serve --batch-no-key) its rows join the others' forward: the
# same matmul over more rows, which BLAS may sum in another order (measured: within 1.2e-7).
ATOL = 1e-5


def _mlp() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(6, 16), nn.ReLU(), nn.Linear(16, 16), nn.Tanh(), nn.Linear(16, 3)).eval()


def _payload(module: nn.Module, kind: str, seed: int) -> Payload:
    mods = dict(module.named_modules())
    layers = [describe_layer(n, mods[n]) for n in ("0", "2")]
    spec = PayloadSpec(kind, layers, rank=2 if KINDS[kind].has_rank else 0)
    p = Payload(spec, torch.Generator().manual_seed(seed))
    g = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        for t in p.params.values():  # away from the base (delta 1, B 0) so every part matters
            t.add_(torch.randn(t.shape, generator=g) * 0.3)
    return p


@pytest.mark.parametrize("batch_no_key", [False, True])
@pytest.mark.parametrize("kind", list(KINDS))
def test_mixed_users_in_one_forward_equal_their_own_runs(kind, batch_no_key):
    module = _mlp()
    users = [_payload(module, kind, s) for s in range(3)]
    rng = np.random.default_rng(0)
    # Rows of three users and the base, interleaved, of different sizes (one user twice).
    who = [users[0], None, users[1], users[0], None, users[2]]
    sizes = (3, 2, 1, 4, 1, 2)
    requests = [Request(b, rng.normal(size=(n, 6)).astype(np.float32)) for b, n in zip(who, sizes)]
    calls = []
    hook = module.register_forward_hook(lambda m, a, o: calls.append(a[0].shape[0]))
    got = run_requests(module, None, requests, batch_no_key=batch_no_key)
    hook.remove()
    # The base ran once on every keyed row; each no-key request alone (bit for bit) unless batched too.
    assert calls == ([13] if batch_no_key else [2, 1, 10]), calls
    worst = 0.0
    with torch.inference_mode():
        for r, y in zip(requests, got):
            x = torch.from_numpy(r.x)
            if r.behaviour is None and not batch_no_key:  # the original alone, bit for bit
                assert torch.equal(y, module(x))
                continue
            if r.behaviour is None:  # the base's rows: float rounding of a larger matmul only
                worst = max(worst, (y - module(x)).abs().max().item())
                continue
            want = r.behaviour.fold(module)(x)
            assert not torch.allclose(want, module(x), atol=1e-3)  # the payload changes the output
            worst = max(worst, (y - want).abs().max().item())
    print(f"{kind}: worst {worst:.2e}")
    assert worst <= ATOL, worst


def test_a_folded_behaviour_runs_apart_in_the_same_call():
    module = _mlp()
    p = _payload(module, "lora", 1)
    x = np.random.default_rng(1).normal(size=(2, 6)).astype(np.float32)
    folded = Folded(p.fold(module).eval())
    a, b = run_requests(module, None, [Request(folded, x), Request(p, x)])
    assert torch.equal(a, folded.module(torch.from_numpy(x)))
    torch.testing.assert_close(a, b, rtol=0, atol=ATOL)


def test_unsealed_users_and_no_key_rows_in_one_forward_equal_keyed_policy(served_bundle):
    bundle = load_bundle(served_bundle / "mine.prop")
    user = Session(bundle, read_key_file(served_bundle / "k.bin"), False)
    base = Session(bundle, None, False)
    assert isinstance(user.behaviour, Deltas) and base.behaviour is None
    x = np.random.default_rng(2).uniform(-1, 1, (5, 4)).astype(np.float32)
    requests = [user.request(x), base.request(x), user.request(x[:2])]
    got = run_requests(bundle.loaded.module, bundle.mode.keyed, requests)
    want_user = KeyedPolicy(bundle, read_key_file(served_bundle / "k.bin"))(x)
    want_base = KeyedPolicy(bundle, None)(x)
    assert not np.allclose(want_user, want_base, atol=1e-3)
    np.testing.assert_allclose(got[0].numpy(), want_user, rtol=0, atol=ATOL)
    np.testing.assert_allclose(got[2].numpy(), want_user[:2], rtol=0, atol=ATOL)
    np.testing.assert_array_equal(got[1].numpy(), want_base)  # no key: the original, bit for bit


def test_the_batcher_runs_what_arrives_in_its_window_as_one_batch():
    seen = []

    def run(requests):
        seen.append([r.rows for r in requests])
        return [r.x * 2 for r in requests]

    async def go():
        pool = cf.ThreadPoolExecutor(1)
        batcher = Batcher(run, pool, window_s=0.05, max_rows=5)
        xs = [np.full((n, 1), i, np.float32) for i, n in enumerate((1, 2, 1, 3, 1))]
        outs = await asyncio.wait_for(asyncio.gather(*(batcher.submit(Request(None, x)) for x in xs)), 10)
        pool.shutdown()
        return xs, outs

    xs, outs = asyncio.run(go())
    for x, y in zip(xs, outs):
        np.testing.assert_array_equal(y, x * 2)
    assert seen[0] == [1, 2, 1]  # five rows at most: the fourth request (3 rows) waits for the next
    assert sum(map(len, seen)) == 5 and len(seen) == 2


@OPENPI_CONNECT
def test_concurrent_clients_of_different_users_are_batched(start, served_bundle):
    running = start(batch_window_ms=20)
    x = np.random.default_rng(3).uniform(-1, 1, (3, 4)).astype(np.float32)
    bundle = load_bundle(served_bundle / "mine.prop")
    want = {None: KeyedPolicy(bundle, None).predict(x)[0],
            "k": KeyedPolicy(bundle, read_key_file(served_bundle / "k.bin")).predict(x)[0]}  # fmt: skip
    Client = client_policy.WebsocketClientPolicy
    clients = [(who, Client(host="127.0.0.1", port=running.port,
                            api_key=key_text(served_bundle / "k.bin") if who else None))
               for who in ("k", None, "k", None, "k", None)]  # fmt: skip
    before = running.server.batcher.batches
    with cf.ThreadPoolExecutor(len(clients)) as pool:
        for _ in range(3):
            outs = list(pool.map(lambda c: c[1].infer({"observation": x})["actions"], clients))
            for (who, _), y in zip(clients, outs):
                if who is None:  # a no-key connection among users': the original's actions bit for bit
                    np.testing.assert_array_equal(y, want[None])
                np.testing.assert_allclose(y, want[who], rtol=0, atol=ATOL)
    forwards = running.server.batcher.batches - before
    assert forwards < 3 * len(clients), forwards  # requests of different users shared forwards
    for _, c in clients:
        c._ws.close()


def test_the_cache_keeps_behaviours_within_its_cap_and_evicts_the_oldest():
    module = _mlp()
    ps = [_payload(module, "lora", s) for s in range(3)]
    size = behaviour_bytes(ps[0])
    cache = BehaviourCache(2 * size)
    keys = [np.full(16, i, np.uint8) for i in range(3)]
    cache.put(keys[0], ps[0])
    cache.put(keys[1], ps[1])
    assert cache.get(keys[0]) == (True, ps[0])  # 0 used last: 1 is the oldest now
    cache.put(keys[2], ps[2])
    assert cache.get(keys[1]) == (False, None) and cache.evictions == 1
    assert cache.get(keys[0])[1] is ps[0] and cache.get(keys[2])[1] is ps[2]
    assert cache.bytes == 2 * size <= cache.cap
    small = BehaviourCache(size - 1)
    small.put(keys[0], ps[0])  # larger than the whole cap: not kept
    assert len(small) == 0


def test_a_cached_key_is_not_decrypted_again(served_bundle, monkeypatch):
    bundle = load_bundle(served_bundle / "mine.prop")
    cache = BehaviourCache(2**20)
    key = read_key_file(served_bundle / "k.bin")
    first = Session(bundle, key, False, cache)
    opened = []
    real = type(bundle.mode).enrolled
    monkeypatch.setattr(
        type(bundle.mode), "enrolled", lambda self, bits: opened.append(1) or real(self, bits)
    )
    second = Session(bundle, key, False, cache)
    assert not first.cached and second.cached and second.behaviour is first.behaviour and opened == []
    Session(bundle, None, False, cache)
    assert opened == [] and cache.hits == 1


@OPENPI_CONNECT
def test_wrong_keys_from_one_peer_slow_it_down_and_others_are_served(start, served_bundle):
    from websockets.exceptions import ConnectionClosed

    running = start()
    server = running.server
    server.backoff.first_s, server.backoff.cap_s = 0.01, 0.08
    Client = client_policy.WebsocketClientPolicy
    good = Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k.bin"))
    x = {"observation": np.zeros((1, 4), np.float32)}
    stop, latencies = False, []

    def serve_good():
        while not stop:
            t = time.perf_counter()
            good.infer(x)
            latencies.append(time.perf_counter() - t)

    wrong = key_text(served_bundle / "k2.bin")
    with cf.ThreadPoolExecutor(1) as pool:
        job = pool.submit(serve_good)
        t0 = time.perf_counter()
        for _ in range(50):
            with pytest.raises(ConnectionClosed):
                Client(host="127.0.0.1", port=running.port, api_key=wrong)
        elapsed = time.perf_counter() - t0
        stop = True
        job.result(timeout=20)
    assert server.backoff.failures["127.0.0.1"] == 50
    assert elapsed >= 40 * 0.08  # from the fourth on, each waited the cap
    assert len(latencies) > 20 and float(np.percentile(latencies, 50)) < 0.05
    good._ws.close()


@pytest.fixture(scope="module")
def sealed_bundle(served_bundle):
    """The tiny MLP sealed (LoRA payload) for k.bin."""
    personalize_here(served_bundle, "sealed.prop", "--seal", "--payload", "lora", "--payload-rank", "2")
    return served_bundle / "sealed.prop"


def test_sealed_users_are_payloads_batched_with_the_base(sealed_bundle, served_bundle):
    bundle = load_bundle(sealed_bundle)
    cache = BehaviourCache(2**20)
    user = Session(bundle, read_key_file(served_bundle / "k.bin"), False, cache)
    assert isinstance(user.behaviour, Payload) and user.keyed
    with pytest.raises(PropError, match="enrolled in nothing"):
        Session(bundle, read_key_file(served_bundle / "k2.bin"), False, cache)
    allowed = Session(bundle, read_key_file(served_bundle / "k2.bin"), True, cache)
    assert allowed.behaviour is None and not allowed.keyed
    x = np.random.default_rng(4).uniform(-1, 1, (4, 4)).astype(np.float32)
    got = run_requests(bundle.loaded.module, None, [user.request(x), allowed.request(x)])
    want_user = KeyedPolicy(bundle, read_key_file(served_bundle / "k.bin"))(x)
    want_base = KeyedPolicy(bundle, None)(x)
    assert not np.allclose(want_user, want_base, atol=1e-3)
    np.testing.assert_allclose(got[0].numpy(), want_user, rtol=0, atol=ATOL)
    np.testing.assert_array_equal(got[1].numpy(), want_base)  # an unenrolled key: the original, bit for bit
    assert Session(bundle, read_key_file(served_bundle / "k.bin"), False, cache).cached


@OPENPI_CONNECT
def test_a_bundle_changed_on_disk_refuses_new_connections_and_keeps_open_ones(
    served_bundle, start_bundle, tmp_path
):
    import shutil

    from websockets.exceptions import ConnectionClosed

    copy = tmp_path / "copy.prop"
    shutil.copytree(served_bundle / "mine.prop", copy)
    running = start_bundle(copy)
    Client = client_policy.WebsocketClientPolicy
    keyed = Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k.bin"))
    x = {"observation": np.zeros((1, 4), np.float32)}
    before = keyed.infer(x)["actions"]
    manifest = copy / "manifest.json"
    manifest.write_text(manifest.read_text() + "\n")  # as remove-user or a hand edit would
    with pytest.raises(ConnectionClosed) as e:
        Client(host="127.0.0.1", port=running.port)
    assert e.value.rcvd.code == 1008 and "changed on disk" in e.value.rcvd.reason
    np.testing.assert_array_equal(keyed.infer(x)["actions"], before)  # an open connection goes on
    keyed._ws.close()


@OPENPI_CONNECT
def test_a_reset_message_is_answered_and_a_bad_seed_refused_in_one_line(start):
    running = start()
    client = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port)
    assert client.infer({"reset": True}) == {"reset": True}
    assert client.infer({"reset": True, "seed": 3}) == {"reset": True}
    with pytest.raises(RuntimeError, match="seed is an int"):
        client.infer({"reset": True, "seed": "x"})
    assert client.infer({"observation": np.zeros(4, np.float32)})["actions"].shape == (2,)
    client._ws.close()


@OPENPI_CONNECT
def test_stop_answers_the_requests_in_flight_while_batching(start, served_bundle):
    """SIGTERM's drain (Running.stop sets the same event): a request waiting in its batch window when the
    server is told to stop is answered before the connections close; nothing new is accepted."""
    running = start(batch_window_ms=400)
    Client = client_policy.WebsocketClientPolicy
    x = np.random.default_rng(7).uniform(-1, 1, (2, 4)).astype(np.float32)
    want = KeyedPolicy(load_bundle(served_bundle / "mine.prop"), read_key_file(served_bundle / "k.bin"))
    clients = [Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k.bin"))
               for _ in range(3)]  # fmt: skip
    with cf.ThreadPoolExecutor(len(clients)) as pool:
        jobs = [pool.submit(c.infer, {"observation": x}) for c in clients]
        deadline = time.perf_counter() + 5
        while running.server.in_flight < len(clients) and time.perf_counter() < deadline:
            time.sleep(0.005)
        assert running.server.in_flight == len(clients) and running.server.batcher.batches == 0
        running.stop()  # returns once the server has drained and closed
        for job in jobs:
            np.testing.assert_allclose(
                job.result(timeout=10)["actions"], want.predict(x)[0], rtol=0, atol=ATOL
            )
    assert not running._thread.is_alive()  # it stopped, within Running.stop's wait
    assert running.server.stopping and running.server.in_flight == 0 and running.server.batcher.batches == 1
    with pytest.raises(OSError):  # nothing listens any more
        Client(host="127.0.0.1", port=running.port)


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _wrong_key_soak(start, served_bundle, n: int) -> None:
    """``n`` wrong-key connections, one after another from one peer, while a good client keeps being
    served: each is refused in one line, the good client's latency stays low, and the server's memory
    and its per-peer state stay bounded."""
    from websockets.exceptions import ConnectionClosed

    running = start()
    server = running.server
    server.backoff.first_s, server.backoff.cap_s = 0.001, 0.002  # the backoff itself is tested above
    Client = client_policy.WebsocketClientPolicy
    good = Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k.bin"))
    x = {"observation": np.zeros((1, 4), np.float32)}
    want = good.infer(x)["actions"]
    stop, latencies, wrong_answers = False, [], []

    def serve_good():
        while not stop:
            t = time.perf_counter()
            y = good.infer(x)["actions"]
            latencies.append(time.perf_counter() - t)
            wrong_answers.append(not np.array_equal(y, want))

    wrong = key_text(served_bundle / "k2.bin")
    rss = []
    with cf.ThreadPoolExecutor(1) as pool:
        job = pool.submit(serve_good)
        for i in range(n):
            with pytest.raises(ConnectionClosed) as e:
                Client(host="127.0.0.1", port=running.port, api_key=wrong)
            assert e.value.rcvd.code == 1008 and "enrolled in nothing" in e.value.rcvd.reason
            if i in (n // 5, n - 1):
                rss.append(_rss_mb())
        stop = True
        job.result(timeout=30)
    assert server.backoff.failures["127.0.0.1"] == n and len(server.backoff.failures) == 1
    assert server.open == 1 and len(server.cache) == 1  # the good key only: wrong keys leave nothing
    assert len(latencies) > 10 and not any(wrong_answers)
    assert float(np.percentile(latencies, 50)) < 0.05
    growth = rss[1] - rss[0]
    print(f"{n} wrong keys: RSS {rss[0]:.0f} -> {rss[1]:.0f} MB, good client p50 "
          f"{1e3 * float(np.percentile(latencies, 50)):.1f} ms over {len(latencies)} requests")  # fmt: skip
    assert growth < 30, growth  # no per-connection leak (a leak of even 50 kB each would show)
    good._ws.close()


@OPENPI_CONNECT
def test_fifty_wrong_key_connections_leave_the_server_serving(start, served_bundle):
    _wrong_key_soak(start, served_bundle, 50)


@pytest.mark.slow
@OPENPI_CONNECT
def test_a_thousand_wrong_key_connections_soak(start, served_bundle):
    _wrong_key_soak(start, served_bundle, 1000)


@pytest.fixture
def one_thread():
    """Bit for bit is within one process and one thread setting: a test before may have left another."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def test_the_server_runs_no_key_requests_alone_unless_told_to_batch_them(served_bundle, one_thread):
    from prop_cli.serve import PolicyServer

    bundle = load_bundle(served_bundle / "mine.prop")
    module = bundle.loaded.module
    x = np.random.default_rng(6).uniform(-1, 1, (2, 4)).astype(np.float32)
    key = read_key_file(served_bundle / "k.bin")
    for batch_no_key, forwards in ((False, 3), (True, 1)):
        server = PolicyServer(bundle, port=0, batch_no_key=batch_no_key)
        user, base = Session(bundle, key, False, server.cache), Session(bundle, None, False, server.cache)
        calls: list[int] = []
        hook = module.register_forward_hook(lambda m, a, o, calls=calls: calls.append(a[0].shape[0]))
        try:
            got = server.batcher.run([base.request(x), user.request(x), base.request(x[:1])])
        finally:
            hook.remove()
        assert len(calls) == forwards, calls  # alone: one forward per no-key request, one for the user
        want = KeyedPolicy(bundle, None)(x)
        if batch_no_key:
            np.testing.assert_allclose(got[0].numpy(), want, rtol=0, atol=ATOL)
        else:
            np.testing.assert_array_equal(got[0].numpy(), want)
            # The original on that request's one row (not row 0 of a two-row forward: BLAS may differ).
            with torch.inference_mode():
                alone = module(torch.from_numpy(x[:1]))
            assert torch.equal(got[2], alone)
