"""A LeRobot policy folder (``save_pretrained`` of policy and processors), loaded by LeRobot's own classes.

The folder holds ``config.json`` (with ``type``), ``model.safetensors`` and the pre/post-processor files
(``policy_preprocessor.json`` ...). The module is the LeRobot policy itself, so state-dict names are
LeRobot's; the bundle carries the folder's config and processor files byte for byte plus the trained
weights, so its ``lerobot/`` folder loads back with ``from_pretrained``.

lerobot is optional (scripts/setup-lerobot.sh builds its environment) and imported only here, inside
functions. Supported: ACT. Diffusion is refused: its actions come out of an iterative sampler, so there
is no deterministic action output to distil the fallback terms against (see CHANGELOG).
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import numpy as np
import torch

from prop_cli.constants import LEROBOT_DIR
from prop_cli.errors import PropError

from .base import Adapter, CheckpointOptions, LoadedModel, PolicyProtocol, finish
from .folder import CONFIG, WEIGHTS, read_config

PREPROCESSOR = "policy_preprocessor.json"
FOLDER_IN_BUNDLE = LEROBOT_DIR  # the bundle's LeRobot folder
SUPPORTED = ("act",)
ACTION, PAD = "action", "action_is_pad"
SETUP_HINT = "set up the LeRobot environment: bash scripts/setup-lerobot.sh (then use .venv-lerobot)"
# Keyed by default (measured in examples/RESULTS.md, "LeRobot ACT"): the feed-forward layers of the
# transformer encoder and decoder and the action head. Not the attention out_proj (never called through
# its forward) nor the VAE encoder (training only).
ACT_LAYERS = [r"model\.(encoder|decoder)\.layers\.\d+\.linear[12]", r"model\.action_head"]


def _lerobot():
    try:
        import lerobot
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    except ImportError:
        raise PropError("this is a LeRobot policy folder, but lerobot is not installed", SETUP_HINT) from None
    # Everything prop reads is local; a missing file must fail, never download.
    os.environ["HF_HUB_OFFLINE"] = "1"
    return lerobot.__version__, get_policy_class, make_pre_post_processors


def _folder_files(folder: Path) -> dict[str, bytes]:
    """The folder's config and processor files, by their path in the bundle."""
    names = [CONFIG] + sorted(p.name for p in folder.glob("policy_*processor*") if p.is_file())
    return {f"{FOLDER_IN_BUNDLE}/{n}": (folder / n).read_bytes() for n in names}


def _check_type(config: dict, where: str) -> str:
    kind = config.get("type")
    if kind == "diffusion":
        raise PropError(
            f"{where}: diffusion policies have no deterministic action output to distil the fallback "
            "terms against",
            "prop supports LeRobot act policies in this version",
        )
    if kind not in SUPPORTED:
        raise PropError(
            f"{where}: policy type {kind!r} is not supported", f"prop supports {', '.join(SUPPORTED)}"
        )
    return kind


def _load(folder: Path, weights: dict[str, torch.Tensor] | None, where: str):
    version, get_policy_class, make_pre_post_processors = _lerobot()
    kind = _check_type(read_config(folder), where)
    try:
        from lerobot.configs.policies import PreTrainedConfig

        cls = get_policy_class(kind)
        with contextlib.redirect_stdout(sys.stderr):  # LeRobot prints progress: stdout is for results
            if weights is None:
                policy = cls.from_pretrained(str(folder))
            else:
                policy = cls(PreTrainedConfig.from_pretrained(str(folder)))
                policy.load_state_dict(weights, strict=True)
            pre, post = make_pre_post_processors(policy.config, pretrained_path=str(folder))
    except PropError:
        raise
    except Exception as e:  # noqa: BLE001 - LeRobot's errors on a damaged or foreign folder
        raise PropError(
            f"{where}: LeRobot could not load the policy "
            f"({type(e).__name__}: {str(e).splitlines()[0][:160]})",
            "check that config.json, model.safetensors and the processor files belong together",
        ) from None
    return version, policy, pre, post


class LeRobotAdapter(Adapter):
    name = "lerobot"
    summary = (
        "a LeRobot policy folder: config.json (type act) + model.safetensors + policy_preprocessor.json "
        "and the other processor files, loaded by LeRobot (scripts/setup-lerobot.sh)"
    )

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return path.is_dir() and all((path / n).is_file() for n in (CONFIG, WEIGHTS, PREPROCESSOR))

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        from .weights import read_weights

        names = read_weights(path / WEIGHTS)[0]
        old = sorted(n for n in names if n.startswith(("normalize_inputs.", "normalize_targets.")))
        if old:
            raise PropError(
                f"{path}: the normalisation statistics are inside model.safetensors (LeRobot < 0.4 layout)",
                "migrate it with lerobot's processor/migrate_policy_normalization.py",
            )
        version, policy, pre, post = _load(path, None, str(path))
        return self._loaded(policy, pre, post, version, str(path), _folder_files(path))

    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        folder = Path(source) / FOLDER_IN_BUNDLE
        if not (folder / CONFIG).is_file() and (Path(source) / PREPROCESSOR).is_file():
            folder = Path(source)  # the original LeRobot folder itself (prop attack --original)
        if not (folder / CONFIG).is_file():
            raise PropError(f"bundle {source} has no {FOLDER_IN_BUNDLE}/{CONFIG}", "write the bundle again")
        version, policy, pre, post = _load(folder, weights, source)
        return self._loaded(policy, pre, post, version, source, _folder_files(folder))

    def _loaded(self, policy, pre, post, version: str, source: str, files: dict[str, bytes]) -> LoadedModel:
        module = finish(policy)
        spec = {"adapter": self.name, "type": policy.config.type, "lerobot_version": version}
        return LoadedModel(
            module=module,
            spec=spec,
            dtypes={k: v.dtype for k, v in module.state_dict().items()},
            input_shape=None,
            source=source,
            continuous=True,
            policy=LeRobotPolicy(module, pre, post),
            files=files,
            base_alias=f"{FOLDER_IN_BUNDLE}/{WEIGHTS}",
        )

    def weights(self, path: Path) -> dict[str, torch.Tensor]:
        from .weights import read_weights

        return read_weights(path / WEIGHTS if path.is_dir() else path)[0]

    def describe(self, loaded: LoadedModel) -> dict:
        info = super().describe(loaded)
        c = loaded.module.config
        info.update(type=c.type, lerobot_version=loaded.spec.get("lerobot_version"), chunk_size=c.chunk_size)
        info["inputs"] = {k: list(v) for k, v in loaded.policy.input_features.items()}
        return info


