"""Stable-Baselines3 ``VecNormalize`` observation statistics, read from its pickle without running it.

SB3 saves ``VecNormalize`` with ``pickle.dump(self)``: there is no other file to read. The house rule
is never to unpickle an untrusted file, so this is not unpickling in the usual sense: a restricted
``pickle.Unpickler`` whose ``find_class`` hands out real objects for exactly three things (numpy's
array rebuild, ``numpy.dtype``, numpy scalars) and ``collections.OrderedDict``; every other global the
pickle names (SB3's ``VecNormalize`` and ``RunningMeanStd``, gymnasium spaces, numpy's RNG, or
``os.system``) becomes an inert record of the arguments and state it is given: nothing is imported,
constructed or called. Object-dtype arrays are refused (their payload would be arbitrary objects), as
are files over ``MAX_BYTES``. What remains is plain data: ``obs_rms`` mean/var (per key for Dict
observations), ``clip_obs``, ``epsilon``, ``norm_obs`` and ``norm_obs_keys``.

Normalisation is SB3's ``VecNormalize.normalize_obs``: ``clip((obs - mean) / sqrt(var + epsilon),
-clip_obs, clip_obs)`` in float64, cast to float32; for Dict observations only ``norm_obs_keys``.
"""

from __future__ import annotations

import collections
import io
import math
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from prop_cli.errors import PropError, brief

MAX_BYTES = 64 << 20  # a VecNormalize pickle is kilobytes; refuse anything that could exhaust memory
_CLASS = "stable_baselines3.common.vec_env.vec_normalize.VecNormalize"
_RMS = "stable_baselines3.common.running_mean_std.RunningMeanStd"
FIX = "pass the file written by VecNormalize.save() (stable-baselines3) for this policy's environment"


class _Inert:
    """Every global that is not allow-listed: instantiated, called or built, it only records."""

    qualname = "?"

    def __new__(cls, *args, **kwargs):
        obj = object.__new__(cls)
        obj.args, obj.state, obj.items = args, None, {}
        return obj

    def __init__(self, *args, **kwargs) -> None:  # REDUCE calls the class: nothing runs
        pass

    def __setstate__(self, state) -> None:  # BUILD keeps the state, sets no attribute from it
        self.state = state

    def __setitem__(self, key, value) -> None:  # SETITEMS on a dict subclass
        self.items[key] = value


class _Array:
    """What numpy's ``_reconstruct`` returns here: an empty array that takes ``__setstate__`` only for
    plain (non-object) dtypes, so the bytes it is filled with stay bytes."""

    def __init__(self) -> None:
        self.array: np.ndarray | None = None

    def __setstate__(self, state) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise pickle.UnpicklingError("an array state that is not numpy's")
        dtype, raw = state[-3], state[-1]
        if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(raw, bytes):
            raise pickle.UnpicklingError("an object array (refused: it would hold arbitrary objects)")
        arr = np.ndarray((0,), np.uint8)
        arr.__setstate__(state)
        self.array = arr


def _reconstruct(subtype, shape, code) -> _Array:
    # numpy pickles every array as _reconstruct(ndarray, (0,), b'b') + BUILD; the subtype is ignored
    # (never instantiated) and nothing else is accepted, so no call here allocates more than the file.
    if not isinstance(shape, tuple) or shape != (0,):
        raise pickle.UnpicklingError("an array rebuilt with a shape numpy never writes")
    return _Array()


def _scalar(dtype, raw=None):
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(raw, bytes):
        raise pickle.UnpicklingError("a numpy scalar that is not a plain number")
    return np.frombuffer(raw, dtype, count=1)[0]


_ALLOWED = {
    **{(m, "_reconstruct"): _reconstruct for m in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(m, "scalar"): _scalar for m in ("numpy.core.multiarray", "numpy._core.multiarray")},
    ("numpy", "dtype"): np.dtype,
    ("collections", "OrderedDict"): collections.OrderedDict,
}


class _InertUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        allowed = _ALLOWED.get((module, name))
        if allowed is not None:
            return allowed
        return type(name, (_Inert,), {"qualname": f"{module}.{name}"})

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("persistent ids are not part of a VecNormalize pickle")


def _plain(x):
    """The unpickled tree as dicts, lists, numbers and arrays; inert objects as {"__global__", state}."""
    if isinstance(x, _Array):
        return x.array
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, _Inert):
        state = x.state if isinstance(x.state, dict) else {}
        return {"__global__": x.qualname, **{k: _plain(v) for k, v in {**x.items, **state}.items()}}
    return x


