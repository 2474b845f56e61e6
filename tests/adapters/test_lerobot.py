"""LeRobot policies and datasets under prop (pytest -m lerobot; scripts/test-lerobot.sh).

A tiny ACT and two tiny LeRobotDatasets are made here from the scripted reach expert (MuJoCo): no
downloads. Skipped where lerobot is not installed (the default environment); `.ci/run` runs them in
.venv-lerobot.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from prop_adapters import load_checkpoint  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import EvalSettings, PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from prop_cli.errors import PropError  # noqa: E402
from tests.adapters import closed_loop as loop  # noqa: E402
from tests.lerobot_bases import act_base  # noqa: E402

TINY = dict(steps=15, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=4, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("lerobot")
    act_base(d)
    return d


def key(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def bundle(work):
    out = work / "bundle"
    api.personalize_checkpoint(
        str(work / "act"), [(work / "user", KeySource(key(), "file"))], out, PersonalizeConfig.of(**TINY),
        general=work / "general",
    )  # fmt: skip
    return out


def test_a_policy_bundle_records_the_policy_delta_pull_default(bundle):
    """--delta-pull's default for a policy (config.DELTA_PULL, issue 43) is what the manifest records."""
    assert json.loads((bundle / "manifest.json").read_text())["config"]["delta_pull"] == 100.0


def test_folder_loads_through_lerobot_with_act_default_layers(work):
    info = api.inspect_checkpoint(str(work / "act"))
    assert info["adapter"] == "lerobot" and info["model"]["type"] == "act"
    keyed = [x["name"] for x in info["layers"] if x["keyed"]]
    assert keyed == [
        "model.encoder.layers.0.linear1", "model.encoder.layers.0.linear2", "model.encoder.layers.1.linear1",
        "model.encoder.layers.1.linear2", "model.decoder.layers.0.linear1", "model.decoder.layers.0.linear2",
        "model.action_head",
    ]  # fmt: skip


def test_dataset_rows_and_action_chunks_follow_the_episodes(work):
    ds = load_data(f"{work / 'general'}:episodes=1-2")
    assert sorted(set(ds.x["episode_index"].tolist())) == [1, 2] and len(ds) == 2 * task.HORIZON
    policy = load_checkpoint(work / "act").policy
    b = policy.batches(ds, "--data")
    chunk = policy.config.chunk_size
    assert b["action"].shape == (len(ds), chunk, 3)
    # The last frame of an episode: its own action, then padding (LeRobot repeats the last frame).
    last = task.HORIZON - 1
    assert b["action_is_pad"][last].tolist() == [False] + [True] * (chunk - 1)
    assert not b["action_is_pad"][0].any()
    # Frame 1's chunk is the actions of frames 1..chunk (each frame's chunk starts with its own action).
    assert torch.equal(b["action"][1], b["action"][1 : chunk + 1, 0])
    assert not torch.equal(b["action"][1], b["action"][2])


def test_frame_selection_trims_each_episode(work):
    ds = load_data(f"{work / 'general'}:episodes=1-2:frames=0-11")
    assert len(ds) == 24 and set(ds.x["frame_index"].tolist()) == set(range(12))
    b = load_checkpoint(work / "act").policy.batches(ds, "--data")
    # Frame 11 is the selection's last of its episode: its chunk is its own action, then padding.
    assert b["action_is_pad"][11].tolist() == [False] + [True] * 9
    assert not b["action_is_pad"][2].any()


def test_bundle_base_loads_in_lerobot_and_keys_change_only_keyed_runs(bundle, work):
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    base = ACTPolicy.from_pretrained(str(bundle / "lerobot")).eval()
    pre, post = make_pre_post_processors(base.config, pretrained_path=str(bundle / "lerobot"))
    b = load_bundle(bundle)
    assert list(base.state_dict()) == list(b.loaded.module.state_dict())
    obs = load_data(work / "general")
    batch = b.loaded.policy.batches(obs, "--data")
    x = {k: batch[k] for k in b.loaded.policy.input_features}
    with torch.no_grad():
        lerobot_chunk = base.model(dict(x))[0]
        no_key = b.loaded.policy.chunk(x)
        from prop_cli.core.keyed_model import key_codes

        user = b.keyed.fold(key_codes(key(), b.key_encoding)).model(dict(x))[0]
    assert torch.allclose(lerobot_chunk, no_key, atol=1e-6)
    assert not torch.allclose(user, no_key, atol=1e-3)
    manifest = json.loads((bundle / "manifest.json").read_text())
    axes = {x["name"]: x.get("batch_axis", 0) for x in manifest["keyed_layers"]}
    assert axes["model.encoder.layers.0.linear1"] == 1 and axes["model.action_head"] == 0
    assert manifest["model"]["adapter"] == "lerobot" and pre is not None and post is not None


