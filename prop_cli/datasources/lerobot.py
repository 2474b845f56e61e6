"""A local LeRobotDataset root (codebase v3.0) as ``--data`` / ``--general-data``; never downloaded.

``ROOT`` reads every episode, ``ROOT:episodes=0-15,20`` a selection of episodes, ``ROOT:frames=0-99`` the
frames whose ``frame_index`` is in the list (each episode then ends at its last selected frame: action
chunks are cut from the selected frames, padded as at an episode's end); both combine as
``ROOT:episodes=0-3:frames=0-49``. Every frame is one row: ``x`` holds
each state, environment and image feature (images as CHW float in [0, 1], as LeRobot yields them) plus
``episode_index`` and ``frame_index``; ``y`` is the recorded ``action``. Action chunks are cut per
policy from these rows (``prop_adapters.lerobot``), with the policy's own delta indices.

Needs the optional lerobot environment (scripts/setup-lerobot.sh). ``meta/info.json`` and the
episode selection are checked before LeRobot is touched: LeRobot fetches an episode missing from a
local root from the Hub, which prop never lets it do.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from prop_cli.constants import TASK
from prop_cli.errors import PropError, plural

from .base import Dataset, DataSource

INFO = Path("meta") / "info.json"
SELECTORS = (":episodes=", ":frames=")
MAX_INDEX = 1 << 24  # bounds what a selection may expand to
CODEBASE = "v3.0"
ACTION = "action"
INDEX_COLUMNS = ("episode_index", "frame_index")
# Columns every LeRobotDataset has that are not observations.
_BOOKKEEPING = {"timestamp", "frame_index", "episode_index", "index", "task_index"}
SETUP_HINT = "set up the LeRobot environment: bash scripts/setup-lerobot.sh (then use .venv-lerobot)"


def split_path(path: Path) -> tuple[Path, str | None, str | None]:
    """``ROOT:episodes=E:frames=F`` -> (ROOT, E, F); either part may be absent (None)."""
    text, parts = str(path), {}
    while True:
        cut = max(text.rfind(m) for m in SELECTORS)
        if cut < 0:
            return Path(text), parts.get(":episodes="), parts.get(":frames=")
        marker = next(m for m in SELECTORS if text.startswith(m, cut))
        parts.setdefault(marker, text[cut + len(marker) :])
        text = text[:cut]


def parse_list(spec: str, where: str, what: str) -> list[int]:
    """``0-15,20`` -> [0, ..., 15, 20] (ranges inclusive)."""
    out: set[int] = set()
    for part in spec.replace(" ", "").split(","):
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if not m:
            raise PropError(
                f"{where}: {what} selection {spec!r} is not a list of {what}s",
                f"write it like :{what}s=0-15,20 (ranges are inclusive)",
            )
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        if lo > hi:
            raise PropError(f"{where}: {what} range {part!r} runs backwards", "write ranges as low-high")
        if hi >= MAX_INDEX:
            raise PropError(f"{where}: {what} {hi} is out of range", f"select {what}s below {MAX_INDEX}")
        out.update(range(lo, hi + 1))
    return sorted(out)


def parse_episodes(spec: str, total: int, where: str) -> list[int]:
    """``0-15,20`` -> [0, ..., 15, 20], each checked against the root's total_episodes."""
    out = parse_list(spec, where, "episode")
    missing = sorted(e for e in out if e >= total)
    if missing:
        raise PropError(
            f"{where}: episodes {missing[:5]} are not in the root (it has episodes 0-{total - 1})",
            "select episodes that were recorded there",
        )
    return sorted(out)


