"""Stable-Baselines3 model zips -> the policy's deterministic actor, with SB3's state-dict names.

Nothing is unpickled and stable-baselines3 is not needed. An SB3 zip holds ``data`` (JSON; fields
that are not JSON-serialisable are cloudpickled, and next to each blob SB3 writes the object's plain
attributes and ``str()`` of the rest: we read only those plain values) and ``policy.pth`` (a state
dict, read with ``weights_only=True``).

What the module computes, per family (``spec["family"]``):

- ``actor_critic`` (PPO, A2C ``MlpPolicy``): ``action_net(mlp_extractor.policy_net(obs))``: the
  Gaussian mean for Box actions (``model.predict(obs, deterministic=True)`` before it clips to the
  action bounds), the logits for Discrete actions (``predict`` returns their argmax).
- ``sac`` (SAC ``MlpPolicy``): ``tanh(actor.mu(actor.latent_pi(obs)))`` rescaled from [-1, 1] to the
  action bounds: exactly what ``predict(obs, deterministic=True)`` returns.
- ``td3`` (TD3, DDPG ``MlpPolicy``): ``actor.mu(obs)`` (ends in tanh) rescaled the same way.

So the outputs are in the environment's action units, the units a user's demonstrations are in.
The rest of ``policy.pth`` (value/critic networks, target networks, ``log_std``) is not part of the
module: it rides along in ``LoadedModel.extra`` and is written back untouched, so the bundle's base
file is a complete SB3 policy state dict (``model.policy.load_state_dict(load_file(base))``).
"""

from __future__ import annotations

import io
import json
import math
import pickle
import re
import zipfile
from pathlib import Path

import torch
from torch import nn

from prop_cli.errors import PropError

from .base import LoadedModel, finish

NAME = "sb3"
SUPPORTED = (
    "PPO and A2C MlpPolicy (Box or Discrete actions), SAC MlpPolicy, TD3 and DDPG MlpPolicy "
    "(Box actions), all with Box observations and without gSDE"
)
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "leaky_relu": nn.LeakyReLU,
    "gelu": nn.GELU,
    "silu": nn.SiLU,
}
# torch class name (as SB3 writes str(activation_fn)) -> our name.
_TORCH_NAMES = {cls.__name__: name for name, cls in ACTIVATIONS.items()}

# The module SB3 defines each policy family in, and the class that is its MlpPolicy.
_FAMILIES = {
    "stable_baselines3.common.policies": ("actor_critic", "ActorCriticPolicy"),
    "stable_baselines3.sac.policies": ("sac", "SACPolicy"),
    "stable_baselines3.td3.policies": ("td3", "TD3Policy"),
}
# SB3's default activation_fn per family: ActorCriticPolicy uses Tanh, SAC and TD3 use ReLU.
DEFAULT_ACTIVATION = {"actor_critic": "tanh", "sac": "relu", "td3": "relu"}
# policy.pth prefixes: (the deterministic actor's, the rest SB3 keeps for training).
_PREFIXES = {
    "actor_critic": (
        ("mlp_extractor.policy_net.", "action_net."),
        ("mlp_extractor.value_net.", "value_net.", "log_std"),
    ),
    "sac": (("actor.latent_pi.", "actor.mu."), ("actor.log_std.", "critic.", "critic_target.")),
    "td3": (("actor.mu.",), ("actor_target.", "critic.", "critic_target.")),
}
_SAVE_HINT = "pass the .zip written by model.save() of a Stable-Baselines3 model"


def _unsupported(path: str, what: str) -> PropError:
    return PropError(f"{path}: {what} is not supported", f"prop reads {SUPPORTED}")


# ---- reading the zip -------------------------------------------------------------------------