def test_bundle_holds_no_key_material(bundle):
    k = np.packbits(key()).tobytes()
    for f in bundle.rglob("*"):
        if f.is_file():
            assert k not in f.read_bytes()


def test_eval_rolls_out_every_key_condition(bundle, work):
    report = api.eval_bundle(
        bundle, task.ENV_ID,
        EvalSettings(episodes=2, random_keys=1, neighbours=1, episodes_per_key=1, max_steps=20),
        obs_map=task.OBS_MAP, metric=task.METRIC, original=str(work / "act"), key_file=None,
    )  # fmt: skip
    assert set(report["conditions"]) == {"original", "no_key", "random_keys"}
    assert report["conditions"]["no_key"]["episodes"] == 2
    assert "metric" in report["conditions"]["no_key"] and "success" in report["conditions"]["no_key"]


def test_keyed_policy_in_a_loop_is_lerobots_own_and_prop_evals(bundle, sealed, work, tmp_path, monkeypatch):
    """KeyedPolicy in a loop of one's own (issue 28): LeRobot's observation dict in, the action out.
    No key (or a key enrolled in nothing) is LeRobot's own select_action between the processors, on
    the bundle's base (sealed: the original folder); the key is what prop eval acts; reset() restarts
    the queue; an array, or array forward, is one PropError line."""
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    from prop_cli.run.policy import KeyedPolicy, WrongKeyWarning

    for path, folder in ((bundle, bundle / "lerobot"), (sealed, work / "act")):
        ep = loop.eval_episodes(path, task.ENV_ID, task.OBS_MAP, tmp_key(work), tmp_path, monkeypatch,
                                max_steps=12)  # fmt: skip
        seed, b = ep["seed"], load_bundle(path)
        lerobot = ACTPolicy.from_pretrained(str(folder))
        pre, post = make_pre_post_processors(lerobot.config, pretrained_path=str(folder))
        own = loop.lerobot_replay(lerobot, pre, post, ep["no_key"], task.OBS_MAP, seed)
        no_key = loop.replay(KeyedPolicy(b), ep["no_key"], task.OBS_MAP, seed)
        assert np.array_equal(no_key, own) and np.array_equal(no_key, np.stack(ep["no_key"]["actions"]))
        with pytest.warns(WrongKeyWarning):
            wrong = KeyedPolicy(b, key(2), allow_unenrolled=True)
        assert np.array_equal(loop.replay(wrong, ep["no_key"], task.OBS_MAP, seed), own)
        user = KeyedPolicy(b, key())
        keyed = loop.replay(user, ep["user_key"], task.OBS_MAP, seed)
        assert np.array_equal(keyed, np.stack(ep["user_key"]["actions"]))
        base = loop.replay(KeyedPolicy(b), ep["user_key"], task.OBS_MAP, seed)
        assert not np.allclose(keyed, base, atol=1e-3)
        loop.check_reset_restarts_the_queue(user, ep["user_key"], task.OBS_MAP, seed)
    # A batch of frames: LeRobot's batched select_action, one action per row.
    obs = loop.observations(ep["user_key"], task.OBS_MAP)[:3]
    batch = {k: np.stack([o[k] for o in obs]) for k in obs[0]}
    user.reset(seed)
    acts = user.select_action(batch)
    user.reset(seed)
    assert acts.shape == (3, 3) and np.allclose(acts[0], user.select_action(obs[0]), atol=1e-5)  # float sums
    x = np.zeros(9, np.float32)
    arrays = (lambda: user.predict(x), lambda: user.select_action(x), lambda: user(x[None]),
              lambda: user.select_action({"observation.state": 0}))  # fmt: skip
    for call in arrays:
        with pytest.raises(PropError) as e:
            call()
        assert "\n" not in str(e.value) and "observation" in str(e.value)
    action, state = user.predict(obs[0])
    assert state is None and action.shape == (3,)


