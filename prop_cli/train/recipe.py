"""What every training recipe takes and gives back (the contract; ``choose`` picks the recipe).

A recipe trains one kind of model in one mode: {array model, policy with its own loss} x {unsealed,
sealed}. It takes the loaded checkpoint and the users (data and key) and returns a ``Trained`` that
writes its bundle once, with the users' reports.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np
from torch import nn

from prop_adapters import LoadedModel
from prop_cli.config import Mode, SealedConfig, TrainConfig
from prop_cli.datasources import Dataset

from .distributed import Ranks

Progress = Callable[[int, dict[str, float]], None]  # (step, latest losses)
# What a run is doing outside its steps (set-up before the first, the report after the last), one line each:
# a real-size policy spends minutes there, and a user should not watch a silent terminal.
Status = Callable[[str], None]
M = TypeVar("M", bound=Mode)  # the mode's own settings: a recipe sees its own part and no other's


@dataclass
class Job(Generic[M]):
    """One training run: the model, its settings (every mode's, and its own mode's), where it computes,
    and who hears of its progress."""

    loaded: LoadedModel
    train: TrainConfig
    mode: M
    device: str = "cpu"
    progress: Progress | None = None
    ranks: Ranks = field(default_factory=Ranks)  # the processes training together (``distributed``)
    status: Status | None = None

    def say(self, what: str) -> None:
        """Tell whoever listens what the run is doing now (on the process that reports only)."""
        if self.status is not None and self.ranks.is_main:
            self.status(what)


@dataclass
class User:
    data: Dataset
    key_bits: np.ndarray  # 0/1, the user's key (never stored)


@dataclass
class Written:
    """What writing a trained bundle produced: the manifest, each user's report, the last step's losses."""

    manifest: dict
    metrics: list[dict]
    final_losses: dict[str, float]


class Trained(ABC):
    """A trained model, ready to be written as a bundle."""

    task: str

    @abstractmethod
    def write(self, out: Path, manifest: dict, *, force: bool = False) -> Written:
        """Write the bundle to ``out``. ``manifest`` holds the fields every mode shares (model, key source
        and passphrase salt, config, io.checkpoint); the recipe adds its own."""


class Recipe(ABC, Generic[M]):
    @abstractmethod
    def personalize(self, job: Job[M], users: list[User], general: Dataset | None = None) -> Trained:
        """Train ``job.loaded`` (in place) for ``users``; ``general``: inputs where the original is kept."""


@dataclass
class SealedUser:
    payload: nn.Module  # prop_cli.core.payload.Payload
    private: dict  # sealed with the payload: the user's personalization and training settings
    bits: np.ndarray
    val: Dataset  # held-out rows, as the report view takes them


class SealedRecipe(Recipe[SealedConfig]):
    """A sealed recipe trains each user alone, so one more user can be added to a bundle later."""

    @abstractmethod
    def train_users(
        self, job: Job[SealedConfig], datasets: list[Dataset], keys: list[np.ndarray], task: str | None,
        first_index: int = 0,
    ) -> tuple[list[SealedUser], str, dict[str, int]]:
        """Each user's payload on their own data (users numbered from ``first_index``); returns the users,
        the task (``task``: an override) and the keyed layers' batch axes (policies; empty otherwise)."""

    @abstractmethod
    def report_view(self, loaded: LoadedModel) -> nn.Module:
        """The array module a sealed user's report runs keys through (a policy's flat view)."""
