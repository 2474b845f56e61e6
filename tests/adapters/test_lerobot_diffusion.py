"""LeRobot Diffusion Policy under prop (pytest -m lerobot; scripts/test-lerobot.sh).

A small Diffusion Policy (U-Net 32/64/128) trained a few steps on datasets recorded from the scripted
reach expert (MuJoCo): no downloads. What differs from ACT is tested here: the keyed convolutions, the
noise seed, the denoiser as the fallback target, LeRobot's own sampler as the deployed chunk.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from prop_adapters import load_checkpoint  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import AuditSettings, EvalSettings, PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from tests.adapters import closed_loop as loop  # noqa: E402
from tests.lerobot_bases import diffusion_base  # noqa: E402

TINY = dict(steps=15, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=2, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
STATE_KEYS = ("observation.state", "observation.environment_state")


def key(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("diffusion")
    diffusion_base(d)
    path = d / "k.bin"
    path.write_bytes(np.packbits(key()).tobytes())
    path.chmod(0o600)
    return d


@pytest.fixture(scope="module")
def bundle(work):
    out = work / "bundle"
    api.personalize_checkpoint(
        str(work / "diffusion"), [(work / "user", KeySource(key(), "file"))], out,
        PersonalizeConfig.of(**TINY), general=work / "general",
    )  # fmt: skip
    return out


@pytest.fixture(scope="module")
def sealed(work):
    out = work / "sealed"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 20}))
    api.personalize_checkpoint(str(work / "diffusion"), [(work / "user", KeySource(key(), "file"))], out, cfg)
    return out


def test_the_unets_convolutions_are_keyed_by_default(work, cli):
    info = api.inspect_checkpoint(str(work / "diffusion"))
    assert info["model"]["type"] == "diffusion" and info["model"]["horizon"] == 16
    keyed = {x["name"]: x for x in info["layers"] if x["keyed"]}
    assert keyed and all(n.startswith("diffusion.unet.") for n in keyed)
    assert "diffusion.unet.final_conv.1" in keyed and "diffusion.unet.down_modules.0.0.conv1.block.0" in keyed
    assert not any("diffusion_step_encoder" in n for n in keyed)
    # Most of the U-Net's parameters sit in keyed layers (the convolutions and their FiLM projections).
    assert info["keyed_share"] > 0.9 and info["keyed_parameters"] <= info["parameters"]
    r = cli("inspect", work / "diffusion")
    assert r.code == 0 and "keyed" in r.out


def test_bundle_base_loads_in_lerobot_and_no_key_is_lerobots_own_action(bundle, work, tmp_path, cli):
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    base = DiffusionPolicy.from_pretrained(str(bundle / "lerobot")).eval()
    pre, post = make_pre_post_processors(base.config, pretrained_path=str(bundle / "lerobot"))
    assert list(base.state_dict()) == list(load_bundle(bundle).loaded.module.state_dict())
    ys = {}
    for name, seed, extra in (("no_key", 7, []), ("again", 7, []), ("seed8", 8, []),
                              ("key", 7, ["--key-file", work / "k.bin"])):  # fmt: skip
        r = cli("run", bundle, "--input", work / "user", "--output", tmp_path / f"{name}.npy",
                "--noise-seed", seed, *extra)  # fmt: skip
        assert r.code == 0, r.err
        ys[name] = np.load(tmp_path / f"{name}.npy")
    data = load_data(work / "user")
    assert ys["no_key"].shape == (len(data), 16, 3)
    assert np.array_equal(ys["no_key"], ys["again"])  # the noise seed makes chunks reproducible
    assert not np.allclose(ys["no_key"], ys["seed8"], atol=1e-3)
    assert not np.allclose(ys["no_key"], ys["key"], atol=1e-3)
    # An episode's first frame: its history is that frame twice, as LeRobot's queue after a reset. Its
    # first action is LeRobot's own select_action after torch.manual_seed(noise seed).
    first = np.flatnonzero(data.x["frame_index"] == 0)
    for row in first:
        base.reset()
        obs = {k: torch.from_numpy(data.x[k][row : row + 1]) for k in STATE_KEYS}
        torch.manual_seed(7)
        with torch.no_grad():
            action = post(base.select_action(pre(obs)))[0].numpy()
        assert np.allclose(action, ys["no_key"][row, base.config.n_obs_steps - 1], atol=1e-5)


def test_keyed_policy_in_a_loop_is_lerobots_own_and_prop_evals(bundle, sealed, work, tmp_path, monkeypatch):
    """KeyedPolicy in a loop of one's own (issue 28), with Diffusion's observation history and noise:
    no key is LeRobot's own select_action between the processors (sealed: on the original folder),
    each call's noise seeded as prop eval seeds it; the key is what prop eval acts; reset() restarts
    the queues."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    from prop_cli.run.policy import KeyedPolicy

    for path, folder in ((bundle, bundle / "lerobot"), (sealed, work / "diffusion")):
        ep = loop.eval_episodes(path, task.ENV_ID, task.OBS_MAP, work / "k.bin", tmp_path, monkeypatch,
                                max_steps=12, noise_seed=3)  # fmt: skip
        seed, b = ep["seed"], load_bundle(path)
        lerobot = DiffusionPolicy.from_pretrained(str(folder))
        pre, post = make_pre_post_processors(lerobot.config, pretrained_path=str(folder))
        own = loop.lerobot_replay(lerobot, pre, post, ep["no_key"], task.OBS_MAP, seed, noise_seed=3)
        no_key = loop.replay(KeyedPolicy(b, noise_seed=3), ep["no_key"], task.OBS_MAP, seed)
        assert np.array_equal(no_key, own) and np.array_equal(no_key, np.stack(ep["no_key"]["actions"]))
        assert not np.allclose(loop.replay(KeyedPolicy(b), ep["no_key"], task.OBS_MAP, seed), own, atol=1e-3)
        user = KeyedPolicy(b, key(), noise_seed=3)
        keyed = loop.replay(user, ep["user_key"], task.OBS_MAP, seed)
        assert np.array_equal(keyed, np.stack(ep["user_key"]["actions"]))
        loop.check_reset_restarts_the_queue(user, ep["user_key"], task.OBS_MAP, seed)


