"""Example tasks that generate data and train a base checkpoint for PRoP demos, tests, benchmarks.

Shared helper: `save_npz`, a byte-reproducible replacement for `np.savez` (numpy stamps each
zip member with the current time, so two identical runs would differ on disk).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

# Fixed zip timestamp (the earliest zip allows) so the same arrays give the same bytes.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Write arrays to an uncompressed .npz readable by np.load, deterministically."""
    path = Path(path)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.external_attr = 0o644 << 16  # regular file, fixed permissions
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.ascontiguousarray(arr), allow_pickle=False)
    return path


__all__ = ["save_npz"]
