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


def test_a_key_enrolled_in_nothing_is_labelled_for_what_ran(pendulum, cli):
    """A wrong key is refused before any rollout (issue 31); with --allow-unenrolled-key it runs the
    bundle's base: its row says so (not user_key), and it is the no-key row."""
    (pendulum / "wrong.bin").write_bytes(bytes(16))
    r = cli("eval", "b", "--env", "Pendulum-v1", "--key-file", "wrong.bin", *QUICK, "--json")
    assert r.code == 2 and not r.out and "enrolled in nothing" in r.err, r.err
    assert "--allow-unenrolled-key" in r.err and "eval:" not in r.err  # no condition was rolled out
    allow = "--allow-unenrolled-key"
    r = cli("eval", "b", "--env", "Pendulum-v1", "--key-file", "wrong.bin", *QUICK, "--json", allow)
    assert r.code == 0, r.err
    cond = json.loads(r.out)["conditions"]
    assert "user_key" not in cond and cond["key_not_enrolled"] == cond["no_key"]
    r = cli("eval", "b", "--env", "Pendulum-v1", "--key-file", "wrong.bin", *QUICK, allow)
    assert r.code == 0 and "key_not_enrolled" in r.out and "user_key" not in r.out


# The user's own environment for --env FILE.py:factory and module:factory (no gymnasium registration).
TINY_ENV = '''
import gymnasium as gym
import numpy as np


class Tiny(gym.Env):
    """3 observations, 1 action, 4 steps an episode."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode=None):
        self.observation_space = gym.spaces.Box(-1, 1, (3,), np.float32)
        self.action_space = gym.spaces.Box(-2, 2, (1,), np.float32)
        self.render_mode = render_mode

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.obs = 0, self.np_random.uniform(-1, 1, 3).astype(np.float32)
        return self.obs, {}

    def step(self, action):
        self.t += 1
        reward = -abs(float(action[0]) - float(self.obs[0]))
        self.obs = self.np_random.uniform(-1, 1, 3).astype(np.float32)
        return self.obs, reward, False, self.t >= 4, {"is_success": reward > -0.5}

    def render(self):
        return np.full((8, 8, 3), 10 * self.t, np.uint8)


def make(render_mode=None):
    return Tiny(render_mode)


def make_plain():
    return Tiny()


def broken():
    raise ValueError("no simulator here")


def not_env():
    return {"reset": 1}


if "TinyRegistered-v0" not in gym.registry:
    gym.register(id="TinyRegistered-v0", entry_point=Tiny, max_episode_steps=3)
'''


@pytest.fixture
def tiny_env(pendulum, monkeypatch):
    """The environment as a file under the bundle's folder and as a module elsewhere on sys.path."""
    (pendulum / "envs").mkdir()
    (pendulum / "envs" / "tiny.py").write_text(TINY_ENV)
    (pendulum / "site").mkdir()
    (pendulum / "site" / "tiny_env_mod.py").write_text(TINY_ENV)
    monkeypatch.syspath_prepend(str(pendulum / "site"))
    return pendulum


def test_eval_env_as_the_users_factory_from_a_file_or_a_module(tiny_env, cli):
    args = ["--key-file", "k.bin", *QUICK, "--json"]
    r = cli("eval", "b", "--env", "envs/tiny.py:make", *args)
    assert r.code == 0, r.err
    by_file = json.loads(r.out)
    cond = by_file["conditions"]
    assert set(cond) == {"no_key", "user_key", "random_keys", "neighbour1_keys"}
    assert cond["no_key"]["steps"]["mean"] == 4 and "success" in cond["no_key"]  # the tiny env, not Pendulum
    r = cli("eval", "b", "--env", "tiny_env_mod:make", *args)
    assert r.code == 0, r.err
    by_module = json.loads(r.out)
    assert by_module["env"] == "tiny_env_mod:make" and by_module["conditions"] == cond
    # package:Id still means the id the module registers (with its time limit), not an attribute.
    r = cli("eval", "b", "--env", "tiny_env_mod:TinyRegistered-v0", *args)
    assert r.code == 0, r.err
    assert json.loads(r.out)["conditions"]["no_key"]["steps"]["mean"] == 3


@pytest.mark.parametrize(
    "env, message",
    [
        ("no_such_env_module:make", "--env 'no_such_env_module:make': cannot import 'no_such_env_module'"),
        ("envs/none.py:make", "envs/none.py does not exist"),
        ("envs/tiny.py:nope", "envs/tiny.py has no attribute 'nope'"),
        ("envs/tiny.py:broken", "broken() raised ValueError: no simulator here"),
        ("envs/tiny.py:not_env", "not_env() returned a dict, not an environment (no reset/step)"),
        ("envs/tiny.py", "names a file but no factory"),
    ],
)
def test_a_bad_env_factory_is_one_line_before_any_rollout(tiny_env, cli, env, message):
    r = cli("eval", "b", "--env", env, *QUICK)
    assert r.code == 2 and message in r.err, r.err
    assert len(r.err.strip().splitlines()) == 1 and "eval:" not in r.err


