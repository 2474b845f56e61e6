"""Reading a Stable-Baselines3 model zip without unpickling anything, and without SB3.

An SB3 zip holds ``data`` (JSON; fields that are not JSON-serialisable are cloudpickled, and next to
each blob SB3 writes the object's plain attributes and ``str()`` of the rest: we read only those plain
values) and ``policy.pth`` (a state dict, read with ``weights_only=True``). What this module returns
is plain data: the policy family, spaces, bounds, activation name and the state dict.
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
from pathlib import Path

import torch

from prop_adapters.weights import ZIP_ERRORS, load_state_dict, verify_zip
from prop_cli.errors import PropError, brief

SUPPORTED = (
    "PPO and A2C (Box or Discrete actions), SAC, TD3 and DDPG (Box actions): MlpPolicy (Box observations), "
    "CnnPolicy (uint8 image observations, NatureCNN) and MultiInputPolicy (Dict of Box observations), "
    "without gSDE or a custom features extractor"
)
# The module SB3 defines each policy family in, and its classes: class name -> features extractor kind
# ("flatten": MlpPolicy, "cnn": NatureCNN, "combined": CombinedExtractor).
_FAMILIES = {
    "stable_baselines3.common.policies": (
        "actor_critic",
        {
            "ActorCriticPolicy": "flatten",
            "ActorCriticCnnPolicy": "cnn",
            "MultiInputActorCriticPolicy": "combined",
        },
    ),
    "stable_baselines3.sac.policies": (
        "sac",
        {"SACPolicy": "flatten", "CnnPolicy": "cnn", "MultiInputPolicy": "combined"},
    ),
    "stable_baselines3.td3.policies": (
        "td3",
        {"TD3Policy": "flatten", "CnnPolicy": "cnn", "MultiInputPolicy": "combined"},
    ),
}
# Features extractors prop rebuilds, as policy_kwargs writes their class.
_EXTRACTORS = ("FlattenExtractor", "NatureCNN", "CombinedExtractor")
SAVE_HINT = "pass the .zip written by model.save() of a Stable-Baselines3 model"


def unsupported(path: str, what: str) -> PropError:
    return PropError(f"{path}: {what} is not supported", f"prop reads {SUPPORTED}")


# What an SB3 zip may inflate to, all members together: its float tensors barely compress (measured 1.0-1.1
# times their zip size), so this leaves room for any model, and refuses a zip bomb (a 1 MB member that
# inflates to 1 GiB) before anything is inflated.
INFLATE_SLACK = 64 << 20
INFLATE_RATIO = 8


def inflate_budget(size: int) -> int:
    """How many bytes the members of an SB3 zip of ``size`` bytes may inflate to, together."""
    return INFLATE_SLACK + INFLATE_RATIO * size


def _too_big(path: Path, inflated: int, budget: int, size: int) -> PropError:
    return PropError(
        f"{path}: its members inflate to {inflated} bytes or more, over the {budget} a Stable-Baselines3 "
        f"zip of {size} bytes may hold ({INFLATE_SLACK >> 20} MiB + {INFLATE_RATIO} x its size): it may be "
        "a zip bomb; nothing was inflated past that",
        SAVE_HINT,
    )


def _read(z: zipfile.ZipFile, name: str, left: list[int], path: Path, budget: int, size: int) -> bytes:
    """Member ``name``, inflated in 1 MiB steps and stopped where the budget still ``left`` runs out
    (whatever its header claims)."""
    parts = []
    with z.open(name) as member:
        while chunk := member.read(1 << 20):
            left[0] -= len(chunk)
            if left[0] < 0:
                raise _too_big(path, budget - left[0], budget, size)
            parts.append(chunk)
    return b"".join(parts)


def read_zip(path: Path) -> tuple[dict, dict[str, torch.Tensor], str | None]:
    """``data`` as JSON, the ``policy.pth`` state dict and the SB3 version string; never unpickles.
    The members are inflated under a budget (``inflate_budget``): sizes the zip declares past it are
    refused before anything is inflated, and each member read stops where the budget runs out."""
    if not path.is_file():
        raise PropError(f"checkpoint {path} does not exist", "check the path")
    size = path.stat().st_size
    budget = inflate_budget(size)
    try:
        with zipfile.ZipFile(path) as z:
            declared = sum(info.file_size for info in z.infolist())
            if declared > budget:
                raise _too_big(path, declared, budget, size)
            verify_zip(z)  # every member's CRC, each read to no more than its declared size
            names = set(z.namelist())
            if "data" not in names or "policy.pth" not in names:
                raise PropError(
                    f"{path} is a zip but not a Stable-Baselines3 model (no 'data' and 'policy.pth' entries)",
                    SAVE_HINT,
                )
            left = [budget]
            raw_data = _read(z, "data", left, path, budget, size)
            raw_policy = _read(z, "policy.pth", left, path, budget, size)
            version = None
            if "_stable_baselines3_version" in names:
                raw = _read(z, "_stable_baselines3_version", left, path, budget, size)
                version = raw.decode(errors="replace").strip() or None
    except ZIP_ERRORS as e:
        raise PropError(f"{path} is not a readable zip archive ({brief(e)})", SAVE_HINT) from None
    try:
        data = json.loads(raw_data)
    except (ValueError, RecursionError):  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        data = None
    if not isinstance(data, dict):
        raise PropError(
            f"{path} is a zip but not a Stable-Baselines3 model (its 'data' entry is not a JSON object)",
            SAVE_HINT,
        )
    state = load_state_dict(io.BytesIO(raw_policy), f"{path} (its policy.pth)")
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()
    ):
        raise PropError(f"{path}: policy.pth is not a state dict of tensors", SAVE_HINT)
    return data, dict(state), version


def policy_class(data: dict, path: str) -> tuple[str, str, str]:
    """(family, class name, extractor kind) from the plain fields SB3 writes beside the pickled class."""
    pc = data.get("policy_class")
    if not isinstance(pc, dict):
        raise PropError(
            f"{path} is a zip but not a Stable-Baselines3 model ('data' has no policy_class)", SAVE_HINT
        )
    module = str(pc.get("__module__", "?"))
    # The class's own __init__ is written as "<function ActorCriticCnnPolicy.__init__ at 0x...>".
    m = re.match(r"<function (\w+)\.__init__", str(pc.get("__init__", "")))
    name = m.group(1) if m else "a subclass"
    family, classes = _FAMILIES.get(module, (None, {}))
    if family is None or name not in classes:
        raise unsupported(path, f"policy {name} from {module}")
    return family, name, classes[name]


def policy_kwarg(data: dict, name: str, default):
    """A plain value of policy_kwargs (SB3 writes a dict, or plain fields beside a pickled one)."""
    kwargs = data.get("policy_kwargs")
    return kwargs.get(name, default) if isinstance(kwargs, dict) else default


def check_extractor(data: dict, path: str) -> None:
    """A custom features_extractor_class would build another network: refuse all but SB3's own."""
    text = policy_kwarg(data, "features_extractor_class", None)
    if text is not None and str(text).rpartition(".")[2].rstrip("'>") not in _EXTRACTORS:
        raise unsupported(path, f"features_extractor_class {text}")