def read_zip(path: Path) -> tuple[dict, dict[str, torch.Tensor], str | None]:
    """``data`` as JSON, the ``policy.pth`` state dict and the SB3 version string; never unpickles."""
    if not path.is_file():
        raise PropError(f"checkpoint {path} does not exist", "check the path")
    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
            if "data" not in names or "policy.pth" not in names:
                raise PropError(
                    f"{path} is a zip but not a Stable-Baselines3 model (no 'data' and 'policy.pth' entries)",
                    _SAVE_HINT,
                )
            raw_data = z.read("data")
            raw_policy = z.read("policy.pth")
            version = None
            if "_stable_baselines3_version" in names:
                version = z.read("_stable_baselines3_version").decode(errors="replace").strip() or None
    except (zipfile.BadZipFile, OSError) as e:
        raise PropError(f"{path} is not a readable zip archive ({e})", _SAVE_HINT) from None
    try:
        data = json.loads(raw_data)
    except (json.JSONDecodeError, UnicodeDecodeError):
        data = None
    if not isinstance(data, dict):
        raise PropError(
            f"{path} is a zip but not a Stable-Baselines3 model (its 'data' entry is not a JSON object)",
            _SAVE_HINT,
        )
    try:
        state = torch.load(io.BytesIO(raw_policy), weights_only=True, map_location="cpu")
    except pickle.UnpicklingError:
        raise PropError(
            f"{path}: policy.pth pickles objects other than tensors, and prop never unpickles code",
            "save the model again with Stable-Baselines3's model.save()",
        ) from None
    except Exception as e:  # torch raises many types on junk
        raise PropError(f"{path}: policy.pth is corrupt ({type(e).__name__})", _SAVE_HINT) from None
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()
    ):
        raise PropError(f"{path}: policy.pth is not a state dict of tensors", _SAVE_HINT)
    return data, dict(state), version


def _policy_class(data: dict, path: str) -> tuple[str, str]:
    """(family, class name) from the plain fields SB3 writes beside the pickled policy class."""
    pc = data.get("policy_class")
    if not isinstance(pc, dict):
        raise PropError(
            f"{path} is a zip but not a Stable-Baselines3 model ('data' has no policy_class)", _SAVE_HINT
        )
    module = str(pc.get("__module__", "?"))
    # The class's own __init__ is written as "<function ActorCriticCnnPolicy.__init__ at 0x...>".
    m = re.match(r"<function (\w+)\.__init__", str(pc.get("__init__", "")))
    name = m.group(1) if m else "a subclass"
    family, mlp_class = _FAMILIES.get(module, (None, None))
    if family is None or name != mlp_class:
        raise _unsupported(path, f"policy {name} from {module}")
    return family, name


def _algorithm(family: str, data: dict) -> str:
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
        raise PropError(f"{path}: 'data' has no readable {field}", _SAVE_HINT)
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


def _observation_shape(data: dict, path: str) -> list[int]:
    kind, space = _space(data, "observation_space", path)
    shape = space.get("_shape")
    if kind != "Box" or not isinstance(shape, list) or not shape:
        raise _unsupported(path, f"a {kind} observation space")
    if space.get("dtype") == "uint8" and len(shape) == 3:
        raise _unsupported(path, "an image observation space (CnnPolicy)")
    return [int(d) for d in shape]


def _action(family: str, data: dict, path: str) -> dict:
    kind, space = _space(data, "action_space", path)
    if kind == "Discrete" and family == "actor_critic":
        return {"space": "Discrete", "n": int(space["n"])}
    shape = space.get("_shape")
    if kind != "Box" or not isinstance(shape, list) or len(shape) != 1:
        raise _unsupported(path, f"a {kind} action space for {family.replace('_', '-')} policies")
    action = {"space": "Box", "shape": [int(shape[0])]}
    if family != "actor_critic":  # squashed policies: we rescale to the bounds as predict() does
        n = int(shape[0])
        low = _numbers(space.get("low"), n) or _numbers(space.get("low_repr"), n)
        high = _numbers(space.get("high"), n) or _numbers(space.get("high_repr"), n)
        if low is None or high is None or not all(map(math.isfinite, low + high)):
            raise PropError(
                f"{path}: cannot read finite action bounds (low/high) from 'data'",
                "save the model with a bounded Box action space, as SAC and TD3 require",
            )
        action.update(low=low, high=high)
    return action


