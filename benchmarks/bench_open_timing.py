"""How long a key takes to open a sealed bundle's records, by which record it opens (or none).

    python -m benchmarks.bench_open_timing [--records 3] [--reps 3000]

A sealed bundle of one user is personalized (a tiny MLP, 40 steps), then its record's plaintext is
sealed again for other keys, without lookup names (as format 1-5 wrote records; format 6 files each
record under its key's name: benchmarks/bench_lookup.py), so that the bundle holds ``--records``
records and the user's key opens each position in turn. Timed: ``SealedState.open`` (every trial
decryption, then the decoding of the payload that opened) for a key enrolled in nothing and for the key
of each record, interleaved, each ``--reps`` times in a shuffled order; the median in microseconds.
Until 0.2 the first record that opened ended the trials, so a key's time told which record it opened;
now every record is tried on every key.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from prop_cli import constants as C
from prop_cli.api import KeySource, PersonalizeConfig, personalize_checkpoint
from prop_cli.bundle import load_bundle
from prop_cli.bundle.cipher import open_record, seal
from prop_cli.bundle.records import SealedState, read_record, record_ad


def _state(root: Path, records: int) -> tuple[SealedState, list[np.ndarray]]:
    """A sealed bundle's records: the user's at position 0 plus re-sealed copies for other keys."""
    from tests.conftest import make_mlp_checkpoint

    rng = np.random.default_rng(0)
    make_mlp_checkpoint(root / "m.safetensors")
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(root / "d.npz", x=x, y=-x[:, :2])
    keys = [rng.integers(0, 2, 128).astype(np.uint8) for _ in range(records)]
    cfg = PersonalizeConfig.of(steps=40, seal=True)
    personalize_checkpoint(str(root / "m.safetensors"), [(root / "d.npz", KeySource(keys[0], "file"))],
                           root / "b.prop", cfg)  # fmt: skip
    state = load_bundle(root / "b.prop").records
    entry = state.manifest[C.M_RECORDS][0]
    rec = replace(state.records[0], ciphertext=read_record(root / "b.prop", entry), lookup=None)
    plaintext = open_record(rec, keys[0], record_ad(state.manifest, rec.id))
    others = [seal(plaintext, k, lambda rid: record_ad(state.manifest, rid)) for k in keys[1:]]
    return SealedState(state.manifest, state.spec, [rec, *others]), keys


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=3)
    ap.add_argument("--reps", type=int, default=3000)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        state, keys = _state(Path(tmp), args.records)
        wrong = np.random.default_rng(99).integers(0, 2, 128).astype(np.uint8)
        cases = {"enrolled in nothing": wrong, **{f"opens record {i}": k for i, k in enumerate(keys)}}
        times: dict[str, list[float]] = {c: [] for c in cases}
        order = list(cases)
        rng = np.random.default_rng(1)
        for _ in range(args.reps):
            rng.shuffle(order)  # no case always follows another (caches, the allocator)
            for case in order:
                bits = cases[case]
                t = time.perf_counter()
                state.open(bits)
                times[case].append(time.perf_counter() - t)
    print(f"SealedState.open, {args.records} records, median of {args.reps}:")
    for case, ts in times.items():
        print(f"  {case:<22} {statistics.median(ts) * 1e6:8.1f} us")


if __name__ == "__main__":
    main()