@pytest.fixture
def fake_writer(monkeypatch):
    """imageio's mp4 writer, simulated (the test environment has no ffmpeg): it records the frames."""
    import sys
    import types

    written: dict[str, int] = {}
    v2 = types.ModuleType("imageio.v2")
    v2.mimsave = lambda path, frames, fps, macro_block_size: written.setdefault(path.name, len(frames)) and (
        path.write_bytes(b"mp4")
    )
    imageio = types.ModuleType("imageio")
    imageio.v2 = v2
    for name, module in (("imageio", imageio), ("imageio.v2", v2), ("imageio_ffmpeg", types.ModuleType("f"))):
        monkeypatch.setitem(sys.modules, name, module)
    return written


def test_video_of_a_factory_env_passes_render_mode(tiny_env, cli, fake_writer):
    r = cli("eval", "b", "--env", "envs/tiny.py:make", *QUICK, "--video", "v", "--json")
    assert r.code == 0, r.err
    assert fake_writer == {"no_key.mp4": 5, "random_keys.mp4": 5}  # reset + 4 steps
    r = cli("eval", "b", "--env", "envs/tiny.py:make_plain", *QUICK, "--video", "v2")
    assert r.code == 2 and "make_plain takes no render_mode" in r.err and "eval:" not in r.err, r.err


def test_video_without_pygame_names_it_before_any_rollout(pendulum, cli, fake_writer, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pygame", None)  # `import pygame` fails, as where it is not installed
    r = cli("eval", "b", "--env", "Pendulum-v1", *QUICK, "--video", "v")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1, r.err
    assert "--video: Pendulum-v1 renders with pygame, which is not installed; pip install pygame" in r.err
    assert "eval:" not in r.err and "Traceback" not in r.err and not (pendulum / "v").exists()


def test_arch_given_again_builds_the_bundle_and_the_original(tmp_path, cli, monkeypatch):
    """From another folder, --arch names the user's module for the bundle and for --original alike, with
    no --trust-remote-code (the recorded arch is never imported)."""
    import torch
    from safetensors.torch import save_file

    (tmp_path / "pend_net.py").write_text(
        "from torch import nn\n\n\ndef build():\n"
        "    return nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))\n"
    )
    monkeypatch.chdir(tmp_path)
    torch.manual_seed(0)
    from torch import nn

    save_file(nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1)).state_dict(), "pi.safetensors")
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (100, 3)).astype(np.float32)
    np.savez("mine.npz", x=x, y=np.clip(-x[:, :1], -1, 1))
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    r = cli("personalize", "pi.safetensors", "--arch", "pend_net.py:build", "--data", "mine.npz",
            "--key-file", "k.bin", "--out", "b", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    args = ["eval", "../b", "--env", "Pendulum-v1", *QUICK, "--original", "../pi.safetensors", "--json"]
    r = cli(*args, "--trust-remote-code")
    assert r.code == 2 and "pass --arch naming the file's path from here" in r.err, r.err
    r = cli(*args, "--arch", "../pend_net.py:build")
    assert r.code == 0, r.err
    assert json.loads(r.out)["conditions"]["original"]["episodes"] == 2


def test_a_video_folder_that_cannot_be_made_fails_before_any_rollout(tmp_path, monkeypatch):
    """Issue 28: outputs are checked before the work; the videos are written after every rollout."""
    import tempfile

    from prop_cli.errors import PropError
    from prop_cli.run.rollout import check_video

    pytest.importorskip("imageio_ffmpeg")

    def refuse(*a, **kw):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    with pytest.raises(PropError, match=r"cannot write video folder .*v: no file can be created .*--video"):
        check_video(tmp_path / "v")
    with pytest.raises(PropError, match="does not exist"):
        check_video(tmp_path / "missing" / "v")


def test_eval_names_each_wrong_key_its_worst_and_reruns_one(pendulum, cli):
    """Issue 32: per-key figures, the worst key, and one key re-run alone gives its figure again."""
    args = ["eval", "b", "--env", "Pendulum-v1", "--key-file", "k.bin", "--episodes", "4", "--max-steps",
            "5", "--random-keys", "3", "--neighbours", "2", "--episodes-per-key", "1"]  # fmt: skip
    cond = json.loads(cli(*args, "--json").out)["conditions"]
    user = np.frombuffer((pendulum / "k.bin").read_bytes(), np.uint8)
    user_bits = "".join(str(b) for b in np.unpackbits(user))
    for group, n in (("random_keys", 3), ("neighbour1_keys", 2)):
        rows = cond[group]["per_key"]
        assert len(rows) == cond[group]["keys"] == n
        assert np.mean([r["return"]["mean"] for r in rows]) == pytest.approx(cond[group]["return"]["mean"])
        worst = cond[group]["worst_key"]
        assert worst["by"] == "return" and worst["key"] == rows[worst["index"]]["key"]
        assert worst["return"]["mean"] == min(r["return"]["mean"] for r in rows)
    for row in cond["random_keys"]["per_key"]:
        assert set(row["key"]) == {"bits"} and len(row["key"]["bits"]) == len(user_bits) != row["key"]["bits"]
    # A neighbour is named by its flipped bit only: its bits with the index would give the key away.
    assert all(set(r["key"]) == {"flipped_bit"} for r in cond["neighbour1_keys"]["per_key"])
    assert user_bits not in json.dumps(cond)
    for group, flag, value in (("random_keys", "--key-bits", "bits"), ("neighbour1_keys", "--flip-bit",
                                                                       "flipped_bit")):  # fmt: skip
        w = cond[group]["worst_key"]
        rerun = ["--seed", str(w["seeds"][0]), "--episodes", str(len(w["seeds"])), "--random-keys", "0",
                 "--neighbours", "0", flag, str(w["key"][value])]  # fmt: skip
        r = cli("eval", "b", "--env", "Pendulum-v1", "--key-file", "k.bin", "--max-steps", "5", *rerun,
                "--json")  # fmt: skip
        assert r.code == 0, r.err
        row = json.loads(r.out)["conditions"]["key_bits" if value == "bits" else "flipped_bit"]
        assert row["key"] == w["key"] and row["return"] == w["return"]
    table = cli(*args)
    assert table.code == 0 and "worst key" in table.out and "(key " in table.out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--key-bits", "0101"], "--key-bits is not 128 characters"),
        (["--key-bits", "2" * 128], "--key-bits is not 128 characters"),
        (["--flip-bit", "128", "--key-file", "k.bin"], "--flip-bit 128 is outside 0..127"),
        (["--flip-bit", "3"], "--flip-bit needs your key"),
        (["--flip-bit", "3", "--key-bits", "0" * 128, "--key-file", "k.bin"], "one key at a time"),
    ],
)
def test_a_bad_key_to_rerun_is_one_line(pendulum, cli, extra, message):
    (pendulum / "k.bin").chmod(0o600)  # no permission warning: the error is stderr's one line
    r = cli("eval", "b", "--env", "Pendulum-v1", *extra)
    assert r.code == 2 and message in r.err and len(r.err.strip().splitlines()) == 1, r.err


