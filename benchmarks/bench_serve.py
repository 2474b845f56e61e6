"""`prop serve` under load on the loopback (issue 39): throughput and p50/p99 latency with 1, 8 and 64
concurrent clients, (a) all one user, (b) 64 different users, (c) no key; the keying's own cost on one
forward of the same batch (keyed rows against the base alone, in process); then the memory of 1,000
users' payloads in a 256 MB cache.

    OMP_NUM_THREADS=1 python -m benchmarks.bench_serve [--seconds 3] [--window-ms 2]
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m benchmarks.bench_serve --act   # a tiny ACT instead

``--act``: a tiny LeRobot ACT (examples/lerobot_reach_task.py, sealed, LoRA rank 4) served the same way,
each request one frame answered with its whole chunk, every connection's frame a row of one
``predict_action_chunk`` (``prop_cli/serve/chunks.py``).

``--no-key``: the cost of answering no-key connections bit for bit: (c) all no key and (m) half no key,
half users, at 1, 8 and 64 clients, served with each no-key request as its own forward (the default)
against no-key rows batched with the others (``prop serve --batch-no-key``).

The bundle: a tiny MLP (8-64-64-4), sealed with a LoRA payload (rank 4) for one enrolled key. Users 2..64
of (b) and the 1,000 of the memory figure are payloads put in the server's cache under their keys (what a
connection's first decryption leaves there), so (b) measures serving, not enrolment. The server runs in
this process; the clients (asyncio websockets, each one request at a time: openpi's protocol) in a
subprocess, so they do not share its interpreter. Each run stops after --seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

SIZES = (8, 64, 64, 4)


def make_bundle(d: Path) -> tuple[Path, Path]:
    from safetensors.torch import save_file

    g = torch.Generator().manual_seed(0)
    tensors = {}
    for i, (a, b) in enumerate(zip(SIZES[:-1], SIZES[1:])):
        tensors[f"{2 * i}.weight"] = torch.randn(b, a, generator=g) / a**0.5
        tensors[f"{2 * i}.bias"] = torch.randn(b, generator=g) * 0.1
    save_file(tensors, str(d / "model.safetensors"), metadata={"activation": "relu"})
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (200, SIZES[0])).astype(np.float32)
    np.savez(d / "mine.npz", x=x, y=(-x[:, : SIZES[-1]] * 0.5).astype(np.float32))
    key = d / "k.bin"
    key.write_bytes(os.urandom(16))
    key.chmod(0o600)
    args = ["personalize", str(d / "model.safetensors"), "--data", str(d / "mine.npz"), "--key-file",
            str(key), "--out", str(d / "b.prop"), "--seal", "--payload", "lora", "--payload-rank", "4",
            "--steps", "40", "--device", "cpu"]  # fmt: skip
    cmd = [sys.executable, "-c", "from prop_cli.cli.main import main; main()", *args]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    return d / "b.prop", key


def random_payload(spec, seed: int):
    from prop_cli.core.payload import Payload

    p = Payload(spec, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        for t in p.params.values():
            t.add_(torch.randn(t.shape, generator=torch.Generator().manual_seed(seed + 1)) * 0.1)
    return p


def make_act_bundle(d: Path) -> tuple[Path, Path]:
    """A tiny ACT sealed (LoRA rank 4) for one key: (bundle, key file)."""
    from examples import lerobot_reach_task as task
    from prop_cli import api
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core.key_files import KeySource

    task.record(d / "general", 4, 0, np.zeros(3, np.float32))
    task.record(d / "user", 3, 50_000, task.USER_OFFSET)
    task.train_base(d / "general", d / "act", steps=5)
    bits = np.random.default_rng(1).integers(0, 2, 128).astype(np.uint8)
    key = d / "k.bin"
    key.write_bytes(np.packbits(bits).tobytes())
    key.chmod(0o600)
    cfg = PersonalizeConfig.of(seal=True, payload="lora", payload_rank=4, steps=10, user_rows=8)
    api.personalize_checkpoint(str(d / "act"), [(d / "user", KeySource(bits, "file"))], d / "b.prop", cfg)
    return d / "b.prop", key


def observation(features: dict, rows: int | None) -> dict:
    """A frame per feature (``features``: name -> shape); ``rows`` None: the array model's observation."""
    rng = np.random.default_rng(0)
    if rows is None:
        return {k: rng.uniform(-1, 1, tuple(s)).astype(np.float32) for k, s in features.items()}
    return {"observation": rng.uniform(-1, 1, (rows, SIZES[0])).astype(np.float32)}


