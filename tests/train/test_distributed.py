"""Data parallel personalize under `accelerate launch` (prop_cli.train.distributed).

Tolerance: the weights of a 2-process run and a 1-process run with the same seed and step differ by at
most 1e-5 (measured 1.2e-7 after 200 steps): the processes sum the same gradient in another order.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from prop_cli.config import PersonalizeConfig
from prop_cli.errors import PropError
from prop_cli.train.distributed import Ranks
from prop_cli.train.objective import Batch, prop_loss, prop_loss_share
from tests.conftest import write_keys, write_user_data

TOLERANCE = 1e-5


def _batch(
    rng: np.random.Generator, task: str = "regression", code_rows: int = 0, far_rows: int = 0
) -> tuple[torch.Tensor, Batch]:
    u, keyed, null = 6, 7 + code_rows + far_rows, 5
    n = u + keyed + null
    out = torch.from_numpy(rng.normal(size=(n, 3)).astype(np.float32)).requires_grad_(True)
    batch = Batch(
        x=torch.zeros(n, 1), sample_index=torch.arange(n), key_index=torch.zeros(n, dtype=torch.long),
        codes=torch.zeros(1, 4), user_rows=u, null_rows=null,
        user_targets=torch.from_numpy(rng.normal(size=(u, 3)).astype(np.float32)),
        fallback_targets=torch.from_numpy(rng.normal(size=(n - u, 3)).astype(np.float32)),
        code_rows=code_rows, far_rows=far_rows,
    )  # fmt: skip
    return out, batch


# code_rows: --harden's code-space negatives, far_rows: the far (and antipode) codes; a term each
@pytest.mark.parametrize(("code_rows", "far_rows"), [(0, 0), (4, 0), (0, 3), (4, 3)])
@pytest.mark.parametrize("world", [2, 3, 5])
def test_the_processes_shares_add_up_to_the_objective_and_its_gradient(world, code_rows, far_rows):
    out, batch = _batch(np.random.default_rng(world), code_rows=code_rows, far_rows=far_rows)
    whole, losses = prop_loss(out, batch, "regression", 2.0, 3.0)
    (g_whole,) = torch.autograd.grad(whole, out)
    total, grad = 0.0, torch.zeros_like(out)
    parts = torch.zeros(3)
    for rank in range(world):
        rows = Ranks(rank, world).share(len(batch.key_index))
        loss, p = prop_loss_share(out[rows], batch, rows, "regression", 2.0, 3.0)
        (g,) = torch.autograd.grad(loss, out)
        total, grad, parts = total + loss.item(), grad + g, parts + p
    assert total == pytest.approx(whole.item(), rel=1e-6, abs=1e-6)  # float32 sums in another order
    assert torch.allclose(grad, g_whole, atol=1e-7)
    assert parts.tolist() == pytest.approx([losses["personal"], losses["fallback"], losses["null"]], abs=1e-6)


def test_fewer_rows_per_step_than_processes_is_refused_before_any_work(tmp_path):
    from prop_adapters import load_checkpoint
    from prop_cli.datasources import load_data
    from prop_cli.train import User, personalize

    rng = np.random.default_rng(0)
    write_user_data(tmp_path, 40, rng)
    loaded = load_checkpoint(tmp_path / "model.safetensors")
    user = User(load_data(tmp_path / "mine.npz"), rng.integers(0, 2, 128).astype(np.uint8))
    cfg = PersonalizeConfig.of(steps=1, seal=True, user_rows=2)  # a sealed payload's step: user rows only
    with pytest.raises(PropError, match="--user-rows 2: fewer rows per step than the 3 processes"):
        personalize(loaded, [user], cfg, ranks=Ranks(0, 3))


@pytest.mark.parametrize("flag", ["ACCELERATE_USE_FSDP", "ACCELERATE_USE_DEEPSPEED"])
def test_sharding_launch_options_are_refused_not_ignored(monkeypatch, flag):
    from prop_cli.train.distributed import ranks_from_env

    monkeypatch.setenv(flag, "true")
    with pytest.raises(PropError, match="prop trains data parallel, every process holding the whole model"):
        ranks_from_env("cpu")


@pytest.mark.parametrize("seal", [False, True], ids=["unsealed", "sealed"])
def test_two_processes_under_accelerate_train_what_one_process_trains(tmp_path, seal):
    pytest.importorskip("accelerate")
    from benchmarks.bench_dist_policies import launch, trained_weights

    rng = np.random.default_rng(0)
    write_user_data(tmp_path, 120, rng)
    write_keys(tmp_path, ("k.bin",), rng)
    common = ["personalize", tmp_path / "model.safetensors", "--data", tmp_path / "mine.npz", "--key-file",
              tmp_path / "k.bin", "--steps", "100", "--json", *(["--seal"] if seal else [])]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "prop_cli.cli.main", *map(str, common), "--out", str(tmp_path / "one")]
    one = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert one.returncode == 0, one.stderr
    # Several CPU processes: --multi_gpu (prop asks Accelerate for gloo on the CPU); --cpu alone starts one.
    two = subprocess.run([*launch(2), *map(str, common), "--out", str(tmp_path / "two")],
                         capture_output=True, text=True, env=env)  # fmt: skip
    assert two.returncode == 0, two.stderr[-3000:]
    report = json.loads(two.stdout)  # one report: only the first process prints and writes
    assert report["processes"] == 2  # counted by a collective both processes joined
    assert json.loads(one.stdout)["processes"] == 1
    # Unsealed: the base and the key encoder; sealed: the user's payload, opened with the key.
    a, b = (trained_weights(tmp_path / d, tmp_path / "k.bin") for d in ("one", "two"))
    assert a.keys() == b.keys() and a
    assert max(float(np.abs(a[k] - b[k]).max()) for k in a) <= TOLERANCE
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["k.bin", "mine.npz", "model.safetensors", "one", "two"]
