"""Stable-Baselines3 model zips -> the policy's deterministic actor, with SB3's state-dict names.

The zip is read by ``archive`` (no unpickling, no SB3 needed). What the module computes, per family
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

import numpy as np
import torch
from torch import nn

from prop_adapters import activations
from prop_adapters.base import Adapter, CheckpointOptions, LoadedModel, finish
from prop_cli.constants import DEFAULT_LAYERS_ATTR
from prop_cli.core.rules import BOOL, DIM, MAX_DIM, choice, list_of, number, obj, optional, text
from prop_cli.errors import PropError, brief

from . import archive
from .archive import unsupported

# SB3's default activation_fn per family: ActorCriticPolicy uses Tanh, SAC and TD3 use ReLU.
DEFAULT_ACTIVATION = {"actor_critic": "tanh", "sac": "relu", "td3": "relu"}
# policy.pth prefixes: (the deterministic actor's, the rest SB3 keeps for training).
_PREFIXES = {
    "actor_critic": (
        ("features_extractor.", "mlp_extractor.policy_net.", "action_net."),
        (
            "pi_features_extractor.",
            "vf_features_extractor.",
            "mlp_extractor.value_net.",
            "value_net.",
            "log_std",
        ),
    ),
    "sac": (
        ("actor.features_extractor.", "actor.latent_pi.", "actor.mu."),
        ("actor.log_std.", "critic.", "critic_target."),
    ),
    "td3": (("actor.features_extractor.", "actor.mu."), ("actor_target.", "critic.", "critic_target.")),
}
# Where SB3 registers the actor's features extractor once more under another name (the same module):
# always pi_features_extractor for PPO/A2C, the value side's too when share_features_extractor is set.
# policy.pth holds each alias as a copy; the bundle's base writes them from the (fine-tuned) module so
# that SB3's load_state_dict, which loads the aliases after the original, sees one set of weights.
_EXTRACTOR = {
    "actor_critic": "features_extractor.",
    "sac": "actor.features_extractor.",
    "td3": "actor.features_extractor.",
}
_ALIASES = {
    "actor_critic": (("pi_features_extractor.",), ("vf_features_extractor.",)),
    "sac": ((), ("critic.features_extractor.",)),
    "td3": ((), ("critic.features_extractor.",)),
}
# NatureCNN's convolutions, fixed in SB3: (kernel, stride) of cnn.0, cnn.2, cnn.4.
_NATURE = ((8, 4), (4, 2), (3, 1))


def _activation(family: str, data: dict, override: str | None, path: str) -> str:
    """The activation SB3 built the actor with; never a guess (a wrong one changes the network)."""
    recorded = archive.activation_class(data)
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


class NatureCNN(nn.Module):
    """SB3's NatureCNN under its names (``cnn.*``, ``linear.0``) on CHW images, scaled as preprocess_obs."""

    def __init__(self, convs: list[nn.Conv2d], linear: nn.Linear, scale: float) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for conv in convs:
            layers += [conv, nn.ReLU()]
        self.cnn = nn.Sequential(*layers, nn.Flatten())
        self.linear = nn.Sequential(linear, nn.ReLU())
        self.scale = scale  # 1/255 where normalize_images (SB3's default), else 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(self.cnn(x * self.scale))


class Features(nn.Module):
    """SB3's features extractor on prop's one input array: Flatten (MlpPolicy), NatureCNN (CnnPolicy)
    or CombinedExtractor (MultiInputPolicy: ``extractors.<key>``). A Dict observation arrives flattened,
    its entries concatenated in ``keys`` order (``observation_array``); it is split here, each entry
    reshaped, images through their NatureCNN, then concatenated again in that order as SB3 does."""

    def __init__(self, cnn: NatureCNN | None = None, keys: list[dict] | None = None, extractors=None) -> None:
        super().__init__()
        if cnn is not None:
            self.cnn, self.linear = cnn.cnn, cnn.linear
            self.scale = cnn.scale
        self.keys = keys
        if extractors is not None:
            self.extractors = nn.ModuleDict(extractors)
        self.image = cnn is not None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.image:
            return self.linear(self.cnn(x * self.scale))
        if self.keys is None:
            return x.flatten(1)
        parts, at = [], 0
        for entry in self.keys:
            n = math.prod(entry["shape"])
            part = x[:, at : at + n]
            at += n
            mod = self.extractors[entry["key"]]
            parts.append(mod(part.reshape(-1, *entry["shape"])) if entry["image"] else part)
        return torch.cat(parts, 1)


