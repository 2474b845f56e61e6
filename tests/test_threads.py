"""The thread policy: one thread for small models, the idle cores for large ones, the user's choice first."""

from __future__ import annotations

import pytest
import torch

from prop_cli import threads
from prop_cli.errors import PropError


@pytest.fixture
def restore():
    old = torch.get_num_threads()
    yield
    torch.set_num_threads(old)


def test_small_models_get_one_thread_large_ones_the_idle_cores():
    assert threads.choose(38_000, free=2) == 1
    assert threads.choose(threads.PARALLEL_PARAMS - 1, free=4) == 1
    assert threads.choose(threads.PARALLEL_PARAMS, free=2) == 2
    assert threads.choose(50_000_000, free=1) == 1  # the other core is busy: no stalled second thread
    assert 1 <= threads.free_cores() <= threads.cores()


def test_explicit_count_wins_then_omp_num_threads_then_the_rule(monkeypatch, restore):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    torch.set_num_threads(1)
    assert threads.configure(50_000_000, 2) == 2 and torch.get_num_threads() == 2
    torch.set_num_threads(1)
    assert threads.configure(50_000_000) == 1  # the user's OMP_NUM_THREADS: left as torch read it
    monkeypatch.delenv("OMP_NUM_THREADS")
    torch.set_num_threads(2)
    assert threads.configure(38_000) == 1 and torch.get_num_threads() == 1
    assert threads.configure(38_000, 0) == 1  # 0 = choose


def test_negative_count_is_refused():
    with pytest.raises(PropError, match=r"--threads -1 is invalid"):
        threads.check(-1)


def test_cli_threads_flag(cli, tmp_path):
    r = cli("run", tmp_path / "missing.prop", "--input", tmp_path / "x.npy", "--output", tmp_path / "y.npy",
            "--threads", "-2")  # fmt: skip
    assert r.code == 2 and "--threads -2 is invalid" in r.err and not (tmp_path / "y.npy").exists()