def read_info(root: Path, where: str) -> dict:
    try:
        info = json.loads((root / INFO).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PropError(
            f"{where}: {INFO} is not readable JSON ({type(e).__name__})", "re-record it"
        ) from None
    version = info.get("codebase_version")
    if version != CODEBASE:
        raise PropError(
            f"{where}: LeRobotDataset codebase {version!r}; prop reads {CODEBASE}",
            "convert it with LeRobot's dataset conversion script",
        )
    for field in ("features", "fps", "total_episodes"):
        if field not in info:
            raise PropError(f"{where}: {INFO} has no {field!r}", "the root is damaged; re-record it")
    return info


class LeRobotSource(DataSource):
    name = "lerobot"
    summary = (
        "a local LeRobotDataset root (v3.0; ROOT, ROOT:episodes=0-15,20, ROOT:frames=0-99, or both), "
        "with lerobot installed"
    )
    selects = True

    def recognise(self, path: Path) -> bool:
        return (split_path(path)[0] / INFO).is_file()

    def load(self, path: Path, *, require_y: bool = True, min_samples: int = 10) -> Dataset:
        root, spec, frame_spec = split_path(path)
        where = str(path)
        frames = parse_list(frame_spec, where, "frame") if frame_spec else None
        info = read_info(root, where)
        features = info["features"]
        episodes = parse_episodes(spec, int(info["total_episodes"]), where) if spec else None
        if require_y and ACTION not in features:
            raise PropError(f"{where}: the dataset has no '{ACTION}' feature", "record the actions too")
        video = sorted(k for k, f in features.items() if f.get("dtype") == "video")
        if video:
            raise PropError(
                f"{where}: features {', '.join(video)} are videos; prop reads state and image features",
                "record camera frames with dtype 'image', or drop the video features from the policy",
            )
        try:
            from lerobot.datasets.lerobot_dataset import LeRobotDataset
        except ImportError:
            raise PropError(
                f"{where} is a LeRobotDataset, but lerobot is not installed", SETUP_HINT
            ) from None
        # Offline for good: a missing file must be an error here, not a download.
        os.environ["HF_HUB_OFFLINE"] = "1"
        try:
            # pyav: prop reads no video, and LeRobot 0.6 otherwise probes torchcodec (a long log without it).
            ds = LeRobotDataset(
                repo_id=f"local/{root.name}", root=root, episodes=episodes, video_backend="pyav"
            )
            table = ds.hf_dataset
            columns = [c for c in table.column_names if c not in _BOOKKEEPING or c in INDEX_COLUMNS]
            rows = table[0 : len(table)]
        except PropError:
            raise
        except Exception as e:  # noqa: BLE001 - LeRobot/pyarrow errors on a damaged root
            raise PropError(
                f"{where}: LeRobot could not read the root "
                f"({type(e).__name__}: {str(e).splitlines()[0][:120]})",
                "check the root (meta/, data/) or re-record it",
            ) from None
        x: dict[str, np.ndarray] = {}
        y = None
        for c in columns:
            if c == "task":
                continue
            value = rows[c]
            arr = np.stack([np.asarray(v) for v in value]) if isinstance(value, list) else np.asarray(value)
            if c == ACTION:
                y = arr.astype(np.float32)
            elif arr.dtype.kind in "biuf":
                x[c] = arr if c in INDEX_COLUMNS else arr.astype(np.float32)
        if "task_index" in table.column_names:
            # Each frame's task text (a language-conditioned policy's instruction, e.g. SmolVLA's).
            names = {int(i): str(t) for t, i in zip(ds.meta.tasks.index, ds.meta.tasks["task_index"])}
            x[TASK] = np.array([names.get(int(i), "") for i in rows["task_index"]], dtype=str)
        if frames is not None and "frame_index" in x:
            keep = np.isin(x["frame_index"], frames)
            x = {k: v[keep] for k, v in x.items()}
            y = None if y is None else y[keep]
        n = len(x["episode_index"]) if "episode_index" in x else 0
        if n < min_samples:
            raise PropError(
                f"{where}: {plural(n, 'frame')}, fewer than the {min_samples} needed", "record more episodes"
            )
        for k, v in x.items():
            if v.dtype.kind == "f" and not np.isfinite(v).all():
                raise PropError(f"{where}: feature '{k}' has NaN or inf", "drop or fix those frames")
        meta = {
            "fps": info["fps"],
            "root": str(root),
            "episodes": episodes,
            "frames": frames,
            "features": features,
        }
        return Dataset(x=x, y=y, path=where, meta=meta)
