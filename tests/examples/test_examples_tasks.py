"""The example task generators: files, shapes, dtypes, determinism, expert correctness."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open

# `examples` is a repo folder, not an installed package: make it importable under plain `pytest`.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from examples import digits_task, il_task  # noqa: E402

IL_SMALL = dict(base_samples=2000, user_samples=300, base_steps=30)  # files and determinism, not a fit


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    # Tiny models gain nothing from intra-op threads, and with other jobs on the 2 cores
    # torch's 2 OpenMP threads stall on each other (measured: 2.6 s -> 76 s).
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def il_dirs(tmp_path_factory):
    a, b = tmp_path_factory.mktemp("il_a"), tmp_path_factory.mktemp("il_b")
    return tuple(il_task.write_example(d, seed=3, **IL_SMALL) for d in (a, b))


@pytest.fixture(scope="module")
def digits_dirs(tmp_path_factory):
    a, b = tmp_path_factory.mktemp("dg_a"), tmp_path_factory.mktemp("dg_b")
    return tuple(digits_task.write_example(d, seed=1) for d in (a, b))


def _same_bytes(p, q):
    return set(p) == set(q) and all(p[k].read_bytes() == q[k].read_bytes() for k in p)


def test_candidates_fixed():
    c = il_task.candidates()
    assert c.shape == (1000, 2) and c.dtype == np.float32
    assert np.all(np.abs(c) <= 1) and np.array_equal(c, il_task.candidates())
    assert il_task.candidates(dim=3).shape == (1000, 3)


def test_expert_hand_made():
    # Robot at the origin, goal far right: best candidate is near (+1, 0).
    x = np.array([[0, 0, 9, 0], [5, 5, -5, 5], [1, 1, 1.1, 0.9]], np.float32)
    a = il_task.expert_actions(x)
    assert a.dtype == np.float32 and a.shape == (3, 2)
    assert a[0, 0] > 0.95 and abs(a[0, 1]) < 0.5  # x dominates the distance
    assert a[1, 0] < -0.95 and abs(a[1, 1]) < 0.5
    assert np.abs(a[2] - [0.1, -0.1]).max() < 0.15  # goal within reach: land almost on it
    np.testing.assert_array_equal(il_task.personal_actions(x), -a)


def test_expert_matches_brute_force_and_chunks():
    x = il_task.make_states(5000, seed=7)  # > one chunk
    cand = il_task.candidates()
    a = il_task.expert_actions(x)
    sub = x[::97]
    dist = np.linalg.norm(sub[:, None, :2] + cand[None] - sub[:, None, 2:], axis=2)
    np.testing.assert_array_equal(a[::97], cand[dist.argmin(axis=1)])


def test_il_files(il_dirs):
    paths, _ = il_dirs
    assert set(paths) == {"base", "mine", "general", "test"}
    mine, general, test = (np.load(paths[k]) for k in ("mine", "general", "test"))
    assert mine["x"].shape == (300, 4) and mine["y"].shape == (300, 2)
    assert mine["x"].dtype == mine["y"].dtype == np.float32
    np.testing.assert_array_equal(mine["y"], il_task.personal_actions(mine["x"]))
    assert set(general.files) == {"x"} and general["x"].shape == (2000, 4)
    assert test["x"].shape == (2000, 4) and test["y"].dtype == np.float32
    np.testing.assert_array_equal(test["y_personal"], -test["y"])
    assert np.abs(test["x"]).max() <= 10
    # Different derived seeds: no file reuses another's states.
    assert not np.array_equal(mine["x"], test["x"][:300])
    with safe_open(str(paths["base"]), "pt") as f:
        assert f.metadata() == {"activation": "relu"}
        assert f.get_tensor("0.weight").shape == (192, 4)
        assert f.get_tensor("4.weight").shape == (2, 192)


def test_il_deterministic(il_dirs):
    assert _same_bytes(*il_dirs)


def test_il_train_base_learns():
    x = il_task.make_states(2000, seed=11)
    y = il_task.expert_actions(x)
    model = il_task.train_base(x, y, hidden=64, steps=300, seed=0)
    base = float(np.mean(y**2))  # predicting zeros
    assert float(np.mean((il_task.predict(model, x) - y) ** 2)) < 0.5 * base


def test_digits_split():
    s = digits_task.load_splits(0)
    sizes = {k: len(v[0]) for k, v in s.items()}
    assert sum(sizes.values()) == 1797 and sizes["base"] == 1078 and sizes["user"] == 359
    assert all(v[0].min() >= 0 and v[0].max() <= 1 for v in s.values())


def test_digits_files(digits_dirs):
    paths, _ = digits_dirs
    mine, general, test = (np.load(paths[k]) for k in ("mine", "general", "test"))
    assert mine["x"].shape == (359, 64) and mine["x"].dtype == np.float32
    assert mine["y"].dtype == np.int64 and mine["y"].min() >= 0 and mine["y"].max() <= 9
    assert set(general.files) == {"x"} and general["x"].shape == (1078, 64)
    assert test["y"].dtype == test["y_personal"].dtype == np.int64
    np.testing.assert_array_equal(test["y_personal"], (test["y"] + digits_task.OFFSET) % 10)
    with safe_open(str(paths["base"]), "pt") as f:
        assert all(k.startswith("net.") for k in f.keys())
        assert f.metadata() == {"activation": "relu"}
    model = digits_task.load_base(paths["base"])
    assert digits_task.accuracy(model, test["x"], test["y"]) >= 0.95


def test_digits_deterministic(digits_dirs):
    assert _same_bytes(*digits_dirs)
