"""What commands feed a bundle: inputs from a file, checked against the bundle's recorded input shape
(``policy.run_array`` runs an array model on them, a shape error said in one line)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.datasources import load_data
from prop_cli.datasources.npz import read_npy
from prop_cli.errors import PropError


def load_inputs(path: Path, bundle: Bundle, flag: str = "--input") -> np.ndarray:
    """Inputs for `prop run`: a .npy array, or the ``x`` of a data file; checked against the bundle."""
    path = Path(path)
    if path.suffix == ".npy":
        if not path.is_file():
            raise PropError(f"{flag} {path} does not exist", "give a .npy or .npz file")
        fix = "save inputs with numpy.save"
        x = read_npy(lambda: np.load(path, allow_pickle=False), f"{flag} {path}", fix)
        if not isinstance(x, np.ndarray) or x.ndim == 0:
            raise PropError(f"{flag} {path} holds no array of samples", fix)
        if x.dtype.kind not in "fiu" or not np.isfinite(x).all():
            raise PropError(f"{flag} {path} must hold finite numbers", "check the array")
        x = x.astype(np.float32)
    else:
        x = load_data(path, require_y=False, min_samples=1, flag=flag).x
    want = tuple(bundle.manifest[C.M_IO]["input_shape"])
    if x.shape[1:] != want:
        if x.shape == want:
            x = x[None]  # a single sample
        elif not _other_size(x.shape[1:], want):
            raise PropError(
                f"{flag} {path}: samples have shape {x.shape[1:]}, the bundle expects {want}",
                "give an array of shape (N, " + ", ".join(map(str, want)) + ")",
            )
    return x


def _other_size(got: tuple, want: tuple) -> bool:
    """Images of another size than the bundle was personalized on (same channels): a fully
    convolutional model takes them. Whether this one does shows when it runs (``policy.run_array``)."""
    return len(want) >= 2 and len(got) == len(want) and got[0] == want[0]
