"""Issue 42, the last item: what reading and writing through descriptors costs (``files.read``,
``files.sha256_inside``, ``files.staged_dir``: each folder below the bundle opened with O_NOFOLLOW)
against the path-based reads and the mkdtemp/rename staging they replaced, measured in one run on one
machine. Prints each as a ratio to its baseline.

    PYTHONPATH=$PWD python -m benchmarks.bench_dir_fd
"""

import os
import shutil
import tempfile
import time
from pathlib import Path

from prop_cli.files import read, sha256_file, sha256_inside, staged_dir


def best(fn, repeat: int = 5) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def staged_by_path(out: Path) -> None:
    """The staging as it was: mkdtemp beside ``out``, one file, os.replace (no old output)."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.resolve().parent))
    (tmp / "f").write_bytes(b"x" * 1024)
    os.replace(tmp, out)


def staged_by_descriptor(out: Path) -> None:
    with staged_dir(out) as tmp:
        (tmp / "f").write_bytes(b"x" * 1024)


d = Path(tempfile.mkdtemp(prefix="prop-bench-dirfd-"))
n = 2000  # records of a sealed bundle, 2 KB each, read one by one (as users/<id>.sealed)
(d / "users").mkdir()
for i in range(n):
    (d / "users" / f"{i:016x}.sealed").write_bytes(os.urandom(2048))
names = [f"users/{i:016x}.sealed" for i in range(n)]
(d / "base.safetensors").write_bytes(os.urandom(256 << 20))  # a 256 MiB base, hashed whole

rows = [
    (
        "read 2,000 records",
        lambda: [(d / r).read_bytes() for r in names],
        lambda: [read(d, r) for r in names],
    ),
    (
        "sha256 of a 256 MiB base",
        lambda: sha256_file(d / "base.safetensors"),
        lambda: sha256_inside(d, "base.safetensors"),
    ),
]
for label, by_path, by_fd in rows:
    a, b = best(by_path), best(by_fd)
    print(f"{label}: by path {a * 1e3:.1f} ms, through descriptors {b * 1e3:.1f} ms, ratio {b / a:.2f}")

outs = d / "outs"
outs.mkdir()
k = 200
a = best(lambda: [staged_by_path(outs / f"p{time.perf_counter_ns()}") for _ in range(k)], 3)
b = best(lambda: [staged_by_descriptor(outs / f"q{time.perf_counter_ns()}") for _ in range(k)], 3)
print(
    f"stage and rename 200 folders: by path {a * 1e3:.1f} ms, through descriptors {b * 1e3:.1f} ms, "
    f"ratio {b / a:.2f}"
)
shutil.rmtree(d)
