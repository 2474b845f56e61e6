"""Datasets: ``.npz`` files with ``x`` (inputs) and ``y`` (targets), checked before training."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prop_cli.errors import PropError

SAVE_HINT = "save it with numpy.savez(path, x=inputs, y=targets)"


@dataclass
class Dataset:
    x: np.ndarray  # float32, (N, *features)
    y: np.ndarray | None  # int64 (N,) class labels, or float32 (N,) / (N, d) targets
    path: str

    @property
    def task(self) -> str | None:
        """'classification' for integer labels, 'regression' for float targets, None without y."""
        if self.y is None:
            return None
        return "classification" if self.y.dtype.kind in "iub" else "regression"

    def __len__(self) -> int:
        return int(self.x.shape[0])


def _nonfinite_rows(a: np.ndarray) -> int:
    if a.dtype.kind != "f":
        return 0
    bad = ~np.isfinite(a.reshape(a.shape[0], -1) if a.ndim > 1 else a.reshape(-1, 1))
    return int(bad.any(axis=1).sum())


def _field(npz, name: str, path: Path) -> np.ndarray:
    try:
        return np.asarray(npz[name])
    except ValueError:  # object arrays need pickle, which we never allow
        raise PropError(
            f"{path}: field '{name}' is an object array (needs pickle, which prop refuses)",
            f"store '{name}' as a numeric array; " + SAVE_HINT,
        ) from None


def load_npz(path: str | Path, *, require_y: bool = True, min_samples: int = 10) -> Dataset:
    """Read and validate a dataset; every problem is a PropError naming the file and the field."""
    path = Path(path)
    if not path.exists():
        raise PropError(f"data file {path} does not exist", "check the path")
    if path.is_dir():
        raise PropError(f"data file {path} is a directory", "pass an .npz file")
    try:
        npz = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise PropError(f"data file {path} is not a valid .npz ({type(e).__name__})", SAVE_HINT) from None
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

    if x.dtype.kind not in "biuf":
        raise PropError(f"{path}: field 'x' has dtype {x.dtype}, not numbers", SAVE_HINT)
    if x.ndim < 2:
        raise PropError(
            f"{path}: field 'x' has shape {x.shape}; it must be (samples, features...)",
            "for one feature per sample use x.reshape(-1, 1)",
        )
    x = x.astype(np.float32)
    bad = _nonfinite_rows(x)
    if bad:
        raise PropError(f"{path}: field 'x' has NaN or inf in {bad} rows", "drop or fix those rows")

    if y is not None:
        if y.dtype.kind not in "biuf":
            raise PropError(f"{path}: field 'y' has dtype {y.dtype}, not numbers", SAVE_HINT)
        if y.ndim == 0 or len(y) != len(x):
            n_y = "a scalar" if y.ndim == 0 else f"{len(y)} rows"
            raise PropError(
                f"{path}: field 'x' has {len(x)} rows but field 'y' has {n_y}",
                "give one target per input",
            )
        if y.dtype.kind == "f":
            y = y.astype(np.float32)
            bad = _nonfinite_rows(y)
            if bad:
                raise PropError(f"{path}: field 'y' has NaN or inf in {bad} rows", "drop or fix those rows")
            if y.ndim not in (1, 2):
                raise PropError(
                    f"{path}: field 'y' (regression targets) has shape {y.shape}; "
                    "it must be (N,) or (N, outputs)",
                    "reshape y to (N, outputs)",
                )
        else:
            if y.ndim != 1:
                raise PropError(
                    f"{path}: field 'y' (integer class labels) has shape {y.shape}; it must be (N,)",
                    "use y.reshape(-1), or store float targets for regression",
                )
            y = y.astype(np.int64)
            neg = int((y < 0).sum())
            if neg:
                raise PropError(
                    f"{path}: field 'y' has {neg} negative class labels",
                    "labels must be 0..classes-1",
                )

    if len(x) < min_samples:
        raise PropError(
            f"{path}: field 'x' has {len(x)} rows, fewer than the {min_samples} needed",
            "collect more samples",
        )
    return Dataset(x=x, y=y, path=str(path))


def check_features(
    ds: Dataset, input_shape: tuple[int, ...] | None, model_name: str, *, flag: str = "--data"
) -> None:
    """Refuse data whose per-sample shape is not what the model takes."""
    if input_shape is None:
        return
    got, want = tuple(ds.x.shape[1:]), tuple(input_shape)
    if got == want:
        return
    if len(got) == 1 and len(want) == 1:
        detail = f"x has {got[0]} features per sample but the model {model_name} expects {want[0]}"
    else:
        detail = f"x has per-sample shape {got} but the model {model_name} expects {want}"
    raise PropError(f"{flag} {ds.path}: {detail}", "use data collected for this model")


def check_targets(ds: Dataset, output_dim: int, *, flag: str = "--data") -> None:
    """Refuse labels the model has no output for, or targets of the wrong width."""
    if ds.y is None:
        return
    if ds.task == "classification":
        top = int(ds.y.max()) if len(ds.y) else -1
        if top >= output_dim:
            raise PropError(
                f"{flag} {ds.path}: field 'y' has class label {top} but the model has only "
                f"{output_dim} outputs (labels 0..{output_dim - 1})",
                "relabel y, or use a model with more outputs",
            )
        return
    width = 1 if ds.y.ndim == 1 else int(ds.y.shape[1])
    if width != output_dim:
        raise PropError(
            f"{flag} {ds.path}: field 'y' has {width} target values per sample but the model "
            f"has {output_dim} outputs",
            f"give y shape (N, {output_dim})",
        )


def split(ds: Dataset, val_fraction: float, seed: int) -> tuple[Dataset, Dataset]:
    """Deterministic shuffled (train, validation) split; >= 1 validation sample if asked for."""
    if not 0.0 <= val_fraction < 1.0:
        raise PropError(f"--val-fraction {val_fraction} is out of range", "use a value in [0, 1), e.g. 0.2")
    n = len(ds)
    n_val = 0 if val_fraction == 0 else min(max(1, round(n * val_fraction)), n - 1)
    order = np.random.default_rng(seed).permutation(n)
    val_idx, train_idx = order[:n_val], order[n_val:]

    def take(idx: np.ndarray) -> Dataset:
        return Dataset(x=ds.x[idx], y=None if ds.y is None else ds.y[idx], path=ds.path)

    return take(train_idx), take(val_idx)
