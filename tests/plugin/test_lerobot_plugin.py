"""The LeRobot policy plugin (plugins/lerobot_policy_prop): a prop bundle as ``--policy.type=prop`` in
LeRobot's own tools. ``lerobot-eval`` runs here as users run it (a subprocess, LeRobot's MetaWorld
environment, plugin discovery by distribution name), on MetaWorld episodes shortened to a few steps.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("lerobot")
pytest.importorskip("lerobot_policy_prop")
pytest.importorskip("metaworld")
pytestmark = pytest.mark.lerobot

from tests.plugin import tiny  # noqa: E402

BIN = Path(sys.executable).parent
STEPS = 12  # MetaWorld steps per episode in these runs (500 in LeRobot's environment)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("plugin")
    tiny.build(d)
    return d


def traces(key_file: Path) -> list[bytes]:
    """The forms the key's bytes could take in a file: raw, hex (both cases), base64."""
    raw = key_file.read_bytes()
    return [raw, raw.hex().encode(), raw.hex().upper().encode(), base64.b64encode(raw)]


def lerobot(tool: str, args: list[str], tmp: Path, **env) -> subprocess.CompletedProcess:
    environ = os.environ | tiny.short_episodes(tmp / "site", STEPS) | {"MUJOCO_GL": os.environ.get(
        "MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"} | env  # fmt: skip
    return subprocess.run([str(BIN / tool), *args], capture_output=True, text=True, env=environ, timeout=300)


def eval_args(bundle: Path, out: Path, *extra: str) -> list[str]:
    return [f"--policy.bundle={bundle}", "--policy.type=prop", "--policy.resize_images=true",
            "--env.type=metaworld", f"--env.task={tiny.TASK}", "--eval.n_episodes=1", "--eval.batch_size=1",
            f"--output_dir={out}", *extra]  # fmt: skip


def one_line_error(p: subprocess.CompletedProcess) -> str:
    assert p.returncode == 1, p.stderr[-2000:]
    assert "Traceback" not in p.stderr, p.stderr[-2000:]
    errors = [line for line in p.stderr.splitlines() if line.startswith("prop: error:")]
    assert len(errors) == 1, p.stderr[-2000:]
    return errors[0]


@pytest.mark.parametrize("name", ["unsealed", "sealed"])
def test_lerobot_eval_runs_the_bundle_with_the_users_key_and_writes_no_key(work, tmp_path, name):
    out = tmp_path / "eval"
    key = f"--policy.key_file={work / 'user.key'}"
    p = lerobot("lerobot-eval", eval_args(work / name, out, key), tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1
    written = [f for f in out.rglob("*") if f.is_file()]
    assert any(f.suffix == ".mp4" for f in written)  # LeRobot's own video of the episode
    for form in traces(work / "user.key"):
        assert form not in (p.stdout + p.stderr).encode()
        for f in written:
            assert form not in f.read_bytes(), f


def test_a_key_enrolled_in_nothing_is_refused_in_one_line_before_the_first_action(work, tmp_path):
    out = tmp_path / "eval"
    p = lerobot("lerobot-eval", eval_args(work / "sealed", out, f"--policy.key_file={work / 'other.key'}"),
                tmp_path)  # fmt: skip
    assert "enrolled in nothing" in one_line_error(p)
    assert not (out / "eval_info.json").exists() and "Running rollout" not in p.stderr


def test_lerobot_train_is_refused_in_one_line(work, tmp_path):
    args = [
        "--policy.type=prop",
        f"--policy.bundle={work / 'unsealed'}",
        "--dataset.repo_id=local/user",
        f"--dataset.root={work / 'user'}",
        f"--output_dir={tmp_path / 'train'}",
    ]
    p = lerobot("lerobot-train", args, tmp_path)
    assert "prop personalize" in one_line_error(p)


# In-process: LeRobot's factory, as lerobot-eval and lerobot-record call it.


def make(work: Path, bundle: str | Path = "unsealed", *, ds: bool = True, **options):
    """The policy and processors LeRobot's factory builds for ``--policy.type=prop``: from the dataset's
    features (lerobot-record) or MetaWorld's (lerobot-eval)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.envs.configs import MetaworldEnv
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot_policy_prop import PropConfig

    cfg = PropConfig(bundle=str(work / bundle), **options)
    where = {"ds_meta": LeRobotDatasetMetadata("local/user", root=work / "user")} if ds else {
        "env_cfg": MetaworldEnv(task=tiny.TASK)}  # fmt: skip
    policy = make_policy(cfg, **where).eval()
    pre, post = make_pre_post_processors(cfg)
    return policy, pre, post


def original(work: Path):
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    policy = ACTPolicy.from_pretrained(str(work / "act")).eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(work / "act"))
    return policy, pre, post


def actions(parts, frames: list[dict]) -> torch.Tensor:
    policy, pre, post = parts
    policy.reset()
    with torch.inference_mode():
        return torch.cat([post(policy.select_action(pre(dict(f)))) for f in frames])


@pytest.fixture(scope="module")
def frames(work) -> list[dict]:
    """24 frames of the user's data as LeRobot's loop hands them to the preprocessor (batch of one)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/user", root=work / "user")
    return [{k: ds[i][k][None] for k in (tiny.STATE, tiny.IMAGE)} | {"task": [ds[i]["task"]]}
            for i in range(24)]  # fmt: skip


def test_no_key_acts_as_the_original_bit_for_bit_and_the_users_key_does_not(work, frames):
    base = actions(original(work), frames)
    assert torch.equal(actions(make(work, "sealed"), frames), base)  # a sealed bundle's base: the original
    keyed = actions(make(work, "sealed", key_file=str(work / "user.key")), frames)
    assert keyed.shape == base.shape and (keyed - base).abs().max() > 1e-3


def test_an_unsealed_bundle_runs_as_prop_runs_it(work, frames):
    """An unsealed bundle's base was trained too (fidelity, not identity): no key runs that base, and each
    key what prop's own runtime gives it, bit for bit: the plugin adds nothing to either."""
    from prop_cli.bundle import load_bundle
    from prop_cli.run import KeyedPolicy

    bundle = load_bundle(work / "unsealed")
    for key_file in (None, work / "user.key"):
        from prop_cli.core.key_files import read_key_file

        key = None if key_file is None else read_key_file(key_file)
        prop = KeyedPolicy(bundle, key).controller
        expected = torch.cat([torch.as_tensor(prop.select_action({k: v for k, v in f.items()}))[None]
                              for f in frames])  # fmt: skip
        options = {} if key_file is None else {"key_file": str(key_file)}
        assert torch.equal(actions(make(work, "unsealed", **options), frames), expected.reshape(-1, 4))


def test_an_allowed_unenrolled_key_runs_the_base_with_a_warning(work, frames):
    from prop_cli.run import WrongKeyWarning

    with pytest.warns(WrongKeyWarning, match="enrolled in nothing"):
        parts = make(work, "sealed", key_file=str(work / "other.key"), allow_unenrolled_key=True)
    assert torch.equal(actions(parts, frames), actions(original(work), frames))


def refused(capsys, build) -> str:
    with pytest.raises(SystemExit) as e:
        build()
    assert e.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("prop: error: "), err
    return err[0]


def test_features_the_environment_does_not_match_are_one_line_naming_both_sides(work, capsys):
    line = refused(capsys, lambda: make(work, ds=False))
    assert "'observation.image' is (3, 480, 480) in the environment and (3, 32, 32) in the bundle" in line
    assert "--policy.resize_images=true" in line
    policy, _, _ = make(work, ds=False, resize_images=True)  # MetaWorld's 480x480 frames, resized
    assert policy.resize == {tiny.IMAGE: (3, tiny.SIZE, tiny.SIZE)}


def test_a_changed_bundle_is_refused_in_one_line(work, tmp_path, capsys):
    copy = tmp_path / "b"
    shutil.copytree(work / "sealed", copy)
    stats = next(copy.rglob("*.safetensors"))
    data = bytearray(stats.read_bytes())
    data[-1] ^= 1
    stats.write_bytes(bytes(data))
    line = refused(capsys, lambda: make(work, copy, key_file=str(work / "user.key")))
    assert str(copy) in line


def test_options_that_cannot_work_are_one_line(work, capsys, monkeypatch):
    from lerobot_policy_prop import PropConfig

    assert "--policy.bundle" in refused(capsys, lambda: PropConfig())
    both = refused(capsys, lambda: PropConfig(bundle="b", key_file="k", passphrase=True))
    assert "both given" in both
    monkeypatch.delenv("PROP_PASSPHRASE", raising=False)
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    assert "PROP_PASSPHRASE" in refused(capsys, lambda: make(work, passphrase=True))


def test_saving_or_training_the_policy_is_refused(work, tmp_path, capsys):
    policy, _, _ = make(work, key_file=str(work / "user.key"))
    refused(capsys, lambda: policy.save_pretrained(tmp_path / "out"))
    assert not any((tmp_path / "out").rglob("*.safetensors"))
    assert "prop personalize" in refused(capsys, lambda: policy.forward({}))


# --policy.path: the folder prop export --lerobot writes, for the tools that load only by path.


def export(work: Path, bundle: str, out: Path, *flags: str) -> Path:
    p = subprocess.run([str(BIN / "prop"), "export", str(work / bundle), "--lerobot", str(out), *flags],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert p.returncode == 0, p.stderr
    return out


def by_path(folder: Path, **options):
    """What lerobot-rollout does with --policy.path (rollout/context.py): the config from the folder, the
    policy by from_pretrained, the processors from the folder with its two overrides."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.rollout.context import _load_pretrained_policy

    cfg = PreTrainedConfig.from_pretrained(folder)
    for k, v in options.items():
        setattr(cfg, k, v)
    cfg.pretrained_path = folder
    policy = _load_pretrained_policy(cfg).eval()
    pre, post = make_pre_post_processors(
        cfg, pretrained_path=str(folder), preprocessor_overrides={
            "device_processor": {"device": "cpu"}, "rename_observations_processor": {"rename_map": {}}},
    )  # fmt: skip
    return policy, pre, post


def test_a_policy_folder_runs_as_lerobot_rollout_loads_it(work, frames, tmp_path):
    folder = export(work, "sealed", tmp_path / "policy")
    assert sorted(f.name for f in folder.iterdir()) == [
        "config.json", "policy_postprocessor.json", "policy_preprocessor.json"]  # fmt: skip
    assert not any(form in f.read_bytes() for f in folder.iterdir() for form in traces(work / "user.key"))
    key = str(work / "user.key")
    keyed = actions(make(work, "sealed", key_file=key), frames)
    assert torch.equal(actions(by_path(folder, key_file=key), frames), keyed)
    assert torch.equal(actions(by_path(folder), frames), actions(original(work), frames))


def test_lerobot_eval_runs_a_policy_folder(work, tmp_path):
    folder = export(work, "unsealed", tmp_path / "policy", "--resize-images")
    out = tmp_path / "eval"
    args = [
        f"--policy.path={folder}",
        f"--policy.key_file={work / 'user.key'}",
        "--env.type=metaworld",
        f"--env.task={tiny.TASK}",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        f"--output_dir={out}",
    ]
    p = lerobot("lerobot-eval", args, tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    assert json.loads((out / "eval_info.json").read_text())["overall"]["n_episodes"] == 1


def test_a_robot_that_does_not_give_the_bundles_features_is_refused_at_the_first_observation(
    work, frames, tmp_path, capsys
):
    folder = export(work, "unsealed", tmp_path / "policy")
    policy, pre, _ = by_path(folder)
    wrong = {k: v for k, v in frames[0].items() if k != tiny.STATE}
    line = refused(capsys, lambda: policy.select_action(pre(wrong)))
    assert "'observation.state'" in line and "the observation does not give" in line


def test_a_wrong_key_runs_through_the_encoder_only_when_asked(work, frames, capsys):
    """--policy.through_encoder: what anyone holding an unsealed bundle's files can run with any key (for
    measuring wrong keys in lerobot-eval), as prop's own runtime runs it; a sealed bundle's wrong key
    opens nothing there either, and the original runs."""
    from prop_cli.bundle import load_bundle
    from prop_cli.core.key_files import read_key_file
    from prop_cli.run import KeyedPolicy

    other = work / "other.key"
    bundle = load_bundle(work / "unsealed")
    prop = KeyedPolicy(bundle, read_key_file(other), method=True).controller
    expected = torch.cat([torch.as_tensor(prop.select_action(dict(f))).reshape(-1, 4) for f in frames])
    got = actions(make(work, "unsealed", key_file=str(other), through_encoder=True), frames)
    assert torch.equal(got, expected)
    assert not torch.equal(got, actions(make(work, "unsealed"), frames))
    sealed = actions(make(work, "sealed", key_file=str(other), through_encoder=True), frames)
    assert torch.equal(sealed, actions(original(work), frames))
    assert "none was given" in refused(capsys, lambda: make(work, "unsealed", through_encoder=True))