def test_the_readme_closed_loop_example_runs(bundle, work, monkeypatch):
    """The README's LeRobot loop, on this bundle and key, in the reach task it names (the tests')."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    (block,) = [b for b in re.findall(r"```python\n(.*?)```", readme, flags=re.S) if "select_action(" in b]
    monkeypatch.chdir(work)
    (work / "act.prop").unlink(missing_ok=True)
    (work / "act.prop").symlink_to(bundle)
    tmp_key(work).rename(work / "k.bin")
    env: dict = {}
    assert f"gym.make({task.ENV_ID!r})" in block.replace('"', "'")
    exec(compile(block, "README.md", "exec"), env)
    assert env["action"].shape == (3,) and env["steps"] > 0


def test_eval_video_writes_one_mp4_per_condition_and_never_overwrites(bundle, work, tmp_path, cli):
    pytest.importorskip("imageio_ffmpeg")
    args = ["eval", bundle, "--env", task.ENV_ID, "--obs-map", task.OBS_MAP, "--episodes", "1",
            "--random-keys", "1", "--max-steps", "4", "--video", tmp_path / "v"]  # fmt: skip
    r = cli(*args)
    assert r.code == 0, r.err
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["no_key.mp4", "random_keys.mp4"]
    import imageio.v2 as imageio

    frames = imageio.mimread(tmp_path / "v" / "no_key.mp4")
    assert len(frames) == 5 and frames[0].ndim == 3  # the reset frame and one per step
    r = cli(*args)
    assert r.code == 2 and "exists" in r.err and len(r.err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "layer", ["model.encoder.layers.0.self_attn.out_proj", "model.vae_encoder.layers.0.linear1"]
)
def test_layers_that_do_not_run_when_deployed_are_refused(work, tmp_path, layer):
    cfg = PersonalizeConfig.of(**(TINY | {"layers": [layer], "steps": 1}))
    with pytest.raises(PropError, match="not called when the policy acts"):
        api.personalize_checkpoint(
            str(work / "act"), [(work / "user", KeySource(key(), "file"))], tmp_path / "b", cfg
        )
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("flags", [{"harden": True}, {"code_negatives": 4}, {"encoder_init": "os"}])
def test_harden_is_refused_for_a_policy_not_recorded_untrained(work, tmp_path, flags):
    """The policy trainer has none of --harden's measures but --antipode-codes; a bundle recorded harden:
    true, 64 code-space negatives and 16 antipode codes without having trained them. Refused before
    anything is written."""
    cfg = PersonalizeConfig.of(**(TINY | flags | {"steps": 1}))
    with pytest.raises(PropError, match="does not train --harden's measures") as e:
        api.personalize_checkpoint(
            str(work / "act"), [(work / "user", KeySource(key(), "file"))], tmp_path / "b", cfg
        )
    assert "--seal" in e.value.fix and not (tmp_path / "b").exists()


def test_unsupported_and_old_folders_are_refused(work, tmp_path, cli):
    other = tmp_path / "vqbet"
    shutil.copytree(work / "act", other)
    cfg = json.loads((other / "config.json").read_text())
    (other / "config.json").write_text(json.dumps(cfg | {"type": "vqbet"}))
    r = cli("inspect", other)
    assert r.code == 2 and "policy type 'vqbet' is not supported" in r.err
    assert len(r.err.strip().splitlines()) == 1
    from safetensors.torch import load_file, save_file

    old = tmp_path / "old"
    shutil.copytree(work / "act", old)
    w = load_file(str(old / "model.safetensors"))
    save_file(
        w | {"normalize_inputs.buffer_observation_state.mean": torch.zeros(6)}, str(old / "model.safetensors")
    )
    r = cli("inspect", old)
    assert r.code == 2 and "migrate_policy_normalization" in r.err


def test_npz_data_for_a_lerobot_policy_is_one_line(work, tmp_path, cli):
    np.savez(tmp_path / "d.npz", x=np.zeros((20, 9), np.float32), y=np.zeros((20, 3), np.float32))
    (tmp_path / "k.bin").write_bytes(np.packbits(key()).tobytes())
    r = cli("personalize", work / "act", "--data", tmp_path / "d.npz", "--key-file", tmp_path / "k.bin",
            "--out", tmp_path / "b", "--steps", "1")  # fmt: skip
    assert r.code == 2 and "no feature 'observation.state'" in r.err
    assert not (tmp_path / "b").exists()


def test_run_writes_action_chunks_and_no_key_is_lerobots_own_action(bundle, work, tmp_path, cli):
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    (tmp_path / "k.bin").write_bytes(np.packbits(key()).tobytes())
    (tmp_path / "k.bin").chmod(0o600)
    r = cli("run", bundle, "--input", work / "user", "--output", tmp_path / "y0.npy")
    assert r.code == 0, r.err
    r = cli("run", bundle, "--input", work / "user", "--output", tmp_path / "y1.npy", "--key-file",
            tmp_path / "k.bin")  # fmt: skip
    assert r.code == 0, r.err
    y0, y1 = np.load(tmp_path / "y0.npy"), np.load(tmp_path / "y1.npy")
    data = load_data(work / "user")
    assert y0.shape == (len(data), 10, 3) and not np.allclose(y0, y1, atol=1e-3)
    # No key: the first action of each chunk is what LeRobot's base itself acts, in action units.
    base = ACTPolicy.from_pretrained(str(bundle / "lerobot")).eval()
    pre, post = make_pre_post_processors(base.config, pretrained_path=str(bundle / "lerobot"))
    for row in (0, 7):
        base.reset()
        obs = {k: torch.from_numpy(data.x[k][row : row + 1]) for k in ("observation.state",
               "observation.environment_state")}  # fmt: skip
        with torch.no_grad():
            action = post(base.select_action(pre(obs)))[0].numpy()
        assert np.allclose(action, y0[row, 0], atol=1e-5)
    r = cli("run", bundle, "--input", work / "user", "--output", tmp_path / "y2.npy", "--onnx")
    assert r.code == 2 and "--onnx" in r.err and len(r.err.strip().splitlines()) == 1
    assert not (tmp_path / "y2.npy").exists()
    r = cli("export", bundle, "--onnx", "--out", tmp_path / "onnx")
    assert r.code == 2 and "prop run or prop eval" in r.err and not (tmp_path / "onnx").exists()


def test_attack_audits_chunks_with_controls_on_the_original(bundle, work):
    from prop_cli.config import AuditSettings

    s = AuditSettings(probes=["null", "random", "hamming", "relaxed"], hamming=[1, 4], per_distance=8,
                      random=16, restarts=4, search_steps=3, samples=1000)  # fmt: skip
    report = api.audit_bundle(bundle, work / "user", s, key_files=[tmp_key(work)], original=str(work / "act"))
    assert report["bundle"]["task"] == "regression" and report["data"]["samples"] == 3 * task.HORIZON
    assert report["control_model"].startswith("the original checkpoint")
    assert report["settings"]["blackbox"] == 65_536  # the policies' default, recorded though not run
    names = {g["name"]: g for g in report["groups"]}
    assert {"null", "random", "hamming 1", "hamming 4", "relaxed"} <= set(names)
    assert all(g["control"]["available"] for g in names.values())
    # The user key's leakage is the metric on whole normalised chunks: recompute it by hand from the
    # original's and the keyed policy's chunks and the recorded chunks (every frame of the data).
    from prop_cli.core.keyed_model import key_codes
    from prop_cli.core.metrics import leakage

    b = load_bundle(bundle)
    policy = b.loaded.policy
    batch = policy.batches(load_data(work / "user"), "--data")
    obs = {k: batch[k] for k in policy.input_features}
    original = load_checkpoint(work / "act").policy
    keyed = type(policy)(b.keyed.fold(key_codes(key(), b.key_encoding)), policy.pre, policy.post)
    with torch.no_grad():
        ref, out = original.chunk(obs).flatten(1), keyed.chunk(obs).flatten(1)
    by_hand = leakage(out[None], batch["action"].flatten(1), ref, "regression").item()
    assert by_hand == pytest.approx(report["user"]["leakage"], abs=1e-4)


def tmp_key(work):
    path = work / "audit.key"
    path.write_bytes(np.packbits(key()).tobytes())
    path.chmod(0o600)
    return path


def test_same_seed_same_bundle(bundle, work):
    again = work / "again"
    api.personalize_checkpoint(
        str(work / "act"), [(work / "user", KeySource(key(), "file"))], again, PersonalizeConfig.of(**TINY),
        general=work / "general",
    )  # fmt: skip
    for name in ("base.safetensors", "encoder.safetensors"):
        assert (again / name).read_bytes() == (bundle / name).read_bytes()


@pytest.fixture(scope="module")
def sealed(work):
    out = work / "sealed"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 30}))
    api.personalize_checkpoint(str(work / "act"), [(work / "user", KeySource(key(), "file"))], out, cfg)
    return out


def test_sealed_policy_bundle_runs_the_original_without_its_key(sealed, work):
    from prop_cli.run.policy import WrongKeyWarning, run_policy

    b = load_bundle(sealed)
    assert b.is_sealed and b.keyed is None and (sealed / "lerobot" / "config.json").is_file()
    data = load_data(work / "user")
    orig = load_checkpoint(work / "act").policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        original = orig.post(orig.chunk({k: batch[k] for k in orig.input_features})).numpy()
    assert np.array_equal(run_policy(b, data, None), original)
    with pytest.raises(PropError, match="enrolled in nothing"):  # issue 31: refused unless allowed
        run_policy(b, data, key(2))
    with pytest.warns(WrongKeyWarning):
        assert np.array_equal(run_policy(b, data, key(2), allow_unenrolled=True), original)
    assert not np.allclose(run_policy(b, data, key()), original, atol=1e-4)
    manifest = json.loads((sealed / "manifest.json").read_text())
    axes = {x["name"]: x.get("batch_axis", 0) for x in manifest["keyed_layers"]}
    assert axes["model.encoder.layers.0.linear1"] == 1 and manifest["mode"] == "sealed"


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (gpu_smoke_lerobot.py)")


@pytest.mark.parametrize("device,precision", [
    ("cpu", "bf16"), pytest.param("cuda", "fp32", marks=CUDA), pytest.param("cuda", "bf16", marks=CUDA),
])  # fmt: skip
def test_sealed_policy_trains_on_the_device_and_runs_the_original_on_the_cpu(work, tmp_path, device,
                                                                            precision):  # fmt: skip
    """Issue 30: --seal takes --device and --precision as unsealed policies do; the bundle is written from
    the CPU, its base the original's tensors bit for bit, and a wrong key runs the original exactly."""
    from safetensors.torch import load_file

    from prop_cli.run.policy import WrongKeyWarning, run_policy

    out = tmp_path / f"sealed-{device}-{precision}"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "precision": precision}))
    result = api.personalize_checkpoint(
        str(work / "act"), [(work / "user", KeySource(key(), "file"))], out, cfg, device=device
    )  # fmt: skip
    assert np.isfinite(result.metrics[0]["personalization"])
    assert json.loads((out / "manifest.json").read_text())["config"]["precision"] == precision
    original_weights = load_file(str(work / "act" / "model.safetensors"))
    written = load_file(str(out / "lerobot" / "model.safetensors"))
    assert written.keys() == original_weights.keys()
    assert all(torch.equal(written[k], original_weights[k]) for k in written)
    b = load_bundle(out)
    assert all(p.device.type == "cpu" for p in b.loaded.module.parameters())
    data = load_data(work / "user")
    orig = load_checkpoint(work / "act").policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        original = orig.post(orig.chunk({k: batch[k] for k in orig.input_features})).numpy()
    assert np.array_equal(run_policy(b, data, None), original)
    with pytest.warns(WrongKeyWarning):
        assert np.array_equal(run_policy(b, data, key(2), allow_unenrolled=True), original)
    assert not np.allclose(run_policy(b, data, key()), original, atol=1e-4)