def algorithm(family: str, data: dict) -> str:
    """The algorithm's name, for the manifest; the actor is the same across each family."""
    if family == "actor_critic":
        return "PPO" if "clip_range" in data else "A2C"
    if family == "sac":
        return "SAC"
    ddpg = data.get("policy_delay") == 1 and data.get("target_noise_clip") == 0.0
    return "DDPG" if ddpg else "TD3"


def _space(data: dict, field: str, path: str) -> tuple[str, dict]:
    space = data.get(field)
    kind = str(space.get(":type:", "")) if isinstance(space, dict) else ""
    m = re.search(r"gymnasium\.spaces\.\w+\.(\w+)'|gym\.spaces\.\w+\.(\w+)'", kind)
    if not m:
        raise PropError(f"{path}: 'data' has no readable {field}", SAVE_HINT)
    return m.group(1) or m.group(2), space


def _numbers(text: object, count: int) -> list[float] | None:
    """Parse numpy's repr of a float array ('[-1. -1. -8.]'); None if it is truncated or odd."""
    if not isinstance(text, str) or "..." in text:
        return None
    try:
        values = [float(t) for t in text.replace("[", " ").replace("]", " ").split()]
    except ValueError:
        return None
    if len(values) == 1 and count > 1:
        values = values * count
    return values if len(values) == count else None


_MAX_DIM = 1 << 24


def _dim(value: object, field: str, path: str) -> int:
    """A size SB3 wrote (an int, or a numeric string for Discrete.n), checked to be a sane one."""
    try:
        d = int(value)  # type: ignore[call-overload]
    except (TypeError, ValueError, OverflowError):
        d = 0
    if not 1 <= d <= _MAX_DIM:
        raise PropError(f"{path}: 'data' has an invalid size {value!r} in {field}", SAVE_HINT)
    return d