def _activation(family: str, data: dict, override: str | None, path: str) -> str:
    if override is not None:
        act = override.strip().lower()
        if act not in ACTIVATIONS:
            raise PropError(
                f"--activation: unknown activation '{act}'", f"use one of: {', '.join(ACTIVATIONS)}"
            )
        return act
    kwargs = data.get("policy_kwargs")
    # Plain dict, or a pickled one with str(activation_fn) beside it: "<class '...activation.ReLU'>".
    text = kwargs.get("activation_fn") if isinstance(kwargs, dict) else None
    if text is None:
        return DEFAULT_ACTIVATION[family]
    name = re.sub(r"^<class '(.*)'>$", r"\1", str(text)).rpartition(".")[2]
    if name not in _TORCH_NAMES:
        raise PropError(
            f"{path}: policy_kwargs activation_fn {name} is not one prop rebuilds",
            f"pass --activation with the closest of: {', '.join(ACTIVATIONS)}",
        )
    return _TORCH_NAMES[name]


# ---- the module ------------------------------------------------------------------------------


def _mlp(
    weights: dict[str, torch.Tensor], prefix: str, act: str, last: str | None, path: str
) -> nn.Sequential:
    """SB3's create_mlp: Linear at 0, 2, 4, ...; the activation between them; ``last`` after the last."""
    idx = sorted(
        int(k[len(prefix) :].split(".")[0])
        for k in weights
        if k.startswith(prefix) and k.endswith(".weight") and k[len(prefix) :].split(".")[0].isdigit()
    )
    if idx != list(range(0, 2 * len(idx), 2)):
        raise _unsupported(path, f"a network '{prefix[:-1]}' that is not SB3's MLP layout")
    layers: list[nn.Module] = []
    for j, i in enumerate(idx):
        out_f, in_f = weights[f"{prefix}{i}.weight"].shape
        layers.append(nn.Linear(in_f, out_f, bias=f"{prefix}{i}.bias" in weights))
        final = j == len(idx) - 1
        if not final:
            layers.append(ACTIVATIONS[act]())
        elif last is not None:
            layers.append(ACTIVATIONS[last]())
    return nn.Sequential(*layers)


def _linear(weights: dict[str, torch.Tensor], name: str, path: str) -> nn.Linear:
    w = weights.get(name + ".weight")
    if w is None or w.ndim != 2:
        raise _unsupported(path, f"a policy without a linear '{name}'")
    return nn.Linear(w.shape[1], w.shape[0], bias=name + ".bias" in weights)


class _Rescale(nn.Module):
    """[-1, 1] -> [low, high], as SB3's unscale_action; bounds are not part of the state dict."""

    def __init__(self, low: list[float], high: list[float]) -> None:
        super().__init__()
        self.register_buffer("low", torch.tensor(low), persistent=False)
        self.register_buffer("high", torch.tensor(high), persistent=False)

    def forward(self, a: torch.Tensor) -> torch.Tensor:
        return self.low + 0.5 * (a + 1.0) * (self.high - self.low)


class ActorCriticActor(nn.Module):
    """PPO/A2C: ``action_net(mlp_extractor.policy_net(flatten(obs)))``; names as in SB3."""

    def __init__(self, policy_net: nn.Sequential, action_net: nn.Linear) -> None:
        super().__init__()
        self.mlp_extractor = nn.Module()
        self.mlp_extractor.policy_net = policy_net
        self.action_net = action_net

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.action_net(self.mlp_extractor.policy_net(obs.flatten(1)))