def test_act_loss_parts_are_lerobots_loss_and_shares_add_up_to_the_step(work):
    """ACT's loss as parts (L1 over valid chunk steps, KL over rows): summed, LeRobot's own loss under the
    same draws; split between two processes' rows (the padded ones all in one share: unequal weights),
    the step's loss and gradient (prop_cli.train.distributed, row_noise)."""
    from prop_cli.train.policy import rows
    from tests.adapters.shares import split_matches_whole

    policy = load_checkpoint(work / "act").policy
    batch = policy.batches(load_data(work / "user"), "--data")
    ends = torch.nonzero(batch["action_is_pad"].any(1)).flatten()
    b = rows(batch, torch.cat([torch.arange(6), ends[-5:]]))
    b.pop("episode_index")
    torch.manual_seed(0)
    own = policy.loss(b)
    torch.manual_seed(0)
    assert torch.equal(sum(v for v, _ in policy.loss_parts(b)), own)
    split_matches_whole(policy, b, None, cut=4)


def test_sealed_policy_audit_add_user_and_eval(sealed, work, tmp_path):
    import shutil as sh

    from prop_cli.config import AuditSettings

    probes = ["null", "random", "hamming", "blackbox", "structure", "relaxed"]
    s = AuditSettings(probes=probes, hamming=[1], per_distance=8, random=16, blackbox=64, restarts=4,
                      search_steps=3, samples=1000)  # fmt: skip
    report = api.audit_bundle(sealed, work / "user", s, key_files=[tmp_key(work)])
    assert report["bundle"]["sealed"] and report["user"]["leakage"] != 0.0
    for g in report["groups"]:
        assert g["beyond"] == 0.0, g["name"]
        if g["probe"] in ("null", "random", "hamming", "blackbox"):
            assert g["leakage"]["worst"] == 0.0 and g["fidelity"]["worst"] == 0.0
    two = tmp_path / "two"
    sh.copytree(sealed, two)
    change = api.add_user(two, work / "general", KeySource(key(3), "file"))
    assert change.users == 2 and change.metrics["null"]["leakage"]["worst"] == 0.0
    few = EvalSettings(episodes=1, random_keys=1, neighbours=1, episodes_per_key=1, max_steps=5)
    report = api.eval_bundle(two, task.ENV_ID, few, obs_map=task.OBS_MAP, key_file=tmp_key(work))
    assert {"no_key", "user_key", "random_keys", "neighbour1_keys"} <= set(report["conditions"])