class ActorCriticActor(nn.Module):
    """PPO/A2C: ``action_net(mlp_extractor.policy_net(features_extractor(obs)))``; names as in SB3."""

    def __init__(self, features: Features, policy_net: nn.Sequential, action_net: nn.Linear) -> None:
        super().__init__()
        self.features_extractor = features
        self.mlp_extractor = nn.Module()
        self.mlp_extractor.policy_net = policy_net
        self.action_net = action_net

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.action_net(self.mlp_extractor.policy_net(self.features_extractor(obs)))


class SquashedActor(nn.Module):
    """SAC (``tanh(actor.mu(actor.latent_pi(obs)))``) or TD3 (``actor.mu(obs)``), rescaled to the bounds."""

    def __init__(self, features: Features, mu: nn.Module, latent_pi: nn.Sequential | None, rescale: _Rescale):
        super().__init__()
        self.actor = nn.Module()
        self.actor.features_extractor = features
        if latent_pi is not None:
            self.actor.latent_pi = latent_pi
        self.actor.mu = mu
        self.squash = latent_pi is not None  # TD3's mu ends in its own Tanh
        self.rescale = rescale

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = self.actor.features_extractor(obs)
        if self.squash:
            x = torch.tanh(self.actor.mu(self.actor.latent_pi(x)))
        else:
            x = self.actor.mu(x)
        return self.rescale(x)


def _nature(weights: dict[str, torch.Tensor], prefix: str, scale: float, path: str) -> NatureCNN:
    convs = []
    for j, (kernel, stride) in enumerate(_NATURE):
        w = weights.get(f"{prefix}cnn.{2 * j}.weight")
        if w is None or w.ndim != 4 or tuple(w.shape[2:]) != (kernel, kernel):
            raise unsupported(path, f"a features extractor '{prefix[:-1]}' that is not SB3's NatureCNN")
        convs.append(
            nn.Conv2d(w.shape[1], w.shape[0], kernel, stride, bias=f"{prefix}cnn.{2 * j}.bias" in weights)
        )
    return NatureCNN(convs, _linear(weights, prefix + "linear.0", path), scale)


def _features(spec: dict, weights: dict[str, torch.Tensor], path: str) -> Features:
    prefix = _EXTRACTOR[spec["family"]]
    scale = 1 / 255 if spec.get("normalize_images", True) else 1.0
    if spec.get("extractor") == "cnn":
        return Features(cnn=_nature(weights, prefix, scale, path))
    keys = spec.get("observation_keys")
    if keys is None:
        return Features()
    extractors = {
        k["key"]: _nature(weights, f"{prefix}extractors.{k['key']}.", scale, path)
        if k["image"]
        else nn.Flatten()
        for k in keys
    }
    return Features(keys=keys, extractors=extractors)


def _alias_hook(sources: list[tuple[str, str]]):
    """A state-dict hook writing the features extractor's tensors under SB3's alias names too."""

    def hook(module, state, prefix, _meta):
        for src, alias in sources:
            for k in [k for k in state if k.startswith(prefix + src)]:
                state[prefix + alias + k[len(prefix + src) :]] = state[k].clone()
        return state

    return hook


def _aliases(spec: dict) -> list[tuple[str, str]]:
    always, shared = _ALIASES[spec["family"]]
    names = always + (shared if spec.get("share_features_extractor") else ())
    return [(_EXTRACTOR[spec["family"]], a) for a in names]


def split_state(family: str, state: dict[str, torch.Tensor], path: str):
    """(actor tensors, the rest); anything SB3's policies do not have is refused."""
    actor_pre, rest_pre = _PREFIXES[family]
    rest = {k: v for k, v in state.items() if k.startswith(rest_pre)}
    actor = {k: v for k, v in state.items() if k.startswith(actor_pre) and k not in rest}
    other = sorted(set(state) - set(actor) - set(rest))
    if other:
        raise unsupported(path, f"a policy with tensors beyond SB3's own ({', '.join(other[:3])})")
    if not actor:
        raise unsupported(path, "a policy.pth without the actor's tensors")
    return actor, rest