def test_fallback_pool_holds_the_originals_denoiser_on_identical_inputs(bundle, work):
    from prop_adapters.lerobot.policy import FALLBACK_DRAWS

    b = load_bundle(bundle)
    policy = b.loaded.policy
    batch = policy.batches(load_data(work / "general"), "--data")
    obs = {k: batch[k][:6] for k in policy.input_features}
    assert obs["observation.state"].shape == (6, 2, 6)  # n_obs_steps frames per row
    original = load_checkpoint(work / "diffusion").policy
    chunks = batch["action"][:6]
    pools = [policy.fallback_pool(obs, chunks, original, torch.Generator().manual_seed(0)) for _ in range(2)]
    (rows, targets), (rows2, targets2) = pools
    assert len(targets) == 6 * FALLBACK_DRAWS and torch.equal(rows["x_t"], rows2["x_t"])
    assert torch.equal(targets, targets2) and len(set(rows["t"].tolist())) > 1
    # Each target is the original's denoiser on that row's own (observation, x_t, t), row by row.
    cond = original.model._prepare_global_conditioning({k: rows[k][3:4] for k in policy.input_features})
    with torch.no_grad():
        one = original.model.unet(rows["x_t"][3:4], rows["t"][3:4], global_cond=cond)
    assert torch.allclose(one, targets[3:4], atol=1e-5)
    # The bundle's base is fine-tuned gently (base_lr_scale): its denoiser stays near the original's.
    with torch.no_grad():
        base_out = policy.fallback_output(rows)
    assert policy.fallback_distance(base_out, targets).mean() < 0.25 * targets.pow(2).mean()