def _scored_outcomes(monkeypatch, worse_key) -> None:
    """Real rollouts whose success is set by who drove: no key and the user key always succeed; random
    key j (in the order eval runs them) fails when ``worse_key(j)`` and ties otherwise."""
    from prop_cli.run import rollout

    made = []
    real_controller, real_episodes = rollout.controller, rollout._episodes

    def controller(*args, method=False, **kwargs):
        ctl = real_controller(*args, method=method, **kwargs)
        ctl._wrong_key = len(made) if method else None
        made.append(method)
        return ctl

    def episodes(env, ctl, seeds, *args, **kwargs):
        results = real_episodes(env, ctl, seeds, *args, **kwargs)
        j = getattr(ctl, "_wrong_key", None)
        wrong = sum(made[: j + 1]) - 1 if j is not None else None  # the j-th random key
        for r in results:
            r["success"] = 0.0 if wrong is not None and worse_key(wrong) else 1.0
        return results

    monkeypatch.setattr(rollout, "controller", controller)
    monkeypatch.setattr(rollout, "_episodes", episodes)


DRIFT = ["--episodes", "6", "--max-steps", "2", "--random-keys", "6", "--neighbours", "0",
         "--episodes-per-key", "1"]  # fmt: skip


def test_eval_warns_when_every_wrong_key_does_worse(pendulum, cli, monkeypatch):
    _scored_outcomes(monkeypatch, lambda j: True)
    r = cli("eval", "b", "--env", "Pendulum-v1", *DRIFT, "--json")
    assert r.code == 0, r.err
    d = json.loads(r.out)["conditions"]["random_keys"]["drift"]
    assert d["against"] == "no_key" and d["by"] == "success"
    assert (d["worse"], d["better"], d["ties"]) == (6, 0, 0)
    assert d["p"] == pytest.approx(2 / 64) and d["systematic"] and d["warn"]
    assert d["episodes"] == {"lost": 6, "gained": 0, "p": pytest.approx(2 / 64)}
    lines = [x for x in r.err.splitlines() if x.startswith("prop: warning:")]
    assert len(lines) == 1 and "6 of 6 random keys do worse than no key on success" in lines[0]
    assert "p = 0.031" in lines[0] and "--delta-pull" in lines[0]
    table = cli("eval", "b", "--env", "Pendulum-v1", *DRIFT)  # the table prints the same line
    assert table.code == 0 and lines[0] in table.err


def test_eval_is_quiet_when_the_wrong_keys_split(pendulum, cli, monkeypatch):
    _scored_outcomes(monkeypatch, lambda j: j % 3 == 0)  # 2 of 6 keys worse, 4 tie
    r = cli("eval", "b", "--env", "Pendulum-v1", *DRIFT, "--json")
    assert r.code == 0, r.err
    d = json.loads(r.out)["conditions"]["random_keys"]["drift"]
    assert (d["worse"], d["better"], d["ties"]) == (2, 0, 4)
    assert d["p"] == pytest.approx(0.5) and not d["systematic"] and not d["warn"]
    assert "warning" not in r.err