def _image(dtype: object, shape: list[int]) -> bool:
    # SB3's is_image_space: a 3-D uint8 Box (bounds 0..255, which the zip's truncated repr cannot show).
    return dtype == "uint8" and len(shape) == 3


def observation(data: dict, path: str, kind: str) -> dict:
    """The spec's observation fields: ``observation_shape`` (the module's input, per sample) and, for a
    Dict space, ``observation_keys`` in the policy's order (the order CombinedExtractor concatenates)."""
    space_kind, space = _space(data, "observation_space", path)
    if kind == "combined":
        if space_kind != "Dict":
            raise unsupported(path, f"MultiInputPolicy with a {space_kind} observation space")
        keys = _dict_spaces(space.get("spaces"), path)
        return {"observation_shape": [sum(math.prod(k["shape"]) for k in keys)], "observation_keys": keys}
    shape = space.get("_shape")
    if space_kind != "Box" or not isinstance(shape, list) or not shape:
        raise unsupported(path, f"a {space_kind} observation space")
    shape = [_dim(d, "observation_space", path) for d in shape]
    image = _image(space.get("dtype"), shape)
    if kind == "cnn" and not image:
        raise unsupported(path, f"CnnPolicy on a {space.get('dtype')} observation of shape {shape}")
    if kind == "flatten" and image:  # MlpPolicy would divide such images by 255: not rebuilt
        raise unsupported(path, "MlpPolicy on an image observation space")
    return {"observation_shape": shape}


# gymnasium's Dict repr: {'key': Box(low, high, (3,), float32), ...}; low/high may be arrays.
_SUBSPACE = re.compile(r"'((?:[^'\\]|\\.)+)': (\w+)\((.*?), \((\d+(?:, \d+)*),?\), (\w+)\)", re.S)


def _dict_spaces(text: object, path: str) -> list[dict]:
    if not isinstance(text, str):
        raise PropError(f"{path}: 'data' has no readable Dict observation_space spaces", SAVE_HINT)
    found = _SUBSPACE.findall(text)
    if not found or text.count("': ") != len(found):
        raise unsupported(path, f"a Dict observation space other than Boxes ({text[:80]})")
    keys = []
    for key, kind, _bounds, dims, dtype in found:
        shape = [_dim(d, "observation_space", path) for d in dims.split(",")]
        if kind != "Box":
            raise unsupported(path, f"a {kind} entry ('{key}') in a Dict observation space")
        keys.append({"key": key, "shape": shape, "image": _image(dtype, shape)})
    if len({k["key"] for k in keys}) != len(keys):
        raise PropError(f"{path}: its Dict observation space repeats a key", SAVE_HINT)
    return keys


def action_space(family: str, data: dict, path: str) -> dict:
    kind, space = _space(data, "action_space", path)
    if kind == "Discrete" and family == "actor_critic":
        return {"space": "Discrete", "n": _dim(space["n"], "action_space", path)}
    shape = space.get("_shape")
    if kind != "Box" or not isinstance(shape, list) or len(shape) != 1:
        raise unsupported(path, f"a {kind} action space for {family.replace('_', '-')} policies")
    n = _dim(shape[0], "action_space", path)
    action: dict = {"space": "Box", "shape": [n]}
    low = _numbers(space.get("low"), n) or _numbers(space.get("low_repr"), n)
    high = _numbers(space.get("high"), n) or _numbers(space.get("high_repr"), n)
    finite = low is not None and high is not None and all(map(math.isfinite, low + high))
    if finite:
        action.update(low=low, high=high)
    elif family != "actor_critic":  # squashed policies: we rescale to the bounds as predict() does
        raise PropError(
            f"{path}: cannot read finite action bounds (low/high) from 'data'",
            "save the model with a bounded Box action space, as SAC and TD3 require",
        )
    return action


def activation_class(data: dict) -> str | None:
    """The torch class name of ``policy_kwargs['activation_fn']`` where SB3 wrote one, else None.

    SB3 writes a plain dict, or a pickled one with ``str(activation_fn)`` beside it:
    ``"<class 'torch.nn.modules.activation.ReLU'>"``.
    """
    kwargs = data.get("policy_kwargs")
    text = kwargs.get("activation_fn") if isinstance(kwargs, dict) else None
    if text is None:
        return None
    return re.sub(r"^<class '(.*)'>$", r"\1", str(text)).rpartition(".")[2]