def test_attack_audits_with_the_original_as_control_on_the_same_noise(bundle, work):
    s = AuditSettings(probes=["null", "random", "hamming"], hamming=[1], per_distance=4, random=8,
                      samples=1000, noise_seed=3)  # fmt: skip
    original = str(work / "diffusion")
    report = api.audit_bundle(bundle, work / "user", s, key_files=[work / "k.bin"], original=original)
    assert report["settings"]["noise_seed"] == 3
    names = {g["name"]: g for g in report["groups"]}
    assert {"null", "random", "hamming 1"} <= set(names)
    assert all(g["control"]["available"] for g in names.values())


def test_sealed_diffusion_runs_the_original_without_its_key(sealed, work):
    from prop_cli.run.policy import WrongKeyWarning, run_policy

    b = load_bundle(sealed)
    assert b.is_sealed and json.loads((sealed / "manifest.json").read_text())["model"]["type"] == "diffusion"
    data = load_data(work / "user")
    orig = load_checkpoint(work / "diffusion").policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        original = orig.post(orig.chunk({k: batch[k] for k in orig.input_features})).numpy()
    assert np.array_equal(run_policy(b, data, None), original)
    with pytest.warns(WrongKeyWarning):
        assert np.array_equal(run_policy(b, data, key(2), allow_unenrolled=True), original)
    assert not np.allclose(run_policy(b, data, key()), original, atol=1e-4)
    # The audit of a sealed Diffusion bundle: its key rows are the original's chunks from the same noise.
    s = AuditSettings(probes=["null", "random"], random=4, samples=1000, noise_seed=2)
    report = api.audit_bundle(sealed, work / "user", s, key_files=[work / "k.bin"],
                              original=str(work / "diffusion"))  # fmt: skip
    rows = {g["name"]: g for g in report["groups"]}
    assert rows["null"]["leakage"]["worst"] == 0 and rows["random"]["leakage"]["worst"] == 0


def test_eval_pairs_the_noise_across_conditions(sealed, work):
    settings = EvalSettings(episodes=2, random_keys=1, neighbours=0, episodes_per_key=1, max_steps=10)
    report = api.eval_bundle(
        sealed, task.ENV_ID, settings, obs_map=task.OBS_MAP, metric=task.METRIC,
        original=str(work / "diffusion"), key_file=None,
    )  # fmt: skip
    c = report["conditions"]
    # Sealed, no key: the original's exact actions from the same noise, so the same episodes.
    assert c["no_key"]["metric"] == c["original"]["metric"]
    assert c["no_key"]["success"] == c["original"]["success"]


