"""How prop trains and runs a LeRobot policy through the policy protocol (``PolicyProtocol``): its own
loss, its deployed action chunk, its processors, and a closed-loop controller.

``LeRobotPolicy`` is ACT, and what every LeRobot policy shares (batches cut from a dataset's frames with
the policy's own delta indices, processors, the controller); ``diffusion.DiffusionPolicy`` is what
differs for Diffusion. No lerobot import here: the policy, preprocessor and postprocessor objects come
from ``adapter``.
"""

from __future__ import annotations

import numpy as np
import torch

from prop_adapters.base import PolicyProtocol
from prop_cli.errors import PropError

ACTION, PAD = "action", "action_is_pad"
# Keyed by default (measured in examples/RESULTS.md, "LeRobot ACT"): the feed-forward layers of the
# transformer encoder and decoder and the action head. Not the attention out_proj (never called through
# its forward) nor the VAE encoder (training only).
ACT_LAYERS = [r"model\.(encoder|decoder)\.layers\.\d+\.linear[12]", r"model\.action_head"]
FALLBACK_DRAWS = 8  # a denoising policy's (t, noise) draws per fallback frame (Diffusion, SmolVLA)
POOL_BATCH = 256  # rows per forward while the fallback targets are drawn


class LeRobotPolicy(PolicyProtocol):
    """ACT through the policy protocol: its own loss, its deployed chunk (latent z = 0), its processors."""

    default_layers = ACT_LAYERS
    fallbacks = ("distill",)

    def __init__(self, policy, pre, post, noise_seed: int = 0) -> None:
        self.policy, self.pre, self.post = policy, pre, post
        self.config = policy.config
        self.noise_seed = noise_seed

    def on(self, module) -> LeRobotPolicy:
        return type(self)(module, self.pre, self.post, self.noise_seed)

    @property
    def input_features(self) -> dict[str, tuple[int, ...]]:
        return {k: tuple(f.shape) for k, f in self.config.input_features.items()}

    @property
    def history(self) -> list[int] | None:
        """The observation frames a row holds, relative to its own (Diffusion: the last n_obs_steps);
        None: the frame alone, without a time axis (ACT)."""
        deltas = getattr(self.config, "observation_delta_indices", None)
        return None if deltas is None else list(deltas)

    @property
    def row_shapes(self) -> dict[str, tuple[int, ...]]:
        h = self.history
        return {k: s if h is None else (len(h), *s) for k, s in self.input_features.items()}

    def describe(self) -> dict:
        return {"chunk_size": self.config.chunk_size}

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
        if self.history is None:
            out = {k: torch.from_numpy(x[k][order]).float() for k in self.input_features}
        else:  # each row's observation history, the episode's first frame repeated before it (as LeRobot)
            obs_idx, _ = self._windows(episodes, self.history)
            out = {k: torch.from_numpy(x[k][order][obs_idx]).float() for k in self.input_features}
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
        out = self.pre(out | self._complementary(x, order, flag, data.path))
        out = {k: v for k, v in out.items() if isinstance(v, torch.Tensor)}
        out["episode_index"] = torch.from_numpy(episodes.astype(np.int64))
        return out

    def _denoiser_pool(
        self, batch: dict[str, torch.Tensor], chunks: torch.Tensor, original: PolicyProtocol,
        generator: torch.Generator, noised,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:  # fmt: skip
        """A denoising policy's fallback rows: FALLBACK_DRAWS per frame, each with the ``{"x_t", "t"}``
        that ``noised(x0, generator)`` makes of the frame's chunk, and the original's output on each."""
        rows = {k: v.repeat_interleave(FALLBACK_DRAWS, 0) for k, v in batch.items()}
        rows |= noised(chunks.repeat_interleave(FALLBACK_DRAWS, 0), generator)
        n = len(rows["t"])
        with torch.no_grad():
            targets = torch.cat([
                original.fallback_output({k: v[i : i + POOL_BATCH] for k, v in rows.items()})
                for i in range(0, n, POOL_BATCH)
            ])  # fmt: skip
        return rows, targets

    def _complementary(self, x: dict, order: np.ndarray, flag: str, path: str) -> dict:
        """What the preprocessor takes beside the tensors (SmolVLA: each frame's task text)."""
        return {}

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
        return self.policy.model(self._model_batch({k: batch[k] for k in self.row_shapes}))[0]

    def example(self, rows: int, data: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        idx = torch.arange(rows) % len(data[next(iter(self.row_shapes))])
        return {k: data[k][idx] for k in self.row_shapes}

    def controller(self, module: torch.nn.Module) -> Controller:
        return Controller(module, self.pre, self.post, list(self.input_features), self.noise_seed)


class Controller:
    """Closed loop: LeRobot's preprocessor -> select_action (its queues) -> postprocessor.

    LeRobot's samplers (Diffusion's DDPM/DDIM steps) draw from torch's global generator. Each call runs
    with that generator seeded from (noise seed, the episode's seed, the call's number) and restored
    afterwards: an episode's noise is reproducible and the same under every key, and nothing else's
    random stream moves."""

    def __init__(
        self, module, pre, post, features: list[str], noise_seed: int = 0, extra: dict | None = None
    ) -> None:
        self.module, self.pre, self.post, self.features = module.eval(), pre, post, features
        self.noise_seed, self.episode, self.calls = noise_seed, 0, 0
        self.extra = dict(extra or {})  # what the preprocessor takes beside the features (SmolVLA's task)

    def reset(self, seed: int | None = None) -> None:
        self.module.reset()
        self.episode, self.calls = int(seed or 0), 0

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        x = {}
        for k in self.features:
            v = torch.from_numpy(np.ascontiguousarray(obs[k]))
            if v.dtype == torch.uint8 and v.dim() == 3:  # an HWC camera frame -> CHW in [0, 1]
                v = v.permute(2, 0, 1).float() / 255.0
            x[k] = v.float()
        seed = np.random.SeedSequence([self.noise_seed, self.episode, self.calls]).generate_state(1)[0]
        self.calls += 1
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            return self.post(self.module.select_action(self.pre(x | self.extra)))[0].numpy()
