"""`prop serve-ray` against `prop serve` on the loopback, in one run (issue 39, "Past one machine"):
throughput and p50/p99 latency with 1 and 8 concurrent clients, (a) all one user, (b) 8 different users,
(c) no key; the time to a connection's metadata when its user's replica already holds it and when it does
not; and how often a user's later connections land on a replica that holds it (Ray Serve's multiplexing).

    OMP_NUM_THREADS=1 python -m benchmarks.bench_serve_ray [--seconds 3] [--replicas 2]
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m benchmarks.bench_serve_ray --policy act

Needs the `ray` extra. The bundle: bench_serve's tiny MLP (8-64-64-4), sealed with a LoRA payload (rank 4),
8 users (the first by personalize, 7 by add-user); ``--policy act``: a tiny LeRobot ACT
(examples/lerobot_reach_task.py) sealed with LoRA payloads (rank 4) for 8 users in one personalize, each
request one frame answered with the whole chunk (needs lerobot and ray in one environment:
``PROP_LEROBOT_RAY=1 scripts/setup-lerobot.sh``). Ray runs as a local instance on this machine
(``--num-cpus`` = the machine's CPUs); `prop serve` in this process; the clients in a subprocess
(bench_serve's, one request at a time each: openpi's protocol).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_serve import SIZES, make_bundle

USERS = 8


def add_users(bundle: Path, d: Path, n: int) -> list[Path]:
    keys = []
    for i in range(n):
        key = d / f"u{i}.bin"
        key.write_bytes(os.urandom(16))
        key.chmod(0o600)
        args = ["add-user", str(bundle), "--data", str(d / "mine.npz"), "--key-file", str(key), "--steps",
                "10", "--device", "cpu"]  # fmt: skip
        cmd = [sys.executable, "-c", "from prop_cli.cli.main import main; main()", *args]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
        keys.append(key)
    return keys


def make_act_users(d: Path, n: int) -> tuple[Path, list[str]]:
    """A tiny ACT sealed (LoRA rank 4) for ``n`` users in one personalize: (bundle, the keys as hex)."""
    from examples import lerobot_reach_task as task
    from prop_cli import api
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core.key_files import KeySource

    task.record(d / "general", 4, 0, np.zeros(3, np.float32))
    users = []
    for i in range(n):  # each user's goal moved its own way
        offset = task.USER_OFFSET * np.float32(1 + i / n) * (1 if i % 2 == 0 else -1)
        task.record(d / f"user{i}", 2, 50_000 + 1000 * i, offset.astype(np.float32))
        users.append((d / f"user{i}", KeySource(np.random.default_rng(i).integers(0, 2, 128).astype(np.uint8),
                                                 "file")))  # fmt: skip
    task.train_base(d / "general", d / "act", steps=5)
    cfg = PersonalizeConfig.of(seal=True, payload="lora", payload_rank=4, steps=10, user_rows=8)
    api.personalize_checkpoint(str(d / "act"), users, d / "b.prop", cfg)
    return d / "b.prop", [np.packbits(k.bits).tobytes().hex() for _, k in users]


def load(url: str, keys: list[str | None], seconds: float, features: dict) -> dict:
    cmd = [sys.executable, "-m", "benchmarks.bench_serve", "--client", url, json.dumps(keys), str(seconds),
           json.dumps(features)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180 + seconds)
    if done.returncode:
        raise SystemExit(done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def connect_meta(url: str, key: str | None) -> tuple[float, dict]:
    """Seconds from connecting to the server's metadata, and the metadata."""
    import msgpack
    from websockets.sync.client import connect

    headers = {"Authorization": f"Api-Key {key}"} if key else None
    t = time.perf_counter()
    with connect(url, additional_headers=headers, max_size=None, compression=None, open_timeout=60) as ws:
        meta = msgpack.unpackb(ws.recv(timeout=60))
    return time.perf_counter() - t, meta


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--replicas", type=int, default=2)
    ap.add_argument("--policy", choices=("mlp", "act"), default="mlp",
                    help="act: a tiny LeRobot ACT (lerobot and ray in one environment)")  # fmt: skip
    args = ap.parse_args()
    torch.set_num_threads(1)
    import ray
    from ray import serve

    from prop_cli.bundle import load_bundle
    from prop_cli.serve import PolicyServer, start_in_thread
    from prop_cli.serve.ray_app import APP_NAME, application

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        if args.policy == "act":
            bundle_path, keys = make_act_users(d, USERS)
        else:
            bundle_path, first = make_bundle(d)
            keys = [k.read_bytes().hex() for k in [first, *add_users(bundle_path, d, USERS - 1)]]
        bundle = load_bundle(bundle_path)
        policy = bundle.loaded.policy
        features = {k: list(s) for k, s in policy.input_features.items()} if policy is not None else {}
        model = ("tiny ACT (examples/lerobot_reach_task.py), one frame per request, its chunk per reply"
                 if policy is not None else f"tiny MLP {'-'.join(map(str, SIZES))}")  # fmt: skip
        modes = {n: (("(a) one user", [keys[0]] * n), (f"(b) {USERS} users", (keys * n)[:n]),
                     ("(c) no key", [None] * n)) for n in (1, 8)}  # fmt: skip
        load_avg = f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"
        print(f"prop serve-ray ({args.replicas} replicas, local Ray {ray.__version__}) against prop serve, "
              f"{model} sealed (LoRA r=4), {USERS} users, loopback, "
              f"{args.seconds:g} s per run, {load_avg}")  # fmt: skip
        results: dict = {}
        running = start_in_thread(PolicyServer(bundle, port=0, max_connections=64))
        try:
            for n, runs in modes.items():
                for mode, ks in runs:
                    results[("prop serve", n, mode)] = load(running.url, ks, args.seconds, features)
        finally:
            running.stop()
        port = free_port()
        t0 = time.perf_counter()
        ray.init(address="local", include_dashboard=False, num_cpus=os.cpu_count(), log_to_driver=False)
        try:
            serve.start(http_options={"host": "127.0.0.1", "port": port})
            serve.run(application(bundle_path, replicas=args.replicas, replica_cpus=0.5), name=APP_NAME,
                      route_prefix="/")  # fmt: skip
            url = f"ws://127.0.0.1:{port}"
            up = time.perf_counter() - t0
            cold, warm, held = [], [], []
            for k in keys:  # each user's first connection: a replica checks and decrypts its record
                cold.append(connect_meta(url, k)[0])
                time.sleep(0.2)  # the replica tells the routers what it holds every 0.1 s
            for _ in range(5):
                for k in keys:
                    s, meta = connect_meta(url, k)
                    warm.append(s)
                    held.append(bool(meta["held"]))
            for n, runs in modes.items():
                for mode, ks in runs:
                    results[("serve-ray", n, mode)] = load(url, ks, args.seconds, features)
        finally:
            serve.shutdown()
            ray.shutdown()
        print(f"Ray and the application up in {up:.1f} s")
        head = ("clients", "mode", "server", "req/s", "p50 ms", "p99 ms", "ray/serve")
        print("{:>7} {:<14} {:<11} {:>7} {:>7} {:>7} {:>9}".format(*head))
        for n, runs in modes.items():
            for mode, _ in runs:
                base = results[("prop serve", n, mode)]
                for server in ("prop serve", "serve-ray"):
                    r = results[(server, n, mode)]
                    rate = r["requests"] / r["seconds"]
                    ratio = rate / (base["requests"] / base["seconds"])
                    p50, p99 = r["p50_ms"], r["p99_ms"]
                    print(f"{n:>7} {mode:<14} {server:<11} {rate:>7.0f} {p50:>7.2f} {p99:>7.2f} "
                          f"{ratio if server == 'serve-ray' else 1:>8.2f}x")  # fmt: skip
        print(
            f"connect to metadata, serve-ray: first of a user (decrypt) p50 {1e3 * np.median(cold):.1f} ms; "
            f"later (held) p50 {1e3 * np.median(warm):.1f} ms, p99 {1e3 * np.percentile(warm, 99):.1f} ms"
        )
        print(f"later connections landing on a replica that holds the user: {sum(held)}/{len(held)}")


if __name__ == "__main__":
    main()
