"""Stable-Baselines3 model zips -> the policy's deterministic actor, with SB3's state-dict names.

The zip is read by ``sb3_zip`` (no unpickling, no SB3 needed). What the module computes, per family
(``spec["family"]``):

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

import math
from pathlib import Path

import torch
from torch import nn

from prop_cli.errors import PropError, brief

from . import activations, sb3_zip
from .base import Adapter, CheckpointOptions, LoadedModel, finish
from .sb3_zip import unsupported

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


def _activation(family: str, data: dict, override: str | None, path: str) -> str:
    """The activation SB3 built the actor with; never a guess (a wrong one changes the network)."""
    recorded = sb3_zip.activation_class(data)
    if recorded is None:
        act = DEFAULT_ACTIVATION[family]  # SB3 wrote no activation_fn: it used its default
    elif recorded in activations.BY_CLASS_NAME:
        act = activations.BY_CLASS_NAME[recorded]
    else:
        raise PropError(
            f"{path}: policy_kwargs activation_fn {recorded} is not one prop can rebuild, and any other "
            "would change the network",
            "prop rebuilds " + ", ".join(cls.__name__ for cls in activations.ACTIVATIONS.values()),
        )
    if override is not None and activations.check(override, "--activation") != act:
        raise PropError(
            f"--activation {override} contradicts {path}, whose actor uses {act}",
            "drop --activation: prop reads the activation from the zip",
        )
    return act


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
        raise unsupported(path, f"a network '{prefix[:-1]}' that is not SB3's MLP layout")
    layers: list[nn.Module] = []
    for j, i in enumerate(idx):
        out_f, in_f = weights[f"{prefix}{i}.weight"].shape
        layers.append(nn.Linear(in_f, out_f, bias=f"{prefix}{i}.bias" in weights))
        final = j == len(idx) - 1
        if not final:
            layers.append(activations.make(act))
        elif last is not None:
            layers.append(activations.make(last))
    return nn.Sequential(*layers)


def _linear(weights: dict[str, torch.Tensor], name: str, path: str) -> nn.Linear:
    w = weights.get(name + ".weight")
    if w is None or w.ndim != 2:
        raise unsupported(path, f"a policy without a linear '{name}'")
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
        raise unsupported(path, f"a policy with tensors beyond MlpPolicy's ({', '.join(other[:3])})")
    if not actor:
        raise unsupported(path, "a policy.pth without the actor's tensors")
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
        except (RuntimeError, TypeError, OverflowError):  # sizes that do not fit (or do not exist)
            out = None
    want = spec["action"].get("n") or spec["action"]["shape"][0]
    if out is None or out.shape[-1] != want:
        raise PropError(
            f"{path}: policy.pth layer sizes do not match the observation ({features}) and action ({want}) "
            "sizes in 'data'",
            "the zip was modified; re-save it with model.save()",
        )
    return module


def _bounds(spec: dict) -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
    action = spec["action"]
    if "low" in action and "high" in action:
        return tuple(action["low"]), tuple(action["high"])
    return None, None


def _loaded(spec: dict, state: dict[str, torch.Tensor], path: str) -> LoadedModel:
    actor, rest = split_state(spec["family"], state, path)
    module = build_module(spec, actor, path)
    low, high = _bounds(spec)
    return LoadedModel(
        module=finish(module),
        spec=spec,
        dtypes={k: v.dtype for k, v in actor.items()},
        input_shape=tuple(spec["observation_shape"]),
        source=path,
        extra=rest,
        continuous=spec["action"]["space"] == "Box",
        action_low=low,
        action_high=high,
    )


class SB3Adapter(Adapter):
    name = "sb3"
    summary = "a Stable-Baselines3 zip: model.save() of " + sb3_zip.SUPPORTED + "; its deterministic actor"
    options = ("activation",)

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return path.suffix.lower() == ".zip"

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        data, state, version = sb3_zip.read_zip(path)
        try:
            spec = self._spec(data, version, str(path), options)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
            raise PropError(
                f"{path}: its 'data' entry is not what Stable-Baselines3 writes ({brief(e)})",
                sb3_zip.SAVE_HINT,
            ) from None
        return _loaded(spec, state, str(path))

    def _spec(self, data: dict, version: str | None, src: str, options: CheckpointOptions) -> dict:
        family, policy = sb3_zip.policy_class(data, src)
        if data.get("use_sde") is True:
            raise unsupported(src, "gSDE (use_sde=True)")
        spec = {
            "adapter": self.name,
            "algorithm": sb3_zip.algorithm(family, data),
            "family": family,
            "policy": policy,
            "activation": _activation(family, data, options.activation, src),
            "observation_shape": sb3_zip.observation_shape(data, src),
            "action": sb3_zip.action_space(family, data, src),
            "sb3_version": version,
        }
        return spec

    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        return _loaded(spec, weights, source)

    def weights(self, path: Path) -> dict[str, torch.Tensor]:
        return sb3_zip.read_zip(path)[1]

    def describe(self, loaded: LoadedModel) -> dict:
        spec = loaded.spec
        info = super().describe(loaded)
        info.update(
            algorithm=spec["algorithm"],
            policy=spec["policy"],
            observation_shape=spec["observation_shape"],
            action_space=spec["action"]["space"],
            sb3_version=spec.get("sb3_version"),
        )
        if spec["action"]["space"] == "Discrete":
            info["actions"] = spec["action"]["n"]
        return info