@dataclass
class ObsNormalizer:
    """SB3's observation normalisation: mean/var per observation key (``None`` for a Box)."""

    mean: dict[str | None, np.ndarray]
    var: dict[str | None, np.ndarray]
    clip_obs: float
    epsilon: float
    keys: list[str] | None = None  # Dict observations: the keys normalised (norm_obs_keys)
    source: str = ""
    enabled: bool = field(default=True)  # norm_obs: False = observations pass through

    def __call__(self, obs):
        if not self.enabled:
            return obs
        if self.keys is None:
            if isinstance(obs, dict):
                raise PropError(
                    f"{self.source} normalises one array, the environment gives dict observations", FIX
                )
            return self._one(obs, None)
        if not isinstance(obs, dict):
            raise PropError(
                f"{self.source} normalises dict observations, the environment gives one array", FIX
            )
        missing = [k for k in self.keys if k not in obs]
        if missing:
            raise PropError(
                f"{self.source} normalises {missing}, which the environment's observation lacks", FIX
            )
        return {k: (self._one(v, k) if k in self.keys else v) for k, v in obs.items()}

    def _one(self, obs, key: str | None) -> np.ndarray:
        obs = np.asarray(obs)
        mean, var = self.mean[key], self.var[key]
        if mean.ndim and obs.shape[-mean.ndim :] != mean.shape:
            where = f"key {key!r}: " if key is not None else ""
            raise PropError(
                f"{self.source}: {where}statistics of shape {mean.shape}, observation of shape {obs.shape}",
                FIX,
            )
        z = np.clip((obs - mean) / np.sqrt(var + self.epsilon), -self.clip_obs, self.clip_obs)
        return z.astype(np.float32)


def _number(state: dict, name: str, path: Path) -> float:
    v = state.get(name)
    try:
        v = float(v)  # a Python float, or a numpy scalar rebuilt by _scalar
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v):
        raise PropError(f"{path}: VecNormalize field '{name}' is missing or not a finite number", FIX)
    return v


def _rms(node, what: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(node, dict) or node.get("__global__") != _RMS:
        raise PropError(f"{path}: {what} is not a RunningMeanStd", FIX)
    mean, var = node.get("mean"), node.get("var")
    ok = isinstance(mean, np.ndarray) and isinstance(var, np.ndarray) and mean.shape == var.shape
    if ok and mean.dtype.kind == "f" and var.dtype.kind == "f":
        mean, var = mean.astype(np.float64), var.astype(np.float64)
        if np.isfinite(mean).all() and np.isfinite(var).all() and (var >= 0).all():
            return mean, var
    raise PropError(f"{path}: {what} mean/var are not finite float arrays of one shape (var >= 0)", FIX)


def read_vecnormalize(path: Path) -> ObsNormalizer:
    """The observation statistics in ``path`` (``VecNormalize.save``); never runs the pickle's code."""
    path = Path(path)
    if not path.is_file():
        raise PropError(f"--vecnormalize {path} does not exist", "check the path")
    if path.stat().st_size > MAX_BYTES:
        raise PropError(
            f"--vecnormalize {path} is over {MAX_BYTES >> 20} MiB: not a VecNormalize pickle", FIX
        )
    try:
        raw = _InertUnpickler(io.BytesIO(path.read_bytes())).load()
        top = _plain(raw)
    except Exception as e:  # noqa: BLE001 - every malformed or hostile pickle ends here, one line
        raise PropError(
            f"--vecnormalize {path} is not a VecNormalize pickle prop can read ({brief(e)})", FIX
        ) from None
    if not isinstance(top, dict) or top.get("__global__") != _CLASS:
        found = top.get("__global__") if isinstance(top, dict) else type(top).__name__
        raise PropError(f"--vecnormalize {path} holds {found}, not SB3's VecNormalize", FIX)
    obs_rms = top.get("obs_rms")
    keys = top.get("norm_obs_keys")
    stats: dict[str | None, tuple[np.ndarray, np.ndarray]]
    if isinstance(obs_rms, dict) and "__global__" not in obs_rms:  # Dict observations: one per key
        if not isinstance(keys, list) or not all(isinstance(k, str) and k in obs_rms for k in keys):
            raise PropError(f"{path}: norm_obs_keys is not a list of the keys obs_rms holds", FIX)
        stats = {k: _rms(obs_rms[k], f"obs_rms[{k!r}]", path) for k in keys}
    else:
        stats, keys = {None: _rms(obs_rms, "obs_rms", path)}, None
    clip = _number(top, "clip_obs", path)
    if clip <= 0:
        raise PropError(f"{path}: VecNormalize clip_obs must be positive (found {clip})", FIX)
    return ObsNormalizer(
        mean={k: m for k, (m, _) in stats.items()},
        var={k: v for k, (_, v) in stats.items()},
        clip_obs=clip,
        epsilon=_number(top, "epsilon", path),
        keys=keys,
        source=str(path),
        enabled=top.get("norm_obs") is not False,
    )