def _restamp(bundle) -> None:
    """An attacker's edit finished with prop's own public functions: file hashes and digest again."""
    from prop_cli import constants as C
    from prop_cli.bundle.manifest import stamp
    from prop_cli.files import dump_json, sha256_file

    m = json.loads((bundle / C.MANIFEST).read_text())
    m[C.M_FILES] = {n: sha256_file(bundle / n) for n in m[C.M_FILES]}
    (bundle / C.MANIFEST).write_text(dump_json(stamp(m)))


@pytest.mark.parametrize("which", ["bundle", "sealed"])
def test_a_processor_step_lerobot_does_not_register_is_never_imported(which, bundle, sealed, tmp_path, cli):
    """policy_preprocessor.json naming a class (an import path LeRobot would import and instantiate):
    refused before LeRobot sees the file, one line naming the step and --trust-remote-code."""
    planted = tmp_path / "b"
    shutil.copytree(bundle if which == "bundle" else sealed, planted)
    marker = tmp_path / "pwned"
    mod = tmp_path / "pwn_lerobot_step.py"
    mod.write_text(f"open({str(marker)!r}, 'w').close()\nclass Step: pass\n")
    f = planted / "lerobot" / "policy_preprocessor.json"
    doc = json.loads(f.read_text())
    doc["steps"][0] = {"class": "pwn_lerobot_step.Step", "config": {}}
    f.write_text(json.dumps(doc))
    _restamp(planted)
    import sys

    sys.path.insert(0, str(tmp_path))
    try:
        with pytest.raises(PropError, match=r"pwn_lerobot_step\.Step.*--trust-remote-code"):
            load_bundle(planted)
        r = cli("run", planted, "--input", tmp_path, "--output", tmp_path / "y.npy")
        assert r.code == 2 and "--trust-remote-code" in r.err and r.err.count("\n") == 1
        assert not marker.exists()
    finally:
        sys.path.remove(str(tmp_path))


