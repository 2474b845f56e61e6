"""Data sources: where ``--data`` and ``--general-data`` samples come from (contract: ``base``).

``SOURCES`` is the registry, in the order formats are tried: the first source whose ``recognise``
accepts a path reads it. A new format is one new file and one line here.
"""

from __future__ import annotations

from pathlib import Path

from prop_cli.errors import PropError

from .base import Dataset, DataSource, Observations
from .lerobot import LeRobotSource
from .npz import NpzSource

SOURCES: list[DataSource] = [
    NpzSource(),
    LeRobotSource(),
]

__all__ = ["SOURCES", "DataSource", "Dataset", "Observations", "load_data"]


def load_data(
    path: str | Path, *, require_y: bool = True, min_samples: int = 10, flag: str = "--data"
) -> Dataset:
    """Read samples with the first registered source that recognises ``path``."""
    path = Path(path)
    if not path.exists():
        for source in SOURCES:
            if source.selects and source.recognise(path):  # a root plus a selection (ROOT:episodes=...)
                return source.load(path, require_y=require_y, min_samples=min_samples)
        raise PropError(f"data file {path} does not exist", "check the path")
    for source in SOURCES:
        if source.recognise(path):
            return source.load(path, require_y=require_y, min_samples=min_samples)
    if path.is_dir():
        raise PropError(
            f"data file {path} is a directory", "pass an .npz file (`prop formats` lists formats)"
        )
    raise PropError(
        f"{flag} {path} is in no data format prop reads",
        "use " + "; or ".join(s.summary for s in SOURCES) + " (`prop formats` lists them)",
    )