def _assemble(spec: dict, actor: dict[str, torch.Tensor], path: str) -> nn.Module:
    """The actor's modules, shaped by ``actor``'s tensors, and its weights loaded into them."""
    family, act = spec["family"], spec["activation"]
    features = _features(spec, actor, path)
    if family == "actor_critic":
        policy_net = _mlp(actor, "mlp_extractor.policy_net.", act, act, path)
        module: nn.Module = ActorCriticActor(features, policy_net, _linear(actor, "action_net", path))
    else:
        rescale = _Rescale(spec["action"]["low"], spec["action"]["high"])
        if family == "sac":
            latent = _mlp(actor, "actor.latent_pi.", act, act, path)
            module = SquashedActor(features, _linear(actor, "actor.mu", path), latent, rescale)
        else:
            module = SquashedActor(features, _mlp(actor, "actor.mu.", act, "tanh", path), None, rescale)
    try:
        module.load_state_dict(actor, strict=True)
    except RuntimeError as e:
        raise PropError(
            f"{path}: policy.pth does not fit SB3's {spec['policy']} ({str(e).splitlines()[0]})",
            "the file was modified or is not the policy its 'data' names; re-save it with model.save()",
        ) from None
    return module


def build_module(spec: dict, actor: dict[str, torch.Tensor], path: str) -> nn.Module:
    # First on the meta device: the observation and action sizes in the spec (a bundle's manifest) are
    # checked against the layers with shapes alone, so a claimed huge observation allocates nothing.
    shape = spec["observation_shape"]
    with torch.device("meta"):
        probe = _assemble(spec, {k: v.to("meta") for k, v in actor.items()}, path)
        try:
            out = probe(torch.zeros(1, *shape))
        except (RuntimeError, TypeError, OverflowError, ValueError):  # sizes that do not fit
            out = None
    want = spec["action"].get("n") or spec["action"]["shape"][0]
    if out is None or out.shape[-1] != want:
        raise PropError(
            f"{path}: policy.pth layer sizes do not match the observation {shape} and action ({want}) "
            "sizes in 'data'",
            "the zip was modified; re-save it with model.save()",
        )
    module = _assemble(spec, actor, path)
    module._register_state_dict_hook(_alias_hook(_aliases(spec)))
    if any(isinstance(m, nn.Conv2d) for m in module.modules()):
        # With a CNN, the first linear layer (features_extractor[.extractors.<key>].linear.0) reads image
        # features, not the raw observation that layers.default_layers skips the first layer for: key
        # every linear layer (NatureCNN's linear, the policy MLP, the action head).
        setattr(
            module, DEFAULT_LAYERS_ATTR, [n for n, m in module.named_modules() if isinstance(m, nn.Linear)]
        )
    return module


def observation_array(spec: dict, obs) -> np.ndarray:
    """An environment observation (one, or a batch) as the module takes it: a Dict flattened and
    concatenated in the policy's key order (``spec["observation_keys"]``), images HWC -> CHW as SB3's
    VecTransposeImage does; float32, raw values (the module scales images itself)."""
    keys = spec.get("observation_keys")
    if keys is None:
        if isinstance(obs, dict):
            raise PropError(
                f"the environment's observations are dicts ({sorted(obs)}); {spec['policy']} takes one array",
                "evaluate a MultiInputPolicy model, or an environment with Box observations",
            )
        return _chw(np.asarray(obs), spec["observation_shape"], "the observation")
    if not isinstance(obs, dict):
        raise PropError(
            f"this {spec['policy']} takes dict observations with keys {[k['key'] for k in keys]}",
            "give an environment with Dict observations (flattened data: see prop inspect)",
        )
    parts = []
    for k in keys:
        if k["key"] not in obs:
            raise PropError(
                f"the environment's observation has no {k['key']!r} (it has {sorted(obs)})",
                "use the environment the policy was trained on",
            )
        a = _chw(np.asarray(obs[k["key"]]), k["shape"], f"observation {k['key']!r}")
        parts.append(a.reshape(*a.shape[: a.ndim - len(k["shape"])], -1))
    return np.concatenate(parts, -1).astype(np.float32)


