"""`prop eval`: closed-loop rollouts per key condition, on a gymnasium classic-control task."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import FAST, make_mlp_checkpoint

pytest.importorskip("gymnasium")

METRIC = "def upright(traj):\n    return float(traj['observations'][-1][0])  # cos(theta) at the end\n"
QUICK = ["--episodes", "2", "--max-steps", "5", "--random-keys", "1", "--neighbours", "1",
         "--episodes-per-key", "1"]  # fmt: skip


@pytest.fixture
def pendulum(tmp_path, cli, monkeypatch):
    """An MLP bundle for Pendulum-v1 (3 observations, 1 action) and a metric module next to it."""
    rng = np.random.default_rng(0)
    make_mlp_checkpoint(tmp_path / "pi.safetensors", sizes=(3, 16, 16, 1))
    x = rng.uniform(-1, 1, (200, 3)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=np.clip(x[:, :1], -1, 1))
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    (tmp_path / "metrics_here.py").write_text(METRIC)
    monkeypatch.chdir(tmp_path)
    r = cli("personalize", "pi.safetensors", "--data", "mine.npz", "--key-file", "k.bin", "--out", "b", *FAST)
    assert r.code == 0, r.err
    return tmp_path


def test_eval_reports_every_condition_on_the_same_seeds(pendulum, cli):
    args = [
        "eval",
        "b",
        "--env",
        "Pendulum-v1",
        "--key-file",
        "k.bin",
        *QUICK,
        "--metric",
        "metrics_here:upright",
    ]
    r = cli(*args, "--json")
    assert r.code == 0, r.err
    report = json.loads(r.out)
    cond = report["conditions"]
    assert set(cond) == {"no_key", "user_key", "random_keys", "neighbour1_keys"}
    assert cond["no_key"]["episodes"] == 2 and cond["no_key"]["steps"]["mean"] == 5
    assert -1 <= cond["user_key"]["metric"]["mean"] <= 1
    assert json.loads(cli(*args, "--json").out) == report  # seeded: the same rollouts again
    no_key_only = json.loads(cli("eval", "b", "--env", "Pendulum-v1", *QUICK, "--json").out)["conditions"]
    assert set(no_key_only) == {"no_key", "random_keys"}  # neighbours need the user's key
    assert no_key_only["no_key"] == {k: v for k, v in cond["no_key"].items() if k != "metric"}


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--env", "NoSuchEnv-v0"], "gymnasium cannot make it"),
        (["--env", "Pendulum-v1", "--metric", "metrics_here:nope"], "--metric 'metrics_here:nope'"),
        (["--env", "Pendulum-v1", "--obs-map", "state"], "is not feature=key"),
        (["--env", "Pendulum-v1", "--episodes", "0"], "--episodes 0 is invalid"),
    ],
)
def test_eval_bad_input_is_one_line(pendulum, cli, extra, message):
    r = cli("eval", "b", *extra)
    assert r.code == 2 and message in r.err and len(r.err.strip().splitlines()) == 1, r.err


def test_original_is_the_control_for_array_bundles_on_the_same_seeds(pendulum, cli, tmp_path):
    r = cli("eval", "b", "--env", "Pendulum-v1", *QUICK, "--original", "pi.safetensors", "--json")
    assert r.code == 0, r.err
    cond = json.loads(r.out)["conditions"]
    assert {"original", "no_key", "random_keys"} <= set(cond) and cond["original"]["episodes"] == 2
    # Frozen base: the no-key bundle is the original bit for bit, so the paired rollouts are equal too.
    frozen = cli("personalize", "pi.safetensors", "--data", "mine.npz", "--key-file", "k.bin", "--out", "f",
                 *FAST, "--freeze-base")  # fmt: skip
    assert frozen.code == 0, frozen.err
    same = json.loads(cli("eval", "f", "--env", "Pendulum-v1", *QUICK, "--original", "pi.safetensors",
                          "--json").out)["conditions"]  # fmt: skip
    assert same["original"]["return"] == same["no_key"]["return"]
    make_mlp_checkpoint(tmp_path / "other.safetensors", sizes=(3, 8, 1))
    r = cli("eval", "b", "--env", "Pendulum-v1", *QUICK, "--original", tmp_path / "other.safetensors")
    assert r.code == 2 and "other.safetensors" in r.err and "match" in r.err
    assert len(r.err.strip().splitlines()) == 1 and "eval:" not in r.err  # before any rollout


def test_original_of_an_arch_bundle_needs_no_arch_again(tmp_path, cli, monkeypatch):
    import torch
    from safetensors.torch import save_file

    (tmp_path / "pend_model.py").write_text(
        "from torch import nn\n\n\ndef build():\n"
        "    return nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    from pend_model import build

    torch.manual_seed(0)
    save_file(build().state_dict(), str(tmp_path / "pi.safetensors"))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (100, 3)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=np.clip(-x[:, :1], -1, 1))
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    r = cli("personalize", "pi.safetensors", "--arch", "pend_model:build", "--data", "mine.npz", "--key-file",
            "k.bin", "--out", "b", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    r = cli("eval", "b", "--env", "Pendulum-v1", *QUICK, "--original", "pi.safetensors",
            "--trust-remote-code", "--json")  # fmt: skip
    assert r.code == 0, r.err
    assert json.loads(r.out)["conditions"]["original"]["episodes"] == 2


def test_a_video_folder_that_cannot_be_made_fails_before_any_rollout(tmp_path, monkeypatch):
    """Issue 28: outputs are checked before the work; the videos are written after every rollout."""
    import tempfile

    from prop_cli.deploy.rollout import check_video
    from prop_cli.errors import PropError

    pytest.importorskip("imageio_ffmpeg")

    def refuse(*a, **kw):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    with pytest.raises(PropError, match=r"cannot write video folder .*v: no file can be created .*--video"):
        check_video(tmp_path / "v")
    with pytest.raises(PropError, match="does not exist"):
        check_video(tmp_path / "missing" / "v")