def test_camera_images_personalize_run_and_roll_out(tmp_path_factory, cli):
    """The rendered camera (32 x 32 RGB, dtype image) as an input: recorded, personalized, run (no key:
    LeRobot's own action on the same image and noise) and rolled out in the camera task."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    d = tmp_path_factory.mktemp("camera")
    task.record(d / "general", 2, 0, np.zeros(3, np.float32), camera=True)
    task.record(d / "user", 2, 50_000, task.USER_OFFSET, camera=True)
    task.train_base(d / "general", d / "diffusion", steps=2, kind="diffusion", camera=True)
    cfg = PersonalizeConfig.of(**(TINY | {"steps": 3}))
    api.personalize_checkpoint(
        str(d / "diffusion"), [(d / "user", KeySource(key(), "file"))], d / "b", cfg, general=d / "general"
    )
    data = load_data(d / "user")
    assert data.x[task.CAMERA].shape == (len(data), 3, task.IMAGE, task.IMAGE)
    r = cli("run", d / "b", "--input", d / "user", "--output", d / "y.npy", "--noise-seed", 5)
    assert r.code == 0, r.err
    y = np.load(d / "y.npy")
    base = DiffusionPolicy.from_pretrained(str(d / "b" / "lerobot")).eval()
    pre, post = make_pre_post_processors(base.config, pretrained_path=str(d / "b" / "lerobot"))
    obs = {k: torch.from_numpy(data.x[k][:1]) for k in (*STATE_KEYS, task.CAMERA)}
    torch.manual_seed(5)
    with torch.no_grad():
        action = post(base.select_action(pre(obs)))[0].numpy()
    assert np.allclose(action, y[0, base.config.n_obs_steps - 1], atol=1e-5)
    few = EvalSettings(episodes=1, random_keys=1, neighbours=0, episodes_per_key=1, max_steps=5)
    report = api.eval_bundle(d / "b", task.CAMERA_ENV_ID, few, obs_map=task.CAMERA_OBS_MAP, key_file=None)
    assert report["conditions"]["no_key"]["episodes"] == 1
    # The audit takes the camera frames in its flat rows; sealed, a wrong key runs the original exactly.
    path = d / "k.bin"
    path.write_bytes(np.packbits(key()).tobytes())
    path.chmod(0o600)
    s = AuditSettings(probes=["null", "random"], random=2, samples=1000)
    audit = api.audit_bundle(d / "b", d / "user", s, key_files=[path], original=str(d / "diffusion"))
    assert {"null", "random"} <= {g["name"] for g in audit["groups"]}
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 3}))
    api.personalize_checkpoint(str(d / "diffusion"), [(d / "user", KeySource(key(), "file"))], d / "s", cfg)
    from prop_cli.run.policy import WrongKeyWarning, run_policy

    orig = load_checkpoint(d / "diffusion").policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        original = orig.post(orig.chunk({k: batch[k] for k in orig.row_shapes})).numpy()
    sealed = load_bundle(d / "s")
    assert np.array_equal(run_policy(sealed, data, None), original)
    with pytest.warns(WrongKeyWarning):
        assert np.array_equal(run_policy(sealed, data, key(2), allow_unenrolled=True), original)


def recorded(work, out, times: str) -> bool:
    """Whether a 2-step personalize with --fallback-times ``times`` records it once in its manifest."""
    cfg = PersonalizeConfig.of(**(TINY | {"steps": 2, "fallback_times": times}))
    api.personalize_checkpoint(str(work / "diffusion"), [(work / "user", KeySource(key(), "file"))], out, cfg,
                               general=work / "general")  # fmt: skip
    manifest = json.loads((out / "manifest.json").read_text())
    return json.dumps(manifest).count(f'"fallback_times": "{times}"') == 1


def test_fallback_times_sampler_draws_only_the_samplers_timesteps_and_is_recorded(work, tmp_path):
    """--fallback-times sampler (issue 43): every fallback row sits at a timestep LeRobot's sampler
    visits in closed loop (num_inference_steps of the training range), the default draws over the whole
    range, and the setting is recorded in the bundle's manifest."""
    policy = load_checkpoint(work / "diffusion").policy
    model = policy.model
    model.noise_scheduler.set_timesteps(model.num_inference_steps)  # what conditional_sample runs
    visited = set(model.noise_scheduler.timesteps.tolist())
    assert len(visited) == model.num_inference_steps < model.noise_scheduler.config.num_train_timesteps
    uniform = policy.fallback_noise(64, torch.Generator().manual_seed(0))
    assert not set(uniform["t"].tolist()) <= visited
    policy.fallback_times = "sampler"
    drawn = policy.fallback_noise(64, torch.Generator().manual_seed(0))
    assert set(drawn["t"].tolist()) <= visited and len(set(drawn["t"].tolist())) > 1
    assert drawn["eps"].shape == uniform["eps"].shape
    assert recorded(work, tmp_path / "bundle", "sampler")


