"""Opening a key among many sealed users (issue 39): format 6's lookup names against format 5's trials.

    python -m benchmarks.bench_lookup [--users 1,100,1000,10000] [--reps 400] [--baseline-max 10000]
    .venv-lerobot/bin/python -m benchmarks.bench_lookup --model act [...]

A tiny MLP (4-16-16-2) is personalized sealed for one user (LoRA rank 4, 40 steps), or with ``--model
act`` the tests' tiny ACT (tests/plugin/tiny.py: resnet18 backbone, LoRA rank 4 on 7 layers, 10 steps;
41 kB records); the bundle then
grows to each ``--users`` count: each new user's record is what `prop add-user` writes (their key's
payload sealed with the bundle's behaviour against the next version, filed under their key's lookup
name, the file in users/, the manifest entry; one manifest write per step of growth), with the first
user's payload, so no training is repeated. At each size, on the bundle (format 6) and on a copy of it as
format 5 wrote it (the same records without names: every key tries every record; up to
``--baseline-max`` users):

- add-user: one real `prop_cli.api.add_user` (MLP: training 40 steps on 200 rows, its report's 1 + 64
  random + 128 one-bit-neighbour keys run through the records, the record and the manifest written), timed
  whole; the user is removed again (`remove_user --record`) so the next size starts from its count;
- open: ``SealedState.open`` of the key of a user drawn at random, ``--reps`` times (format 5: at most
  50,000 / users, at least 5): p50 / p99 in ms;
  and load + open (``load_bundle`` then ``mode.payload_for``, what `prop run` does before its forward),
  p50 of 5;
- first / middle / last user and a key enrolled in nothing: ``SealedState.open``, interleaved in a
  shuffled order, median of ``--reps`` each; and the same for ``SealedState.find``, the work up to the
  decision (name, lookup, the record or stand-in read, checked and decrypted), before a key that opens
  its record has its payload decoded and built;
- bundle size on disk (every file) and manifest size; `prop inspect` (a subprocess, Python start
  included) and ``describe_bundle`` in process (what inspect checks: every record's sha256).

Times depend on the machine's load: compare rows of one run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from prop_cli import constants as C
from prop_cli.api import KeySource, PersonalizeConfig, add_user, personalize_checkpoint, remove_user
from prop_cli.bundle import load_bundle
from prop_cli.bundle.describe import describe_bundle
from prop_cli.bundle.manifest import next_version, stamp
from prop_cli.bundle.records import rewrite_records, seal_payload, with_records
from prop_cli.files import dump_json

STEPS = 40


def _keys(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    return [rng.integers(0, 2, 128).astype(np.uint8) for _ in range(n)]


def grow(bundle: Path, first: np.ndarray, keys: list[np.ndarray]) -> None:
    """Add ``keys``' users to ``bundle`` as add-user writes them (their payload: the first user's)."""
    b = load_bundle(bundle)
    opened = b.records.open(first)
    m = b.manifest
    future = next_version(m)
    recs = [seal_payload(future, opened.meta, opened.payload, k) for k in keys]
    rewrite_records(bundle, m, with_records(m, recs, []), recs)


def as_format_5(src: Path, dst: Path) -> None:
    """A copy of ``src`` as format 5 wrote it: the same records, no lookup names."""
    shutil.copytree(src, dst)
    inodes: dict[tuple[int, int], Path] = {}
    for f in sorted(p for p in src.rglob("*") if p.is_file()):  # hard links stay links (LeRobot's alias)
        st = f.stat()
        first = inodes.setdefault((st.st_dev, st.st_ino), f)
        if first != f:
            (dst / f.relative_to(src)).unlink()
            os.link(dst / first.relative_to(src), dst / f.relative_to(src))
    m = json.loads((dst / C.MANIFEST).read_text())
    m[C.M_FORMAT] = 5
    for e in m[C.M_RECORDS]:
        e.pop(C.M_LOOKUP, None)
    (dst / C.MANIFEST).write_text(dump_json(stamp(m)))


def _size(path: Path) -> int:
    """Bytes on disk, a hard-linked file once (a LeRobot bundle's lerobot/model.safetensors)."""
    seen = {(s.st_dev, s.st_ino): s.st_size for s in (f.stat() for f in path.rglob("*") if f.is_file())}
    return sum(seen.values())


def _ms(ts: list[float], q: float) -> float:
    return float(np.quantile(np.array(ts), q)) * 1e3


def measure(bundle: Path, keys: list[np.ndarray], data: Path, reps: int, rng: np.random.Generator) -> dict:
    n = len(keys)
    row: dict = {"reps": reps}
    new = KeySource(_keys(1, rng)[0], "file")
    t = time.perf_counter()
    change = add_user(bundle, data, new)
    row["add_user_s"] = time.perf_counter() - t
    remove_user(bundle, record=change.record)
    state = load_bundle(bundle).records
    state.open(keys[0])  # warm: imports, the first file read
    ts = []
    for i in rng.integers(0, n, reps):
        t = time.perf_counter()
        state.open(keys[i])
        ts.append(time.perf_counter() - t)
    row["open_p50_ms"], row["open_p99_ms"] = _ms(ts, 0.5), _ms(ts, 0.99)
    loads = []
    for i in rng.integers(0, n, 5):
        t = time.perf_counter()
        load_bundle(bundle).mode.payload_for(keys[i])
        loads.append(time.perf_counter() - t)
    row["load_open_ms"] = statistics.median(loads) * 1e3
    wrong = _keys(1, rng)[0]
    cases = {"first": keys[0], "middle": keys[n // 2], "last": keys[-1], "nothing": wrong}
    for what, call in (("", state.open), ("find_", state.find)):
        times: dict[str, list[float]] = {c: [] for c in cases}
        order = list(cases)
        for _ in range(reps):
            rng.shuffle(order)
            for c in order:
                t = time.perf_counter()
                call(cases[c])
                times[c].append(time.perf_counter() - t)
        for c, v in times.items():
            row[f"{what}{c}_ms"] = statistics.median(v) * 1e3
    row["size_mb"] = _size(bundle) / 1e6
    row["manifest_kb"] = (bundle / C.MANIFEST).stat().st_size / 1e3
    t = time.perf_counter()
    describe_bundle(bundle)
    row["describe_s"] = time.perf_counter() - t
    t = time.perf_counter()
    cmd = [sys.executable, "-m", "prop_cli.cli.main", "inspect", str(bundle)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    row["inspect_s"] = time.perf_counter() - t
    assert r.returncode == 0, r.stderr
    return row


COLUMNS = [
    ("add_user_s", "add-user s", "{:.2f}"),
    ("open_p50_ms", "open p50 ms", "{:.3f}"),
    ("open_p99_ms", "open p99 ms", "{:.3f}"),
    ("load_open_ms", "load + open ms", "{:.0f}"),
    ("first_ms", "first ms", "{:.3f}"),
    ("middle_ms", "middle ms", "{:.3f}"),
    ("last_ms", "last ms", "{:.3f}"),
    ("nothing_ms", "enrolled in nothing ms", "{:.3f}"),
    ("find_first_ms", "to the decision: first / middle / last / nothing ms", "{:.3f}"),
    ("size_mb", "bundle MB", "{:.2f}"),
    ("manifest_kb", "manifest kB", "{:.0f}"),
    ("inspect_s", "prop inspect s", "{:.2f}"),
    ("describe_s", "describe_bundle s", "{:.3f}"),
]


def _cell(r: dict, k: str, f: str) -> str:
    if k == "find_first_ms":  # one column: the four keys' times up to the decision (``find``)
        return " / ".join(f.format(r[f"find_{c}_ms"]) for c in ("first", "middle", "last", "nothing"))
    return f.format(r[k]) if k in r else "-"


def table(rows: list[dict]) -> str:
    head = "| users | format | reps | " + " | ".join(h for _, h, _ in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 3)]
    for r in rows:
        cells = [_cell(r, k, f) for k, _, f in COLUMNS]
        lines.append(f"| {r['users']:,} | {r['format']} | {r['reps']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _mlp(root: Path, rng: np.random.Generator) -> tuple[Path, np.ndarray, Path]:
    """(a sealed bundle of the tiny MLP for one user, their key, data for add-user)."""
    from tests.conftest import make_mlp_checkpoint

    make_mlp_checkpoint(root / "m.safetensors")
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(root / "d.npz", x=x, y=-x[:, :2])
    key = _keys(1, rng)[0]
    cfg = PersonalizeConfig.of(steps=STEPS, seal=True)
    personalize_checkpoint(str(root / "m.safetensors"), [(root / "d.npz", KeySource(key, "file"))],
                           root / "b.prop", cfg)  # fmt: skip
    return root / "b.prop", key, root / "d.npz"


def _act(root: Path, rng: np.random.Generator) -> tuple[Path, np.ndarray, Path]:
    """The same for the tests' tiny ACT (tests/plugin/tiny.py; needs .venv-lerobot)."""
    from prop_cli.core.key_files import read_key_file
    from tests.plugin.tiny import build

    build(root / "act")
    return root / "act" / "sealed", read_key_file(root / "act" / "user.key"), root / "act" / "user"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--users", default="1,100,1000,10000")
    ap.add_argument("--reps", type=int, default=400)
    ap.add_argument("--baseline-max", type=int, default=10000, help="format 5 copies up to this many users")
    ap.add_argument("--model", choices=("mlp", "act"), default="mlp")
    args = ap.parse_args()
    sizes = sorted(int(s) for s in args.users.split(","))

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        os.environ[C.ENV_STATE_DIR] = str(root / "state")  # the versions seen: not the user's own
        rng = np.random.default_rng(0)
        bundle, first, data = (_mlp if args.model == "mlp" else _act)(root, rng)
        keys = [first]
        for n in sizes:
            t = time.perf_counter()
            more = _keys(n - len(keys), rng)
            grow(bundle, keys[0], more) if more else None
            keys += more
            print(f"{n} users: grown in {time.perf_counter() - t:.1f} s", file=sys.stderr, flush=True)
            rows.append({"users": n, "format": 6, **measure(bundle, keys, data, args.reps, rng)})
            print(table(rows[-1:]), file=sys.stderr, flush=True)
            if n <= args.baseline_max:
                old = root / f"old-{n}.prop"
                as_format_5(bundle, old)
                reps = max(5, min(args.reps, 50_000 // n))  # every key tries every record: fewer reps
                rows.append({"users": n, "format": 5, **measure(old, keys, data, reps, rng)})
                print(table(rows[-1:]), file=sys.stderr, flush=True)
                shutil.rmtree(old)
    print(table(rows))


if __name__ == "__main__":
    main()
