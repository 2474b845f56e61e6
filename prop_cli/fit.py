"""Data against the model: does it fit, what task it is, the train/validation split, and a policy's
frames as the rows of its flat array view (``flat_dataset``).

The task is decided against the model, not by the dtype of ``y`` alone: a checkpoint whose adapter
says its outputs are continuous (a Box action space) is regression whatever ``y``'s dtype, one that
says discrete is classification; for the rest, integer labels (N,) for a model with several outputs
are classification and everything else regression. ``--task`` overrides it.
"""

from __future__ import annotations

import numpy as np
import torch

from prop_adapters.base import LoadedModel, PolicyProtocol
from prop_cli.datasources.base import Dataset
from prop_cli.errors import PropError, plural

# Targets this far outside a recorded action bound still count as inside (float32 round-off).
_BOUND_TOL = 1e-5


def check_features(
    ds: Dataset, input_shape: tuple[int, ...] | None, model_name: str, *, flag: str = "--data"
) -> None:
    """Refuse data whose per-sample shape is not what the model takes."""
    if input_shape is None or isinstance(ds.x, dict):
        return
    got, want = tuple(ds.x.shape[1:]), tuple(input_shape)
    if got == want:
        return
    if len(got) == 1 and len(want) == 1:
        detail = f"x has {got[0]} features per sample but the model {model_name} expects {want[0]}"
    else:
        detail = f"x has per-sample shape {got} but the model {model_name} expects {want}"
    raise PropError(f"{flag} {ds.path}: {detail}", "use data collected for this model")


def output_width(loaded: LoadedModel, ds: Dataset, flag: str) -> int:
    """Run the model on one sample: its output width, or a PropError if the inputs do not fit."""
    check_features(ds, loaded.input_shape, loaded.source, flag=flag)
    try:
        with torch.no_grad():
            out = loaded.module(torch.from_numpy(ds.x[:1]))
    except Exception as e:  # noqa: BLE001 - any failure here means the inputs do not fit the model
        raise PropError(
            f"{flag} {ds.path}: x of shape {tuple(ds.x.shape[1:])} does not fit the model "
            f"({type(e).__name__}: {str(e).splitlines()[0][:120]})",
            "give inputs of the shape the checkpoint was trained on",
        ) from e
    return int(out.shape[-1])


def resolve_task(y: np.ndarray, loaded: LoadedModel, width: int, override: str | None = None) -> str:
    """'classification' or 'regression' for targets ``y`` of this model (see the module docstring)."""
    if override is not None:
        return override
    if loaded.continuous is not None:
        return "regression" if loaded.continuous else "classification"
    labels = y.dtype.kind in "biu" and y.ndim == 1 and width > 1
    return "classification" if labels else "regression"


def _labels(ds: Dataset, width: int, flag: str) -> np.ndarray:
    y = ds.y
    where = f"{flag} {ds.path}: field 'y'"
    if y.ndim != 1:
        raise PropError(
            f"{where} (class labels) has shape {y.shape}; it must be (N,)",
            "use y.reshape(-1), or --task regression if these are targets",
        )
    if y.dtype.kind == "f" and not np.array_equal(y, np.round(y)):
        raise PropError(
            f"{where} holds non-integer values, but the model's {width} outputs are class logits",
            f"give class indices 0..{width - 1} (--task regression if the outputs are not classes)",
        )
    y = y.astype(np.int64)
    neg = int((y < 0).sum())
    if neg:
        raise PropError(f"{where} has {neg} negative class labels", "labels must be 0..classes-1")
    top = int(y.max()) if len(y) else -1
    if top >= width:
        raise PropError(
            f"{where} has class label {top} but the model has only {width} outputs (labels 0..{width - 1})",
            "relabel y, or use a model with more outputs",
        )
    return y


def _targets(ds: Dataset, loaded: LoadedModel, width: int, flag: str) -> np.ndarray:
    y = ds.y.astype(np.float32)
    where = f"{flag} {ds.path}: field 'y'"
    got = 1 if y.ndim == 1 else int(y.shape[1])
    if got != width:
        raise PropError(
            f"{where} has {got} target values per sample but the model has {width} outputs",
            f"give y shape (N, {width})",
        )
    if loaded.action_low is not None and loaded.action_high is not None:
        low, high = np.asarray(loaded.action_low), np.asarray(loaded.action_high)
        tol = _BOUND_TOL * np.maximum(1.0, np.maximum(np.abs(low), np.abs(high)))
        y2 = y.reshape(len(y), -1)
        out = (y2 < low - tol) | (y2 > high + tol)
        if out.any():
            row, col = (int(i) for i in np.argwhere(out)[0])
            raise PropError(
                f"{where} has {plural(int(out.sum()), 'value')} outside the action bounds the checkpoint "
                f"records (low {low.tolist()}, high {high.tolist()}; row {row}, output {col}: "
                f"{y2[row, col]:.4g})",
                "give actions in the environment's units, within the bounds (the policy cannot act outside)",
            )
    return y


def prepare(
    loaded: LoadedModel, ds: Dataset, flag: str = "--data", task: str | None = None
) -> tuple[Dataset, str | None]:
    """Check ``ds`` against the model; returns it with typed targets, and its task (None without y)."""
    width = output_width(loaded, ds, flag)
    if ds.y is None:
        return ds, None
    task = resolve_task(ds.y, loaded, width, task)
    y = _labels(ds, width, flag) if task == "classification" else _targets(ds, loaded, width, flag)
    return Dataset(ds.x, y, ds.path, dict(ds.meta)), task


def split(ds: Dataset, val_fraction: float, seed: int) -> tuple[Dataset, Dataset]:
    """Deterministic shuffled (train, validation) split; >= 1 validation sample if asked for."""
    if not 0.0 <= val_fraction < 1.0:
        raise PropError(f"--val-fraction {val_fraction} is out of range", "use a value in [0, 1), e.g. 0.2")
    n = len(ds)
    n_val = 0 if val_fraction == 0 else min(max(1, round(n * val_fraction)), n - 1)
    order = np.random.default_rng(seed).permutation(n)
    return ds.subset(order[n_val:]), ds.subset(order[:n_val])


def flat_chunks(policy: PolicyProtocol, batch: dict[str, torch.Tensor], path: str) -> Dataset:
    """A policy's batch -> x (N, F) normalised features and y (N, chunk * action_dim) recorded chunks
    (None without actions): the rows of the policy's flat view (``PolicyProtocol.flat_rows``)."""
    x = policy.flat_rows(batch).numpy().astype(np.float32)
    y = batch["action"].flatten(1).numpy().astype(np.float32) if "action" in batch else None
    return Dataset(x=x, y=y, path=path, meta={"episode_index": batch["episode_index"].numpy()})


def flat_dataset(policy: PolicyProtocol, data: Dataset, flag: str) -> Dataset:
    """A LeRobot Dataset as the flat view takes it; rows ordered by episode and frame, as the policy cuts
    its chunks (recorded chunks cut and padded as for training)."""
    return flat_chunks(policy, policy.batches(data, flag), data.path)