def test_fallback_times_trajectory_rows_sit_on_the_originals_sampler_states(work, tmp_path, cli, monkeypatch):
    """--fallback-times trajectory (issue 43): a fallback row's x_t is the original's own sampler state at
    the row's step (the sampler run on the row's frame from the row's own prior and step noise), its t
    the timestep the sampler is at there: the last state stepped once more is LeRobot's own
    ``conditional_sample`` on the same noise; a row's state does not depend on its batch; the pool keeps
    those states and the original's U-Net on them as targets; the setting is recorded in the manifest,
    and a policy whose sampler prop cannot follow refuses it in one line."""
    import copy

    from prop_adapters.base import FRAME
    from prop_adapters.lerobot.diffusion import UNet
    from prop_cli.train.policy import FallbackPool

    policy = load_checkpoint(work / "diffusion").policy
    model = policy.model
    policy.fallback_times = "trajectory"
    drawn = policy.fallback_noise(4, torch.Generator().manual_seed(0))
    visited = policy.denoiser.sampler_timesteps()
    assert torch.equal(drawn["t"], visited[drawn["k"]]) and len(set(drawn["k"].tolist())) > 2
    batch = policy.batches(load_data(work / "general"), "--data")
    obs = {k: batch[k][drawn[FRAME]] for k in policy.input_features}
    noise = {k: v for k, v in drawn.items() if k != FRAME}
    with torch.no_grad():
        states = policy.fallback_states(obs, noise)
        at0 = drawn["k"] == 0
        assert torch.equal(states[at0], noise["eps"][at0])  # step 0: the prior itself
        assert not torch.allclose(states[~at0], noise["eps"][~at0], atol=1e-2)
        alone = {k: v[5:6] for k, v in obs.items()}, {k: v[5:6] for k, v in noise.items()}
        one = policy.fallback_states(*alone)
        assert torch.allclose(one, states[5:6], atol=1e-6)  # alone or in a batch: the same state
        # Every row at the last step, then that step (t = 0: DDPM draws no noise there): LeRobot's sample.
        last = noise | {"k": torch.full_like(noise["k"], len(visited) - 1)}
        x = policy.fallback_states(obs, last)
        cond = model._prepare_global_conditioning(policy.denoiser._observations(obs))
        sched = copy.deepcopy(model.noise_scheduler)
        sched.set_timesteps(model.num_inference_steps)
        assert int(sched.timesteps[-1]) == 0
        at0 = torch.zeros(len(x), dtype=torch.long)
        x = sched.step(model.unet(x, at0, global_cond=cond), 0, x).prev_sample
        gens = [torch.Generator().manual_seed(int(s)) for s in noise["seed"]]
        ref = model.conditional_sample(len(x), global_cond=cond, generator=gens, noise=noise["eps"].clone())
        assert torch.allclose(x, ref, atol=1e-5)
    # The pool: x_t the original's sampler state for the row, the target the original's U-Net there.
    original = load_checkpoint(work / "diffusion").policy
    frames = {k: batch[k] for k in [*policy.row_shapes, "episode_index"]}
    pool = FallbackPool(policy, original, frames, torch.Generator().manual_seed(0), 16)
    idx = torch.tensor([0, 3, 5, 17])
    fb_rows, targets = pool.take(idx)
    pick = {k: v[idx] for k, v in pool.noise.items()}
    with torch.no_grad():
        want = original.fallback_states({k: frames[k][pool.frame[idx]] for k in policy.input_features}, pick)
        assert torch.allclose(fb_rows["x_t"], want, atol=1e-6) and torch.equal(fb_rows["t"], pick["t"])
        assert torch.allclose(original.fallback_output(fb_rows), targets, atol=1e-5)
    assert recorded(work, tmp_path / "bundle", "trajectory")
    monkeypatch.setattr(UNet, "follows_sampler", False)  # as a sampler prop cannot follow (flow matching)
    r = cli("personalize", work / "diffusion", "--data", work / "user", "--key-file", work / "k.bin",
            "--out", tmp_path / "refused", "--steps", "1", "--fallback-times", "trajectory")  # fmt: skip
    assert r.code != 0 and "Traceback" not in r.err
    assert r.err.startswith("prop: error: --fallback-times trajectory") and "uniform or sampler" in r.err
    assert not (tmp_path / "refused").exists()
