"""``.npz`` files with ``x`` (inputs) and ``y`` (targets), written by ``numpy.savez``."""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from prop_cli.errors import PropError, plural

from .base import Dataset, DataSource

SAVE_HINT = "save it with numpy.savez(path, x=inputs, y=targets)"


def _nonfinite_rows(a: np.ndarray) -> int:
    if a.dtype.kind != "f" or a.size == 0:
        return 0
    bad = ~np.isfinite(a.reshape(a.shape[0], -1) if a.ndim > 1 else a.reshape(-1, 1))
    return int(bad.any(axis=1).sum())


def read_npy(
    read: Callable[[], object],
    what: str,
    fix: str = SAVE_HINT,
    problem: str = "is corrupt or not numpy data",
    pickled: str | None = "is an object array (needs pickle, which prop refuses)",
) -> object:
    """``read()`` (an ``np.load`` or an npz member) with numpy's and zipfile's errors as a PropError.

    A damaged file fails in many ways (zipfile.BadZipFile for a bad CRC, zlib.error, EOFError, a
    ValueError or SyntaxError from a mangled .npy header, MemoryError from a header claiming a huge
    shape), so everything but an interrupt becomes the one message.
    """
    try:
        return read()
    except ValueError as e:
        if pickled and "allow_pickle" in str(e):  # object arrays need pickle, which we never allow
            raise PropError(f"{what} {pickled}", fix) from None
        raise PropError(f"{what} {problem} ({type(e).__name__})", fix) from None
    except Exception as e:  # noqa: BLE001 - see the docstring
        raise PropError(f"{what} {problem} ({type(e).__name__})", fix) from None


def _field(npz, name: str, path: Path) -> np.ndarray:
    fix = f"store '{name}' as a numeric array; " + SAVE_HINT
    return np.asarray(read_npy(lambda: npz[name], f"{path}: field '{name}'", fix))


def _numbers(a: np.ndarray, name: str, path: Path) -> None:
    if a.dtype.kind not in "biuf":
        raise PropError(f"{path}: field '{name}' has dtype {a.dtype}, not numbers", SAVE_HINT)
    bad = _nonfinite_rows(a)
    if bad:
        raise PropError(
            f"{path}: field '{name}' has NaN or inf in {plural(bad, 'row')}", "drop or fix those rows"
        )


class NpzSource(DataSource):
    name = "npz"
    summary = "an .npz with x (inputs, (N, ...)) and y (targets: (N,) or (N, outputs)), from numpy.savez"

    def recognise(self, path: Path) -> bool:
        return path.suffix.lower() in (".npz", ".npy") or (path.is_file() and zipfile.is_zipfile(path))

    def load(self, path: Path, *, require_y: bool = True, min_samples: int = 10) -> Dataset:
        npz = read_npy(
            lambda: np.load(path, allow_pickle=False),
            f"data file {path}",
            problem="is not a valid .npz",
            pickled=None,
        )
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise PropError(f"data file {path} holds a single array, not an .npz with x and y", SAVE_HINT)
        with npz:
            fields = list(npz.files)
            if "x" not in fields:
                raise PropError(f"{path} has no field 'x' (fields: {', '.join(fields) or 'none'})", SAVE_HINT)
            x = _field(npz, "x", path)
            y = _field(npz, "y", path) if "y" in fields else None
        if y is None and require_y:
            raise PropError(
                f"{path} has no field 'y' (fields: {', '.join(fields)})",
                "add the targets you want under your key: " + SAVE_HINT,
            )
        _numbers(x, "x", path)
        if x.ndim < 2:
            raise PropError(
                f"{path}: field 'x' has shape {x.shape}; it must be (samples, features...)",
                "for one feature per sample use x.reshape(-1, 1)",
            )
        if y is not None:
            _numbers(y, "y", path)
            if y.ndim == 0 or len(y) != len(x):
                n_y = "a scalar" if y.ndim == 0 else plural(len(y), "row")
                raise PropError(
                    f"{path}: field 'x' has {plural(len(x), 'row')} but field 'y' has {n_y}",
                    "give one target per input",
                )
            if y.ndim > 2:
                raise PropError(
                    f"{path}: field 'y' has shape {y.shape}; it must be (N,) or (N, outputs)",
                    "reshape y to (N, outputs)",
                )
            y = y.astype(np.int64) if y.dtype.kind in "biu" else y.astype(np.float32)
        if len(x) < min_samples:
            raise PropError(
                f"{path}: field 'x' has {plural(len(x), 'row')}, fewer than the {min_samples} needed",
                "collect more samples",
            )
        return Dataset(x=x.astype(np.float32), y=y, path=str(path))