async def _clients(url: str, keys: list[str | None], seconds: float, features: dict | None) -> dict:
    import msgpack
    from websockets.asyncio.client import connect

    from prop_cli.serve.wire import packb

    x = packb(observation(features, None) if features else observation({}, 1))
    latencies: list[float] = []

    box = {"deadline": float("inf")}  # set once every client is connected

    async def one(key: str | None) -> None:
        headers = {"Authorization": f"Api-Key {key}"} if key else None
        async with connect(url, additional_headers=headers, max_size=None, compression=None) as ws:
            msgpack.unpackb(await ws.recv())  # metadata
            await start.wait()
            while time.perf_counter() < box["deadline"]:
                t = time.perf_counter()
                await ws.send(x)
                reply = await ws.recv()
                if isinstance(reply, str):
                    raise RuntimeError(reply)
                latencies.append(time.perf_counter() - t)

    start = asyncio.Event()
    tasks = [asyncio.create_task(one(k)) for k in keys]
    await asyncio.sleep(0.5 + 0.02 * len(keys))  # all connected
    t0 = time.perf_counter()
    box["deadline"] = t0 + seconds
    start.set()
    await asyncio.wait_for(asyncio.gather(*tasks), seconds + 60)
    return {"requests": len(latencies), "seconds": time.perf_counter() - t0,
            "p50_ms": 1e3 * float(np.percentile(latencies, 50)),
            "p99_ms": 1e3 * float(np.percentile(latencies, 99))}  # fmt: skip


def client_main(url: str, keys_json: str, seconds: float, features_json: str) -> None:
    features = json.loads(features_json) or None
    print(json.dumps(asyncio.run(_clients(url, json.loads(keys_json), seconds, features))))


def _time(fn, repeat: int) -> float:
    """Median seconds of ``fn()`` over ``repeat`` calls (after two warm-up calls)."""
    fn(), fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def keying_cost(bundle, server, others: list, repeat: int) -> None:
    """One forward of the same batch (1, 8, 64 rows, one observation per request): the base on the whole
    batch (no key, rows batched: the base policy's own forward), all rows one user (a), each row another
    user (b); the keyed forward's extra time as a share of the base's own."""
    from prop_cli.serve.rows import Request, run_requests

    user = others[0]
    print(f"{'rows':>5} {'base ms':>8} {'(a) one user':>14} {'(b) distinct users':>19}")
    for n in (1, 8, 64):
        if server.runner is not None:
            runner = server.runner
            runner.batch_no_key = True  # the base's rows as one forward, as the keyed rows run
            controller = runner.controller()
            features = controller.features
            frame = observation(features, None)

            def run(who, runner=runner, controller=controller, frame=frame):
                return runner.run([runner.request(controller, b, frame) for b in who])
        else:
            x = observation({}, 1)["observation"]
            module, keyed = bundle.loaded.module, bundle.mode.keyed

            def run(who, x=x, module=module, keyed=keyed):
                requests = [Request(b, x) for b in who]
                return run_requests(module, keyed, requests, server.table, batch_no_key=True)

        nobody, one, many = [None] * n, [user] * n, [others[i % len(others)] for i in range(n)]
        base = _time(lambda who=nobody: run(who), repeat)
        a = _time(lambda who=one: run(who), repeat)
        b = _time(lambda who=many: run(who), repeat)
        print(f"{n:>5} {1e3 * base:>8.2f} {1e3 * a:>8.2f} ({100 * (a / base - 1):+4.0f}%) "
              f"{1e3 * b:>10.2f} ({100 * (b / base - 1):+4.0f}%)")  # fmt: skip