class LeRobotPolicy(PolicyProtocol):
    """ACT through the policy protocol: its own loss, its deployed chunk (latent z = 0), its processors."""

    default_layers = ACT_LAYERS
    fallbacks = ("distill",)

    def __init__(self, policy, pre, post) -> None:
        self.policy, self.pre, self.post = policy, pre, post
        self.config = policy.config

    @property
    def input_features(self) -> dict[str, tuple[int, ...]]:
        return {k: tuple(f.shape) for k, f in self.config.input_features.items()}

    def _windows(self, episodes: np.ndarray, deltas: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Row indices t + d for every row t and delta d, clamped to t's episode; and where they fell out."""
        n = len(episodes)
        starts = np.r_[0, np.flatnonzero(np.diff(episodes)) + 1]
        ends = np.r_[starts[1:], n] - 1
        ep_of = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, n]))
        idx = np.arange(n)[:, None] + np.asarray(deltas)[None, :]
        lo, hi = starts[ep_of][:, None], ends[ep_of][:, None]
        return np.clip(idx, lo, hi), (idx < lo) | (idx > hi)

    def batches(self, data, flag: str) -> dict[str, torch.Tensor]:
        x = data.x if isinstance(data.x, dict) else {}
        for name, shape in self.input_features.items():
            if name not in x:
                raise PropError(
                    f"{flag} {data.path}: no feature '{name}', which the policy takes "
                    f"(the data has {', '.join(sorted(x)) or 'no features'})",
                    "record the policy's input features (`prop inspect` lists them)",
                )
            if tuple(x[name].shape[1:]) != shape:
                raise PropError(
                    f"{flag} {data.path}: feature '{name}' has shape {tuple(x[name].shape[1:])}, the policy "
                    f"takes {shape}",
                    "use data recorded for this policy",
                )
        order = np.lexsort((x["frame_index"], x["episode_index"]))
        episodes = x["episode_index"][order]
        out = {k: torch.from_numpy(x[k][order]).float() for k in self.input_features}
        if data.y is not None:
            want = tuple(self.config.output_features[ACTION].shape)
            if tuple(data.y.shape[1:]) != want:
                raise PropError(
                    f"{flag} {data.path}: actions have shape {tuple(data.y.shape[1:])}, the policy's {want}",
                    "use data recorded for this policy",
                )
            # The policy's own action window (LeRobot's action_delta_indices), padded at episode ends.
            idx, pad = self._windows(episodes, list(self.config.action_delta_indices))
            out[ACTION] = torch.from_numpy(data.y[order][idx]).float()
            out[PAD] = torch.from_numpy(pad)
        out = self.pre(out)
        out = {k: v for k, v in out.items() if isinstance(v, torch.Tensor)}
        out["episode_index"] = torch.from_numpy(episodes.astype(np.int64))
        return out

    def _model_batch(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        # What ACTPolicy.forward does before calling its model: the list of camera tensors.
        b = {k: v for k, v in batch.items() if k != "episode_index"}
        if self.config.image_features:
            b["observation.images"] = [b[k] for k in self.config.image_features]
        return b

    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.policy.train()
        return self.policy.forward({k: v for k, v in batch.items() if k != "episode_index"})[0]

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        # The deployed path: eval mode (dropout off, and the VAE latent is 0, as select_action runs it).
        self.policy.eval()
        return self.policy.model(self._model_batch({k: batch[k] for k in self.input_features}))[0]

    def example(self, rows: int, data: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        idx = torch.arange(rows) % len(data[next(iter(self.input_features))])
        return {k: data[k][idx] for k in self.input_features}

    def controller(self, module: torch.nn.Module) -> Controller:
        return Controller(module, self.pre, self.post, list(self.input_features))


class Controller:
    """Closed loop: LeRobot's preprocessor -> select_action (its action queue) -> postprocessor."""

    def __init__(self, module, pre, post, features: list[str]) -> None:
        self.module, self.pre, self.post, self.features = module.eval(), pre, post, features

    def reset(self) -> None:
        self.module.reset()

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        x = {}
        for k in self.features:
            v = torch.from_numpy(np.ascontiguousarray(obs[k]))
            if v.dtype == torch.uint8 and v.dim() == 3:  # an HWC camera frame -> CHW in [0, 1]
                v = v.permute(2, 0, 1).float() / 255.0
            x[k] = v.float()
        return self.post(self.module.select_action(self.pre(x)))[0].numpy()
