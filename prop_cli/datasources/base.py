"""The data-source contract: a file or folder of samples -> a ``Dataset`` the trainer and audit use.

A data source is one file holding a subclass of :class:`DataSource` plus one line in the registry
(``prop_cli.datasources.SOURCES``). It reads and checks what its format can check (numbers, finite,
shapes, one target per input); what depends on the model (features, task, bounds) is checked later
against the checkpoint (``prop_cli.fit``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

# Observations: one array (N, *features) today; a dict of arrays (e.g. images + state) is allowed by
# the type so formats with several inputs can grow into it.
Observations = np.ndarray | dict[str, np.ndarray]


def take(x: Observations, idx: np.ndarray) -> Observations:
    """Rows ``idx`` of an array or of every array of a dict."""
    return {k: v[idx] for k, v in x.items()} if isinstance(x, dict) else x[idx]


@dataclass
class Dataset:
    x: Observations  # float32 (N, *features); see Observations
    y: np.ndarray | None  # targets as read: numbers (N,) or (N, d); their meaning is decided per model
    path: str
    meta: dict = field(default_factory=dict)  # what the source knows beyond x and y (e.g. episodes)

    def __len__(self) -> int:
        x = next(iter(self.x.values())) if isinstance(self.x, dict) else self.x
        return int(x.shape[0])

    def subset(self, idx: np.ndarray) -> Dataset:
        return Dataset(take(self.x, idx), None if self.y is None else self.y[idx], self.path, dict(self.meta))


class DataSource(ABC):
    """One data format. Subclasses set ``name`` and ``summary`` and implement ``recognise`` and ``load``."""

    name: ClassVar[str]
    summary: ClassVar[str]  # one line for `prop formats`, help texts and docs/formats.md
    # True if a path may carry a selection after the file or folder name (so it need not exist as is).
    selects: ClassVar[bool] = False

    @abstractmethod
    def recognise(self, path: Path) -> bool:
        """Cheap: is ``path`` in this format (suffix, files present, a peek at a header)?"""

    @abstractmethod
    def load(self, path: Path, *, require_y: bool, min_samples: int) -> Dataset:
        """Read and check the samples; every problem is a one-line PropError naming the file and field."""