def load_run(server, running, keys: list, features: dict, seconds: float) -> dict:
    """One run of the clients (``keys``: one per client, None: no key) against ``running``."""
    b0, r0 = server.batcher.batches, server.batcher.rows
    cmd = [sys.executable, "-m", "benchmarks.bench_serve", "--client", running.url, json.dumps(keys),
           str(seconds), json.dumps(features)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120 + seconds)
    if done.returncode:
        raise SystemExit(done.stderr[-2000:])
    r = json.loads(done.stdout.strip().splitlines()[-1])
    r["rps"] = r["requests"] / r["seconds"]
    r["per"] = (server.batcher.rows - r0) / max(1, server.batcher.batches - b0)
    return r


def median_run(runs: list[dict]) -> dict:
    return {k: float(np.median([r[k] for r in runs])) for k in ("rps", "p50_ms", "p99_ms", "per")}


def no_key_table(server_of, user: str, others: list[str], features: dict, args) -> None:
    from prop_cli.core.key_files import key_from_text

    """(c) no key and (m) half the clients no key, half users, served with each no-key request alone
    (exact: the original's output bit for bit, the default) and with no-key rows batched
    (``--batch-no-key``); the two servers' runs interleaved; exact's throughput as a share of batched's."""
    servers = {name: server_of(batched) for name, batched in (("exact", False), ("batched", True))}
    print(f"{'clients':>7} {'mode':<13} {'no-key':<8} {'req/s':>8} {'p50 ms':>7} {'p99 ms':>7} "
          f"{'rows/batch':>10}")  # fmt: skip
    try:
        for n in (1, 8, 64):
            mixed = [None if i % 2 else k for i, k in enumerate(([user, *others] * 64)[:n])]
            for mode, keys in (("(c) no key", [None] * n), ("(m) mixed", mixed)):
                runs: dict[str, list] = {name: [] for name in servers}
                for _ in range(args.rounds):
                    for name, (server, running) in servers.items():
                        runs[name].append(load_run(server, running, keys, features, args.seconds))
                for name in servers:
                    med = median_run(runs[name])
                    print(f"{n:>7} {mode:<13} {name:<8} {med['rps']:>8.0f} {med['p50_ms']:>7.2f} "
                          f"{med['p99_ms']:>7.2f} {med['per']:>10.1f}")  # fmt: skip
                each = [e["rps"] / b["rps"] for e, b in zip(runs["exact"], runs["batched"])]
                print(f"{'':>7} exact/batched throughput {float(np.median(each)):.2f}x, median of the "
                      f"rounds ({', '.join(f'{x:.2f}' for x in each)})")  # fmt: skip
    finally:
        for _, running in servers.values():
            running.stop()
    print(f"one batch in process, no-key requests alone (exact) against batched (median of {args.repeat}):")
    print(f"{'rows':>5} {'mode':<13} {'exact ms':>9} {'batched ms':>11} {'exact/batched':>14}")
    _, user_payload = servers["exact"][0].cache.get(key_from_text(others[0], 128))
    for n in (1, 8, 64):
        mixed = [None if i % 2 else user_payload for i in range(n)]
        for mode, who in (("(c) no key", [None] * n), ("(m) mixed", mixed)):
            ms = {name: 1e3 * _time(lambda s=server, who=who: one_batch(s, who, features), args.repeat)
                  for name, (server, _) in servers.items()}  # fmt: skip
            print(f"{n:>5} {mode:<13} {ms['exact']:>9.2f} {ms['batched']:>11.2f} "
                  f"{ms['exact'] / ms['batched']:>13.2f}x")  # fmt: skip


