"""Which recipe trains a model: {array model, policy with its own loss} x {unsealed, sealed}, decided
here and nowhere else. Each recipe receives its own mode's settings (``Job.mode``) and no other's."""

from __future__ import annotations

from prop_adapters import LoadedModel
from prop_cli.config import PersonalizeConfig, SealedConfig, UnsealedConfig
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from . import array, policy, sealed_array, sealed_policy
from .distributed import Ranks
from .recipe import Job, Progress, Recipe, SealedRecipe, Status, Trained, User


def settled(loaded: LoadedModel, cfg: PersonalizeConfig) -> PersonalizeConfig:
    """``cfg`` with the settings whose default depends on the model's kind filled in: what trains, and
    what the manifest records (so a bundle names the value it was trained with, not "the default")."""
    if not isinstance(cfg.mode, UnsealedConfig):
        return cfg
    return PersonalizeConfig(cfg.train, cfg.mode.for_kind("array" if loaded.policy is None else "policy"))


def sealed_recipe(loaded: LoadedModel) -> SealedRecipe:
    return sealed_policy.RECIPE if loaded.policy is not None else sealed_array.RECIPE


def unsealed_recipe(loaded: LoadedModel, mode: UnsealedConfig) -> Recipe[UnsealedConfig]:
    if loaded.policy is None:
        if mode.fallback_every != 1:  # an array model's step is cheap (its fallback rows are one matmul)
            raise PropError(
                f"--fallback-every {mode.fallback_every} applies to LeRobot policies only",
                "drop --fallback-every for this model",
            )
        return array.RECIPE
    if given := [f for f in mode.hardening.flags() if not f.startswith("--antipode-codes")]:
        # --harden's measures (train.hardening) are the array trainer's, but for --antipode-codes (issue
        # 43: the wrong keys farthest from the user's code were the ones that drifted). A policy bundle
        # recorded them in its manifest without having trained any of them, so a policy refuses them.
        raise PropError(
            f"{', '.join(given)}: the LeRobot policy trainer does not train --harden's measures yet (a "
            "policy bundle would record them without having them)",
            "drop them (the default unsealed mode), or --seal for a bundle whose payload stays encrypted",
        )
    return policy.RECIPE


def choose(loaded: LoadedModel, mode: UnsealedConfig | SealedConfig) -> Recipe:
    if isinstance(mode, SealedConfig):
        return sealed_recipe(loaded)
    return unsealed_recipe(loaded, mode)


def personalize(
    loaded: LoadedModel,
    users: list[User],
    cfg: PersonalizeConfig,
    general: Dataset | None = None,
    device: str = "cpu",
    progress: Progress | None = None,
    ranks: Ranks | None = None,
    status: Status | None = None,
) -> Trained:
    """Train ``loaded`` for ``users`` with the recipe for its kind and ``cfg``'s mode; the loaded module is
    updated in place (unsealed) or stays the original (sealed). ``ranks``: the processes `accelerate
    launch` started (``distributed``), every recipe data parallel."""
    if not users:
        raise PropError("no user data given", "pass --data and --key-file (or --passphrase)")
    cfg = settled(loaded, cfg)
    recipe = choose(loaded, cfg.mode)
    job = Job(loaded, cfg.train, cfg.mode, device, progress, ranks or Ranks(), status)
    return recipe.personalize(job, users, general)