def _chw(a: np.ndarray, shape: list[int], what: str) -> np.ndarray:
    """``a`` (one or a batch) in ``shape``; an HWC image of a CHW shape is transposed."""
    n = len(shape)
    if list(a.shape[-n:]) != list(shape) and n == 3 and list(a.shape[-3:]) == [shape[1], shape[2], shape[0]]:
        a = np.moveaxis(a, -1, -3)
    if list(a.shape[-n:]) != list(shape) or a.ndim not in (n, n + 1):
        raise PropError(
            f"{what} has shape {list(a.shape)}; the policy takes {shape}",
            "use the environment the policy was trained on",
        )
    return a.astype(np.float32)


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
    summary = "a Stable-Baselines3 zip: model.save() of " + archive.SUPPORTED + "; its deterministic actor"
    options = ("activation",)
    manifest_fields = {
        "algorithm": text(),
        "family": choice(("actor_critic", "sac", "td3")),
        "policy": text(),
        "activation": text(),
        "observation_shape": list_of(DIM, 1, 16),
        "observation_keys": optional(
            list_of(obj({"key": text(), "shape": list_of(DIM, 1, 16), "image": BOOL}), 1)
        ),
        "extractor": optional(choice(("flatten", "cnn", "combined"))),
        "normalize_images": optional(BOOL),
        "share_features_extractor": optional(BOOL),
        "action": obj({
            "space": choice(("Box", "Discrete")),
            "shape": optional(list_of(DIM, 1, 1)),
            "n": optional(DIM),
            "low": optional(list_of(number(-math.inf), 1, MAX_DIM)),
            "high": optional(list_of(number(-math.inf), 1, MAX_DIM)),
        }),  # fmt: skip
        "sb3_version": optional(text(), nullable=True),
    }

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return path.suffix.lower() == ".zip"

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        data, state, version = archive.read_zip(path)
        try:
            spec = self._spec(data, version, str(path), options)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
            raise PropError(
                f"{path}: its 'data' entry is not what Stable-Baselines3 writes ({brief(e)})",
                archive.SAVE_HINT,
            ) from None
        return _loaded(spec, state, str(path))

    def _spec(self, data: dict, version: str | None, src: str, options: CheckpointOptions) -> dict:
        family, policy, kind = archive.policy_class(data, src)
        if data.get("use_sde") is True:
            raise unsupported(src, "gSDE (use_sde=True)")
        archive.check_extractor(data, src)
        spec = {
            "adapter": self.name,
            "algorithm": archive.algorithm(family, data),
            "family": family,
            "policy": policy,
            "activation": _activation(family, data, options.activation, src),
            **archive.observation(data, src, kind),
            "action": archive.action_space(family, data, src),
            "sb3_version": version,
        }
        if kind != "flatten":
            # SB3's defaults: images scaled by 1/255; PPO/A2C share the extractor, SAC/TD3 do not.
            spec["extractor"] = kind
            spec["normalize_images"] = bool(archive.policy_kwarg(data, "normalize_images", True))
            default_share = family == "actor_critic"
            spec["share_features_extractor"] = bool(
                archive.policy_kwarg(data, "share_features_extractor", default_share)
            )
        return spec

    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        return _loaded(spec, weights, source)

    def weights(self, path: Path) -> dict[str, torch.Tensor]:
        return archive.read_zip(path)[1]

    def describe(self, loaded: LoadedModel) -> dict:
        spec = loaded.spec
        info = super().describe(loaded)
        info.update(
            algorithm=spec["algorithm"],
            policy=spec["policy"],
            observation_shape=spec["observation_shape"],
            extractor=spec.get("extractor", "flatten"),
            action_space=spec["action"]["space"],
            sb3_version=spec.get("sb3_version"),
        )
        if spec["action"]["space"] == "Discrete":
            info["actions"] = spec["action"]["n"]
        if "observation_keys" in spec:  # where each Dict entry sits in the flattened input (data's x)
            info["observation_layout"], at = [], 0
            for k in spec["observation_keys"]:
                n = math.prod(k["shape"])
                info["observation_layout"].append(f"x[{at}:{at + n}] = {k['key']} {k['shape']}")
                at += n
        return info
