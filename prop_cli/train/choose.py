"""Which recipe trains a model: {array model, policy with its own loss} x {unsealed, sealed}, decided
here and nowhere else."""

from __future__ import annotations

from prop_adapters import LoadedModel
from prop_cli.config import PersonalizeConfig
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from . import array, policy, sealed_array, sealed_policy
from .distributed import Ranks
from .recipe import Job, Progress, Recipe, SealedRecipe, Trained, User


def sealed_recipe(loaded: LoadedModel) -> SealedRecipe:
    return sealed_policy.RECIPE if loaded.policy is not None else sealed_array.RECIPE


def choose(loaded: LoadedModel, sealed: bool) -> Recipe:
    if sealed:
        return sealed_recipe(loaded)
    return policy.RECIPE if loaded.policy is not None else array.RECIPE


def personalize(
    loaded: LoadedModel,
    users: list[User],
    cfg: PersonalizeConfig,
    general: Dataset | None = None,
    device: str = "cpu",
    progress: Progress | None = None,
    ranks: Ranks | None = None,
) -> Trained:
    """Train ``loaded`` for ``users`` with the recipe for its kind and ``cfg.seal``; the loaded module is
    updated in place (unsealed) or stays the original (sealed). ``ranks``: the processes `accelerate
    launch` started (``distributed``), every recipe data parallel."""
    if not users:
        raise PropError("no user data given", "pass --data and --key-file (or --passphrase)")
    recipe = choose(loaded, cfg.seal)
    return recipe.personalize(Job(loaded, cfg, device, progress, ranks or Ranks()), users, general)