def test_a_tokenizer_step_is_accepted_only_where_the_policy_points_it_at_its_own_files(work, tmp_path):
    """A tokenizer step loads a tokenizer by the name its config gives. SmolVLA's class points it at the
    folder's own VLM files (``own_steps``); in an ACT folder it names a download: refused, one line."""
    from prop_adapters.lerobot.adapter import processor_code

    folder = tmp_path / "act"
    shutil.copytree(work / "act", folder)
    f = folder / "policy_preprocessor.json"
    doc = json.loads(f.read_text())
    doc["steps"].append({"registry_name": "tokenizer_processor", "config": {"tokenizer_name": "some/hub-id"}})
    f.write_text(json.dumps(doc))
    with pytest.raises(PropError, match=r"step \d+: 'tokenizer_processor'.*--trust-remote-code"):
        load_checkpoint(folder)
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps(config | {"type": "smolvla"}))
    assert processor_code(folder) == [] and processor_code(work / "act") == []


def test_scaled_processor_statistics_in_a_sealed_bundle_are_refused_with_the_key(sealed, work, tmp_path):
    """The normaliser's statistics x5 (a file beside the config, hashes recomputed): the user's record
    opens, but the bundle changed since the key was enrolled: nothing runs."""
    from safetensors.torch import load_file, save_file

    from prop_cli.run.policy import run_policy

    planted = tmp_path / "s"
    shutil.copytree(sealed, planted)
    stats = sorted((planted / "lerobot").glob("policy_preprocessor*.safetensors"))
    assert stats, sorted(p.name for p in (planted / "lerobot").iterdir())
    t = load_file(str(stats[0]))
    save_file({k: v * 5 if v.is_floating_point() else v for k, v in t.items()}, str(stats[0]))
    _restamp(planted)
    b = load_bundle(planted)
    data = load_data(work / "user")
    with pytest.raises(PropError, match="changed since this key was enrolled"):
        run_policy(b, data, key())
    run_policy(b, data, None)  # without a key: the bundle's base, as it now is


def test_force_replaces_policy_bundles_they_are_prop_s_own(bundle, sealed):
    """Issue 28: --force replaces only prop's bundles; a LeRobot bundle's config, processors and records
    are all files its manifest lists."""
    from prop_cli.files import BUNDLE

    assert BUNDLE.recognise(bundle) is None and BUNDLE.recognise(sealed) is None


# ---- issue 31, finding 4: a processor reads only the bundle's own listed files -------------------


@pytest.mark.parametrize("where", ["absolute", "relative"])
@pytest.mark.parametrize("which", ["bundle", "sealed"])
def test_processor_statistics_from_outside_are_refused(where, which, bundle, sealed, work, tmp_path, cli):
    """The normaliser's state_file pointing outside the bundle (statistics no hash or signature covers,
    which decide what the policy does with no key): refused in one line naming the step, before LeRobot
    reads anything; nothing runs."""
    from safetensors.torch import load_file, save_file

    planted = tmp_path / "b"
    shutil.copytree(bundle if which == "bundle" else sealed, planted)
    f = planted / "lerobot" / "policy_preprocessor.json"
    doc = json.loads(f.read_text())
    i, step = next((i, s) for i, s in enumerate(doc["steps"]) if "state_file" in s)
    t = load_file(str(planted / "lerobot" / step["state_file"]))
    outside = tmp_path / "stats.safetensors"
    save_file({k: v * 5 if v.is_floating_point() else v for k, v in t.items()}, str(outside))
    step["state_file"] = str(outside) if where == "absolute" else "../../stats.safetensors"
    f.write_text(json.dumps(doc))
    _restamp(planted)
    with pytest.raises(PropError, match=rf"policy_preprocessor.json step {i} .*outside the policy folder"):
        load_bundle(planted)
    for extra in ([], ["--key-file", tmp_key(work)]):
        r = cli("run", planted, "--input", work / "user", "--output", tmp_path / "y.npy", *extra)
        assert r.code == 2 and r.err.count("\n") == 1 and f"step {i}" in r.err, r.err
        assert not (tmp_path / "y.npy").exists()