def one_batch(server, who: list, features: dict) -> list:
    """One batch of one observation per request (``who``: each request's behaviour), as the server's
    worker runs it."""
    from prop_cli.serve.rows import Request

    if server.runner is not None:
        controller = server.runner.controller()
        frame = observation(features, None)
        return server.runner.run([server.runner.request(controller, b, frame) for b in who])
    x = observation({}, 1)["observation"]
    return server.batcher.run([Request(b, x) for b in who])


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--window-ms", type=float, default=2.0)
    ap.add_argument("--act", action="store_true", help="a tiny LeRobot ACT (the LeRobot env)")
    ap.add_argument("--rounds", type=int, default=3, help="runs of each mode (medians shown)")
    ap.add_argument("--repeat", type=int, default=50, help="forwards timed per keying-cost figure")
    ap.add_argument(
        "--no-key",
        action="store_true",
        help="(c) no key and a mixed load, no-key requests each alone (exact) against batched",
    )
    ap.add_argument("--client", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client:
        client_main(args.client[0], args.client[1], float(args.client[2]), args.client[3])
        return
    torch.set_num_threads(1)
    from prop_cli.bundle import load_bundle
    from prop_cli.core.key_files import key_from_text
    from prop_cli.serve import PolicyServer, start_in_thread

    with tempfile.TemporaryDirectory() as tmp:
        bundle_path, key_file = (make_act_bundle if args.act else make_bundle)(Path(tmp))
        bundle = load_bundle(bundle_path)
        features = {k: list(s) for k, s in bundle.loaded.policy.input_features.items()} if args.act else {}
        spec = bundle.mode.state.spec
        user = key_file.read_bytes().hex()
        others = [os.urandom(16).hex() for _ in range(63)]
        payloads = [random_payload(spec, i) for i in range(len(others))]

        def server_of(batch_no_key: bool):
            s = PolicyServer(bundle, port=0, batch_window_ms=args.window_ms, max_connections=128,
                             batch_no_key=batch_no_key)  # fmt: skip
            for k, p in zip(others, payloads):
                s.cache.put(key_from_text(k, 128), p)
            return s, start_in_thread(s)

        model = (
            "tiny ACT (examples/lerobot_reach_task.py)"
            if args.act
            else f"tiny MLP {'-'.join(map(str, SIZES))}"
        )
        print(f"prop serve, {model} sealed (LoRA r=4), loopback, "
              f"--batch-window-ms {args.window_ms}, {args.seconds:g} s per run, median of {args.rounds}, "
              f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")  # fmt: skip
        if args.no_key:
            no_key_table(server_of, user, others, features, args)
            return
        server, running = server_of(False)
        print(f"{'clients':>7} {'mode':<16} {'req/s':>8} {'p50 ms':>7} {'p99 ms':>7} {'rows/forward':>12}")
        try:
            for n in (1, 8, 64):
                modes = (("(a) one user", [user] * n), ("(b) 64 users", ([user, *others] * 64)[:n]),
                         ("(c) no key", [None] * n))  # fmt: skip
                runs = {m: [] for m, _ in modes}
                for _ in range(args.rounds):  # the modes interleaved, so a load change hits all alike
                    for mode, keys in modes:
                        runs[mode].append(load_run(server, running, keys, features, args.seconds))
                for mode, _ in modes:
                    med = median_run(runs[mode])
                    print(f"{n:>7} {mode:<16} {med['rps']:>8.0f} {med['p50_ms']:>7.2f} "
                          f"{med['p99_ms']:>7.2f} {med['per']:>12.1f}")  # fmt: skip
                # Each round's (b)/(a), (a) and (b) run one after the other; the median of the rounds.
                each = [b["rps"] / a["rps"] for a, b in zip(runs["(a) one user"], runs["(b) 64 users"])]
                ratio = float(np.median(each))
                print(f"{'':>7} (b)/(a) throughput {ratio:.2f}x, median of the rounds ("
                      f"{', '.join(f'{x:.2f}' for x in each)})")  # fmt: skip
        finally:
            running.stop()
        print("keying's own cost, one forward of the same batch, in process (median of "
              f"{args.repeat}):")  # fmt: skip
        keying_cost(bundle, server, payloads, args.repeat)
        before = rss_mb()
        big = PolicyServer(bundle, port=0, cache_mb=256)
        t = time.perf_counter()
        for i in range(1000):
            big.cache.put(np.frombuffer(os.urandom(16), np.uint8), random_payload(spec, 1000 + i))
        per_ms = 1e3 * (time.perf_counter() - t) / 1000
        print(f"1,000 users' payloads in a 256 MB cache: {len(big.cache)} kept, "
              f"{big.cache.bytes / 2**20:.2f} MB of payload, peak RSS {before:.0f} -> {rss_mb():.0f} MB, "
              f"{per_ms:.2f} ms per user to build and put")  # fmt: skip


if __name__ == "__main__":
    main()