class SquashedActor(nn.Module):
    """SAC (``tanh(actor.mu(actor.latent_pi(obs)))``) or TD3 (``actor.mu(obs)``), rescaled to the bounds."""

    def __init__(self, mu: nn.Module, latent_pi: nn.Sequential | None, rescale: _Rescale) -> None:
        super().__init__()
        self.actor = nn.Module()
        if latent_pi is not None:
            self.actor.latent_pi = latent_pi
        self.actor.mu = mu
        self.squash = latent_pi is not None  # TD3's mu ends in its own Tanh
        self.rescale = rescale

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = obs.flatten(1)
        if self.squash:
            x = torch.tanh(self.actor.mu(self.actor.latent_pi(x)))
        else:
            x = self.actor.mu(x)
        return self.rescale(x)


def split_state(family: str, state: dict[str, torch.Tensor], path: str):
    """(actor tensors, the rest); anything SB3's MlpPolicy does not have is refused."""
    actor_pre, rest_pre = _PREFIXES[family]
    actor = {k: v for k, v in state.items() if k.startswith(actor_pre)}
    rest = {k: v for k, v in state.items() if k.startswith(rest_pre)}
    other = sorted(set(state) - set(actor) - set(rest))
    if other:
        raise _unsupported(path, f"a policy with tensors beyond MlpPolicy's ({', '.join(other[:3])})")
    if not actor:
        raise _unsupported(path, "a policy.pth without the actor's tensors")
    return actor, rest


def build_module(spec: dict, actor: dict[str, torch.Tensor], path: str) -> nn.Module:
    family, act = spec["family"], spec["activation"]
    if family == "actor_critic":
        policy_net = _mlp(actor, "mlp_extractor.policy_net.", act, act, path)
        module: nn.Module = ActorCriticActor(policy_net, _linear(actor, "action_net", path))
    else:
        rescale = _Rescale(spec["action"]["low"], spec["action"]["high"])
        if family == "sac":
            latent = _mlp(actor, "actor.latent_pi.", act, act, path)
            module = SquashedActor(_linear(actor, "actor.mu", path), latent, rescale)
        else:
            module = SquashedActor(_mlp(actor, "actor.mu.", act, "tanh", path), None, rescale)
    try:
        module.load_state_dict(actor, strict=True)
    except RuntimeError as e:
        raise PropError(
            f"{path}: policy.pth does not fit SB3's {spec['policy']} ({str(e).splitlines()[0]})",
            "the file was modified or is not an MlpPolicy; re-save it with model.save()",
        ) from None
    features = math.prod(spec["observation_shape"])
    with torch.no_grad():
        try:
            out = module(torch.zeros(1, features))
        except RuntimeError:
            out = None
    want = spec["action"].get("n") or spec["action"]["shape"][0]
    if out is None or out.shape[-1] != want:
        raise PropError(
            f"{path}: policy.pth layer sizes do not match the observation ({features}) and action ({want}) "
            "sizes in 'data'",
            "the zip was modified; re-save it with model.save()",
        )
    return module


def _loaded(spec: dict, state: dict[str, torch.Tensor], path: str) -> LoadedModel:
    actor, rest = split_state(spec["family"], state, path)
    module = build_module(spec, actor, path)
    return LoadedModel(
        module=finish(module),
        spec=spec,
        dtypes={k: v.dtype for k, v in actor.items()},
        input_shape=tuple(spec["observation_shape"]),
        source=path,
        extra=rest,
    )


def load(path: str | Path, *, activation: str | None = None) -> LoadedModel:
    """Read an SB3 zip (no unpickling, no SB3 needed) into its deterministic actor."""
    path = Path(path)
    data, state, version = read_zip(path)
    src = str(path)
    family, policy = _policy_class(data, src)
    if data.get("use_sde") is True:
        raise _unsupported(src, "gSDE (use_sde=True)")
    spec = {
        "adapter": NAME,
        "algorithm": _algorithm(family, data),
        "family": family,
        "policy": policy,
        "activation": _activation(family, data, activation, src),
        "observation_shape": _observation_shape(data, src),
        "action": _action(family, data, src),
        "sb3_version": version,
    }
    return _loaded(spec, state, src)


def rebuild(spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
    return _loaded(spec, weights, source)