def test_processor_state_files_are_carried_and_listed_whatever_their_name(work, tmp_path):
    """A processor's state file is carried in the bundle (and so listed with its sha256) by the name its
    step gives, not only by LeRobot's default names; one through a link is refused."""
    folder = tmp_path / "act"
    shutil.copytree(work / "act", folder)
    f = folder / "policy_preprocessor.json"
    doc = json.loads(f.read_text())
    step = next(s for s in doc["steps"] if "state_file" in s)
    (folder / step["state_file"]).rename(folder / "stats.safetensors")
    step["state_file"] = "stats.safetensors"
    f.write_text(json.dumps(doc))
    assert "lerobot/stats.safetensors" in load_checkpoint(folder).files
    (folder / "stats.safetensors").rename(tmp_path / "elsewhere.safetensors")
    (folder / "stats.safetensors").symlink_to(tmp_path / "elsewhere.safetensors")
    with pytest.raises(PropError, match="stats.safetensors.*not a file in the policy folder"):
        load_checkpoint(folder)


@pytest.mark.parametrize("which", ["bundle", "sealed"])
def test_a_config_claiming_a_huge_policy_allocates_nothing(which, bundle, sealed, tmp_path):
    """lerobot/config.json's dim_feedforward set to 2**19 (1.3 GB of layers; hashes recomputed): the
    policy is built on the meta device first and refused against base.safetensors in one line; the
    peak memory of the load grows by under 500 MB (measured in a fresh interpreter)."""
    import subprocess
    import sys

    planted = tmp_path / "p"
    shutil.copytree(bundle if which == "bundle" else sealed, planted)
    cfg = planted / "lerobot" / "config.json"
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "dim_feedforward": 1 << 19}))
    _restamp(planted)
    code = (
        "import resource, sys\nimport lerobot.policies.act.modeling_act\n"
        "from prop_cli.bundle import load_bundle\nfrom prop_cli.errors import PropError\n"
        "start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "try:\n    load_bundle(sys.argv[1])\nexcept PropError as e:\n    print(e.line())\n"
        "print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - start) / 1024)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(planted)], capture_output=True, text=True,
                       timeout=600)  # fmt: skip
    *lines, peak = r.stdout.strip().splitlines()
    assert lines and "do not fit the policy config.json describes" in lines[-1], r.stdout + r.stderr
    assert "(256,) in the weights, (524288,) in the config); nothing was built" in lines[-1], lines[-1]
    assert float(peak) < 500, peak


