"""Image classification (paper Sec. "Image Classification"): personalized label (l + k) mod 10.

Data: scikit-learn's bundled 8x8 digits (real handwriting, offline), split 60/20/20 into base training,
user data and test (``examples.digits_task``); or, with ``--mnist DIR``, local MNIST idx files (never
downloaded). The base is an MLP (the issue allows an MLP; the paper used conv layers + batch norm).
"""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from examples import digits_task
from examples.reproduce import common
from prop_cli.errors import PropError

TOTAL_PARAMS = 50_000  # sklearn digits; with MNIST the 784-wide input makes the base alone ~118k
MNIST_ENCODER = 64
MNIST_SIZES = (10_000, 2_000, 2_000)  # base training, user, test samples taken from MNIST
OFFSET = digits_task.OFFSET
MNIST_FILES = {
    "train_x": "train-images-idx3-ubyte",
    "train_y": "train-labels-idx1-ubyte",
    "test_x": "t10k-images-idx3-ubyte",
    "test_y": "t10k-labels-idx1-ubyte",
}


def _read_idx(path: Path) -> np.ndarray:
    raw = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
    if len(raw) < 4 or raw[0] != 0 or raw[1] != 0 or raw[2] != 8:
        raise PropError(
            f"--mnist: {path} is not an idx file of unsigned bytes", "give the original MNIST files"
        )
    ndim = raw[3]
    shape = tuple(int.from_bytes(raw[4 + 4 * i : 8 + 4 * i], "big") for i in range(ndim))
    data = np.frombuffer(raw, dtype=np.uint8, offset=4 + 4 * ndim)
    if data.size != int(np.prod(shape)):
        raise PropError(f"--mnist: {path} is truncated", "download the MNIST files again, yourself")
    return data.reshape(shape)


def load_mnist(folder: Path, seed: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """base/user/test splits (x in [0, 1] flattened to 784, y) from local idx files (.gz or not)."""
    arrays = {}
    for name, stem in MNIST_FILES.items():
        found = [folder / stem, folder / (stem + ".gz")]
        path = next((p for p in found if p.is_file()), None)
        if path is None:
            raise PropError(
                f"--mnist {folder}: {stem}[.gz] not found",
                "point --mnist at a folder with the four MNIST idx files (prop never downloads them)",
            )
        arrays[name] = _read_idx(path)
    x_tr = (arrays["train_x"].reshape(len(arrays["train_x"]), -1) / 255.0).astype(np.float32)
    x_te = (arrays["test_x"].reshape(len(arrays["test_x"]), -1) / 255.0).astype(np.float32)
    y_tr, y_te = arrays["train_y"].astype(np.int64), arrays["test_y"].astype(np.int64)
    rng = np.random.default_rng(seed)
    tr, te = rng.permutation(len(x_tr)), rng.permutation(len(x_te))
    n_base, n_user, n_test = MNIST_SIZES
    return {
        "base": (x_tr[tr[:n_base]], y_tr[tr[:n_base]]),
        "user": (x_tr[tr[n_base : n_base + n_user]], y_tr[tr[n_base : n_base + n_user]]),
        "test": (x_te[te[:n_test]], y_te[te[:n_test]]),
    }


def splits(seed: int, mnist: Path | None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return load_mnist(mnist, seed) if mnist is not None else digits_task.load_splits(seed)


def _train_wide(x: np.ndarray, y: np.ndarray, steps: int, seed: int) -> torch.nn.Sequential:
    """digits_task's recipe (Adam, cross-entropy, seeded batches) for any input width (MNIST: 784)."""
    torch.manual_seed(seed)
    h = 128
    model = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], h), torch.nn.ReLU(), torch.nn.Linear(h, h), torch.nn.ReLU(),
        torch.nn.Linear(h, digits_task.N_CLASSES),
    )  # fmt: skip
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(0, len(xt), (128,), generator=gen)
        loss = torch.nn.functional.cross_entropy(model(xt[idx]), yt[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return model.eval()


def write_base(x: np.ndarray, y: np.ndarray, work: Path, seed: int, steps: int):
    if x.shape[1] == 64:
        model = digits_task.train_base(x, y, steps=steps, seed=seed)
    else:
        model = _train_wide(x, y, steps, seed)
    work.mkdir(parents=True, exist_ok=True)
    path = work / "base.safetensors"
    state = {digits_task.PREFIX + k: v.contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(path), metadata={"activation": "relu"})
    return model.eval(), path


def make_task(seed: int, work: Path, quick: bool, mnist: Path | None) -> common.TaskData:
    sp = splits(seed, mnist)
    (xb, yb), (xu, yu), (xt, yt) = sp["base"], sp["user"], sp["test"]
    steps = 40 if quick else (600 if mnist is None else 1500)  # quick: a smoke run of the pipeline
    model, path = write_base(xb, yb, work, seed, steps)
    shift = lambda y: ((y + OFFSET) % 10).astype(np.int64)  # noqa: E731
    return common.TaskData(
        task="classification",
        base=model,
        base_path=path,
        user_x=xu,
        user_y=shift(yu),
        general_x=xb,
        test_x=xt,
        test_y=yt,
        test_y_personal=shift(yt),
    )


def run(out: Path, quick: bool, seeds: int | None, mnist: Path | None = None, log=print) -> list[dict]:
    budget = common.Budget(prop_steps=2000, baseline_steps=2600)
    if quick:
        budget = common.Budget(prop_steps=40, baseline_steps=40, random_keys=8, hamming_keys=16,
                               t2_restarts=2, t2_steps=10, t2_samples=64)  # fmt: skip
    n_seeds = seeds or (2 if quick else 5)
    per_seed, params = [], {}
    for seed in range(n_seeds):
        work = out / "work" / f"digits-{seed}"
        td = make_task(seed, work, quick, mnist)
        enc = MNIST_ENCODER if mnist is not None else common.encoder_width(td, TOTAL_PARAMS)
        r = common.run_seed(td, seed, work, budget, enc, log=log)
        params = r["_params"]
        per_seed.append(r)
    src = f"MNIST from {mnist}" if mnist is not None else "scikit-learn digits (8x8)"
    return [
        {
            "name": "digits" if mnist is None else "mnist",
            "title": f"Image classification, {src}, label (l + {OFFSET}) mod 10 (key 128 bits)",
            "objective": "classification rate",
            "higher_is_better": True,
            "row_labels": {
                "general": "general (rate on true labels)",
                "personal": "personalized (rate on offset labels)",
                "leakage": "leakage (shared metric)",
            },
            **common.seed_fields(per_seed, params),
            "notes": [
                "PRoP personalizes a pretrained MLP classifier; baselines are trained from scratch on the "
                f"same data ({budget.baseline_steps} steps), fallback targets = the base's outputs.",
                "Parameters: " + ", ".join(f"{m} {n}" for m, n in params.items()),
            ],
        }
    ]
