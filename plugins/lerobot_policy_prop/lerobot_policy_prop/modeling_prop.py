"""``PropPolicy``: the bundle's LeRobot policy under the user's key, as LeRobot's tools drive a policy.

LeRobot calls ``select_action`` / ``predict_action_chunk`` between the processors ``processor_prop``
hands it (the bundle's own) and ``reset`` between episodes; each goes to the bundle's policy (ACT,
Diffusion, SmolVLA, pi0, pi0.5) unchanged, so no key runs the original exactly as LeRobot runs it.
Everything that can refuse (the bundle changed or rolled back, code in it, a key enrolled in nothing, a
feature the host does not give) refuses while the policy is built, before the first action, in one line.
Training and saving are refused: the policy under a key is the user's behaviour in the clear.
"""

from __future__ import annotations

import getpass
import os
import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from lerobot.policies.pretrained import PreTrainedPolicy

from prop_cli.constants import ENV_PASSPHRASE
from prop_cli.errors import PropError
from prop_cli.run.hosted import Hosted, host_policy, match_features

from .configuration_prop import PropConfig, refuse

_HOSTED = "_prop_hosted"  # where the loaded bundle waits on the config (not a dataclass field: never dumped)
_LAST: list[Hosted] = []  # the bundle this process hosts (a policy folder's processor step runs it)


def last_hosted() -> Hosted | None:
    """The bundle of the prop policy built last in this process (LeRobot's tools build one)."""
    return _LAST[-1] if _LAST else None


def resize_frames(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Camera frames (..., C, H, W) resized to ``size``: bilinear, antialiased. Record a policy's data
    with this same function to run it with --policy.resize_images=true."""
    lead = x.shape[:-3]
    y = F.interpolate(x.reshape(-1, *x.shape[-3:]).float(), size=tuple(size), mode="bilinear",
                      antialias=True, align_corners=False)  # fmt: skip
    return y.reshape(*lead, *y.shape[-3:]).to(x.dtype)


def _passphrase(config: PropConfig) -> str | None:
    if not config.passphrase:
        return None
    value = os.environ.get(ENV_PASSPHRASE)
    if value is not None:
        return value
    if not sys.stdin.isatty():
        raise PropError("--policy.passphrase=true needs a terminal to ask on",
                        f"set {ENV_PASSPHRASE} for scripts, or use --policy.key_file")  # fmt: skip
    return getpass.getpass(f"Passphrase for {config.bundle}: ")


def hosted_for(config: PropConfig) -> Hosted:
    """The bundle of ``config``, read and checked once: LeRobot builds the policy and then its
    processors from the same config object."""
    hosted = getattr(config, _HOSTED, None)
    if hosted is None:
        try:
            hosted = host_policy(
                Path(config.bundle), key_file=Path(config.key_file) if config.key_file else None,
                passphrase=_passphrase(config), allow_unenrolled_key=config.allow_unenrolled_key,
                allow_rollback=config.allow_rollback, trust_remote_code=config.trust_remote_code,
                through_encoder=config.through_encoder,
            )  # fmt: skip
        except PropError as e:
            refuse(e)
        object.__setattr__(config, _HOSTED, hosted)
    _LAST[:] = [hosted]
    return hosted


class PropPolicy(PreTrainedPolicy):
    config_class = PropConfig
    name = "prop"

    def __init__(self, config: PropConfig, dataset_stats=None, dataset_meta=None, **_) -> None:
        super().__init__(config)
        hosted = hosted_for(config)
        self.resize: dict[str, tuple[int, ...]] = {}
        # Tools that load by path (lerobot-rollout) know the robot's features only after the policy is
        # built: then they are matched on the first observation, before its action is taken.
        self.unmatched = not config.input_features
        if not self.unmatched:
            where = "the dataset" if dataset_meta is not None else "the environment"
            try:
                self.resize = match_features(
                    hosted,
                    {k: tuple(f.shape) for k, f in config.input_features.items()},
                    {k: tuple(f.shape) for k, f in (config.output_features or {}).items()},
                    where, resize_images=config.resize_images,
                )  # fmt: skip
            except PropError as e:
                refuse(e)
        self.policy = hosted.module  # the bundle's LeRobot policy, under the key
        self.keyed = hosted.keyed
        self.hosted = hosted

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *, config: PropConfig | None = None, **kwargs):
        """``--policy.path=FOLDER``: the folder ``prop export --lerobot`` wrote names the bundle, relative
        to itself; no weights are read from it (the bundle holds them, verified)."""
        folder = Path(pretrained_name_or_path)
        if config is None:
            config = PropConfig.from_pretrained(folder)
        bundle = Path(config.bundle)
        if not bundle.is_absolute():
            config.bundle = str(folder / bundle)
        keep = {k: v for k, v in kwargs.items() if k in ("dataset_stats", "dataset_meta")}
        return cls(config, **keep)

    def _inputs(self, batch: dict) -> dict:
        if self.unmatched:
            given = {k: tuple(v.shape[1:]) for k, v in batch.items() if isinstance(v, torch.Tensor)}
            try:
                self.resize = match_features(self.hosted, given, {}, "the observation",
                                             resize_images=self.config.resize_images)  # fmt: skip
            except PropError as e:
                refuse(e)
            self.unmatched = False
        if not self.resize:
            return batch
        batch = dict(batch)
        for name, shape in self.resize.items():
            batch[name] = resize_frames(batch[name], shape[1:])
        return batch

    @torch.no_grad()
    def select_action(self, batch: dict, **kwargs) -> torch.Tensor:
        return self.policy.select_action(self._inputs(batch), **kwargs)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict, **kwargs) -> torch.Tensor:
        return self.policy.predict_action_chunk(self._inputs(batch), **kwargs)

    def reset(self) -> None:
        self.policy.reset()

    def forward(self, batch: dict):
        self.config.get_optimizer_preset()  # refuses: prop personalize trains the bundle

    def get_optim_params(self) -> dict:
        self.config.get_optimizer_preset()
        return {}

    def save_pretrained(self, *_, **__) -> None:
        refuse(PropError(
            "a prop policy is not saved as a LeRobot checkpoint (under a key its weights are the user's "
            "behaviour in the clear)",
            "keep the bundle itself; share it with prop push",
        ))  # fmt: skip

    _save_pretrained = push_model_to_hub = push_to_hub = save_pretrained