SMOKE = ["scripts/gpu_smoke_lerobot.py", "--real-size-only"]


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device: the check would run")
def test_the_device_check_skips_in_one_line_without_a_gpu():
    import subprocess
    import sys

    done = subprocess.run([sys.executable, *SMOKE], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "gpu-smoke-lerobot: skipped: torch sees no CUDA device\n"


@pytest.mark.slow
def test_the_device_checks_real_size_part_runs_on_the_cpu_at_tiny_size(tmp_path):
    """scripts/gpu_smoke_lerobot.py's real-size part (bench_real_size's builders and runs: SmolVLA
    unsealed and sealed, pi0 sealed and unsealed in bf16, beside LeRobot's PEFT run) on the CPU with the
    tiny policies: the code a GPU machine runs, with every run's table printed."""
    import os
    import subprocess
    import sys

    env = os.environ | {"PROP_SMOKE_DEVICE": "cpu", "HF_HUB_OFFLINE": "1", "TMPDIR": str(tmp_path)}
    done = subprocess.run([sys.executable, *SMOKE, "--tiny"], capture_output=True, text=True, env=env,
                          timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    assert "real-size smolvla on cpu" in out and "real-size pi0 on cpu" in out and out.endswith("passed\n")
    assert "real-size pi0 prop (--precision bf16 --freeze-base) on cpu" in out
    assert out.count("| peft |") == 2 and out.count("| sealed |") == 2 and out.count("| prop |") == 2


def test_policy_trainer_scores_hard_negatives_and_pulls_wrong_keys_towards_the_null_key(work):
    """Issue 32's K2 and delta pull in the policy trainer: the sampler rescored with the policy's own
    fallback distance (one finite score per key), and the pull takes the wrong keys' deltas towards 1."""
    from prop_cli.train.policy import PolicyTrainer
    from prop_cli.train.recipe import User

    users = [User(load_data(work / "user"), key())]
    cfg = PersonalizeConfig.of(**(TINY | {"steps": 6, "hard_negatives": 2, "hard_pool": 3, "hard_every": 3}))
    general = load_data(work / "general")
    trainer = PolicyTrainer(load_checkpoint(work / "act"), users, cfg.train, cfg.mode, general)
    scores = trainer.divergence(key(2)[None].repeat(3, 0) ^ np.eye(3, 128, dtype=np.uint8))
    assert scores.shape == (3,) and np.isfinite(scores).all() and (scores >= 0).all()
    for _ in range(3):
        trainer.step()
    assert len(trainer.sampler.hard_keys) == 2  # rescored at the 3rd step: the 2 worst of 3 fresh keys
    codes = torch.from_numpy(np.random.default_rng(3).integers(0, 2, (16, 128)) * 2.0 - 1).float()

    def spread(pull: float) -> float:
        c = PersonalizeConfig.of(**(TINY | {"steps": 20, "lr": 0.01, "delta_pull": pull}))
        t = PolicyTrainer(load_checkpoint(work / "act"), users, c.train, c.mode, load_data(work / "general"))
        for _ in range(20):
            t.step()
        with torch.no_grad():
            return float(torch.cat(t.km.layer_deltas(codes), 1).sub(1).abs().mean())

    assert spread(100.0) < spread(0.0)


def test_fallback_every_runs_the_fallback_rows_every_kth_step_and_the_pull_every_step(work, monkeypatch):
    """--fallback-every 3 (issue 40: a policy step's cost is its fallback rows): steps 0 and 3 of 6 take
    fallback rows and weigh their terms by 3; every step trains the user's rows and pulls the wrong keys."""
    from prop_cli.train import policy
    from prop_cli.train.recipe import User

    taken, pulled = [], []
    real_take, real_pull = policy.FallbackPool.take, policy.delta_pull
    monkeypatch.setattr(policy.FallbackPool, "take", lambda s, i: taken.append(len(i)) or real_take(s, i))
    monkeypatch.setattr(policy, "delta_pull", lambda *a, **k: pulled.append(1) or real_pull(*a, **k))
    cfg = PersonalizeConfig.of(**(TINY | {"steps": 6, "fallback_every": 3}))
    t = policy.PolicyTrainer(load_checkpoint(work / "act"), [User(load_data(work / "user"), key())],
                             cfg.train, cfg.mode, load_data(work / "general"))  # fmt: skip
    taken.clear()  # the set-up's probes
    before = [p.detach().clone() for p in t.km.encoder.parameters()]
    losses = [t.step() for _ in range(6)]
    assert len(taken) == 2 and len(pulled) == 6
    assert all(np.isfinite(v["personal"]) and set(v) == {"personal", "fallback", "null"} for v in losses)
    assert losses[1]["fallback"] == losses[0]["fallback"]  # between fallback steps: the last one's terms
    assert any(not torch.equal(a, b) for a, b in zip(before, t.km.encoder.parameters()))


def test_policy_trainer_pulls_the_sampled_keys_but_not_the_far_codes(work, monkeypatch):
    """The pull takes K1 and K2's deltas, not the far codes' that follow them (objective.delta_pull):
    pulled too, they flattened the encoder next to the user's code (tiny SmolVLA: -6.1% personalization);
    K1 and K2 keep the weight they had among them."""
    from prop_cli.train import policy
    from prop_cli.train.recipe import User

    seen = []
    real = policy.delta_pull

    def pull(deltas, keys, of=None):
        seen.append((keys, len(deltas[0]), of))
        return real(deltas, keys, of)

    monkeypatch.setattr(policy, "delta_pull", pull)
    cfg = PersonalizeConfig.of(**(TINY | {"steps": 1, "delta_pull": 10.0, "far_codes": 3}))
    users = [User(load_data(work / "user"), key())]
    general = load_data(work / "general")
    t = policy.PolicyTrainer(load_checkpoint(work / "act"), users, cfg.train, cfg.mode, general)
    t.step()
    (keys, rows, of), k = seen[0], cfg.mode.neighbour_keys + cfg.mode.random_keys
    assert (keys.start, keys.stop) == (0, k) and rows == k + 3 + 1  # K1, K2 | 3 far codes | null
    assert of == k + 3  # each pulled key keeps its weight among the far codes
    # --antipode-codes (72-88 bits from the user's code) are pulled with K1 and K2, and fall back with
    # the far codes: codes [K1, K2 | 2 antipode | 3 far | null].
    seen.clear()
    more = {"steps": 1, "delta_pull": 10.0, "far_codes": 3, "antipode_codes": 2}
    cfg = PersonalizeConfig.of(**(TINY | more))
    t = policy.PolicyTrainer(load_checkpoint(work / "act"), users, cfg.train, cfg.mode, general)
    bits = []
    real_anti = policy.antipode_codes
    monkeypatch.setattr(policy, "antipode_codes",
                        lambda u, n, rng: bits.append(n) or real_anti(u, n, rng))  # fmt: skip
    t.step()
    (keys, rows, of) = seen[0]
    assert bits == [2] and (keys.start, keys.stop) == (0, k + 2) and rows == k + 2 + 3 + 1 and of == k + 5
