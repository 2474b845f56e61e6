"""LeRobot SmolVLA under prop (pytest -m lerobot; scripts/test-lerobot.sh).

A tiny SmolVLA built here (examples/smolvla_tiny.py: a 2-layer SmolVLM with random weights, a tokenizer
built with `tokenizers`, SmolVLM's image processor; nothing downloaded) on the MuJoCo reach's camera task
(32 x 32 frames, state, the task text as instruction). What differs from ACT and Diffusion is tested:
the instruction as tokens in every row, the VLM folder the bundle carries, the flow-matching expert as
the fallback target, LeRobot's own sampler as the deployed chunk.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytest.importorskip("num2words")  # SmolVLM's processor needs it (scripts/setup-lerobot.sh installs it)
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from prop_adapters import load_checkpoint  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import AuditSettings, EvalSettings, PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from prop_cli.train.policy import chunks  # noqa: E402
from tests.adapters.shares import buffers_as_built, memo_terms  # noqa: E402
from tests.lerobot_bases import smolvla_base  # noqa: E402

TINY = dict(steps=6, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=2, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
INPUTS = ("observation.state", task.CAMERA)


def key(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("smolvla")
    smolvla_base(d)
    path = d / "k.bin"
    path.write_bytes(np.packbits(key()).tobytes())
    path.chmod(0o600)
    return d


@pytest.fixture(scope="module")
def bundle(work):
    out = work / "bundle"
    api.personalize_checkpoint(
        str(work / "smolvla"), [(work / "user", KeySource(key(), "file"))], out, PersonalizeConfig.of(**TINY),
        general=work / "general",
    )  # fmt: skip
    return out


@pytest.fixture(scope="module")
def sealed(work):
    out = work / "sealed"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 10}))
    api.personalize_checkpoint(str(work / "smolvla"), [(work / "user", KeySource(key(), "file"))], out, cfg)
    return out


def lerobot_base(bundle):
    """The bundle's base in LeRobot itself, its VLM from the bundle's vlm/: (policy, pre, post)."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    vlm = bundle / "lerobot" / "vlm"
    cfg = PreTrainedConfig.from_pretrained(str(bundle / "lerobot"))
    cfg.vlm_model_name = str(vlm)
    base = SmolVLAPolicy.from_pretrained(str(bundle / "lerobot"), config=cfg).eval()
    pre, post = make_pre_post_processors(
        base.config, pretrained_path=str(bundle / "lerobot"),
        preprocessor_overrides={"tokenizer_processor": {"tokenizer_name": str(vlm)}},
    )  # fmt: skip
    return base, pre, post


def test_lerobots_peft_targets_are_keyed_by_default(work, cli):
    info = api.inspect_checkpoint(str(work / "smolvla"))
    assert info["model"]["type"] == "smolvla" and info["model"]["chunk_size"] == 10
    keyed = {x["name"] for x in info["layers"] if x["keyed"]}
    assert "model.action_out_proj" in keyed and "model.state_proj" in keyed
    assert "model.vlm_with_expert.lm_expert.layers.0.self_attn.q_proj" in keyed
    assert not any(".k_proj" in n or "text_model" in n or "vision_model" in n for n in keyed)
    assert 0 < info["keyed_share"] < 1
    r = cli("inspect", work / "smolvla")
    assert r.code == 0 and "smolvla" in r.out


def test_rows_carry_the_instruction_as_tokens_padded_to_one_width(work):
    policy = load_checkpoint(work / "smolvla").policy
    data = load_data(work / "user")
    assert set(data.x["task"]) == {"reach the target"}
    batch = policy.batches(data, "--data")
    tokens, mask = batch["observation.language.tokens"], batch["observation.language.attention_mask"]
    assert tokens.shape == mask.shape == (len(data), 16) and mask.dtype == torch.bool
    assert mask[:, 0].all() and not mask[:, -1].any()  # padded to tokenizer_max_length, masked
    no_task = load_data(work / "user")
    del no_task.x["task"]
    with pytest.raises(Exception, match="no task text per frame"):
        policy.batches(no_task, "--data")


def test_bundle_carries_the_vlm_files_and_its_base_loads_in_lerobot(bundle, work, tmp_path, cli):

    vlm = bundle / "lerobot" / "vlm"
    assert (vlm / "config.json").is_file() and (vlm / "tokenizer.json").is_file()
    assert not list(vlm.glob("*.safetensors"))  # the VLM's weights are the policy's own
    # The VLM folder the base was trained with is gone: the bundle alone must do.
    moved = work / "vlm-elsewhere"
    (work / "vlm").rename(moved)
    try:
        ys = {}
        runs = (("no_key", 7, []), ("again", 7, []), ("key", 7, ["--key-file", work / "k.bin"]))
        for name, seed, extra in runs:
            r = cli("run", bundle, "--input", work / "user", "--output", tmp_path / f"{name}.npy",
                    "--noise-seed", seed, *extra)  # fmt: skip
            assert r.code == 0, r.err
            ys[name] = np.load(tmp_path / f"{name}.npy")
    finally:
        moved.rename(work / "vlm")
    data = load_data(work / "user")
    assert ys["no_key"].shape == (len(data), 10, 3)
    assert np.array_equal(ys["no_key"], ys["again"])
    assert not np.allclose(ys["no_key"], ys["key"], atol=1e-3)
    # The base in LeRobot itself (its VLM from the bundle's vlm/): no key is its own select_action.
    base, pre, post = lerobot_base(bundle)
    for row in (0, 17):
        base.reset()
        obs = {k: torch.from_numpy(data.x[k][row : row + 1]) for k in INPUTS}
        obs["task"] = str(data.x["task"][row])
        torch.manual_seed(7)
        with torch.no_grad():
            action = post(base.select_action(pre(obs)))[0].numpy()
        assert np.allclose(action, ys["no_key"][row, 0], atol=1e-5)


def test_keyed_policy_takes_the_instruction_as_lerobot_does(bundle, work):
    """KeyedPolicy on SmolVLA (issue 28): the instruction given at construction or as the observation's
    `task` entry (as LeRobot's preprocessor takes it) gives LeRobot's own select_action without a key,
    each call's noise seeded as prop eval seeds it; no instruction at all is one PropError line."""
    from prop_adapters.lerobot.policy import call_seed
    from prop_cli.errors import PropError
    from prop_cli.run.policy import KeyedPolicy

    task_text = "reach the target"
    base, pre, post = lerobot_base(bundle)
    data = load_data(work / "user")
    frames = [{k: data.x[k][row] for k in INPUTS} for row in range(7)]  # more than n_action_steps
    own = []
    for i, frame in enumerate(frames):
        torch.manual_seed(call_seed(7, 0, i))
        with torch.no_grad():
            x = {k: torch.from_numpy(v) for k, v in frame.items()} | {"task": task_text}
            own.append(post(base.select_action(pre(x)))[0].numpy())
    b = load_bundle(bundle)
    by_argument = KeyedPolicy(b, instruction=task_text, noise_seed=7)
    assert np.array_equal(np.stack([by_argument.select_action(f) for f in frames]), np.stack(own))
    by_task = KeyedPolicy(b, noise_seed=7)  # one no-key policy at a time: they share the base's queues
    assert np.array_equal(np.stack([by_task.select_action(f | {"task": task_text}) for f in frames]),
                          np.stack(own))  # fmt: skip
    with pytest.raises(PropError, match="instruction") as e:
        KeyedPolicy(b).select_action(frames[0])
    assert "\n" not in str(e.value)


def test_fallback_targets_are_the_originals_velocity_on_identical_inputs(bundle, work):
    from prop_adapters.lerobot.policy import FALLBACK_DRAWS

    policy = load_bundle(bundle).loaded.policy
    batch = policy.batches(load_data(work / "general"), "--data")
    obs = {k: batch[k][:4] for k in policy.row_shapes}
    original = load_checkpoint(work / "smolvla").policy
    rows, targets = policy.fallback_pool(obs, batch["action"][:4], original, torch.Generator().manual_seed(0))
    assert len(targets) == 4 * FALLBACK_DRAWS and targets.shape[1:] == (10, 4)
    assert ((rows["t"] > 0) & (rows["t"] <= 1)).all() and len(set(rows["t"].tolist())) > 1
    with torch.no_grad():
        one = original.fallback_output({k: v[5:6] for k, v in rows.items()})
    assert torch.allclose(one, targets[5:6], atol=1e-5)
    # One forward for both terms gives the same fallback output as its own forward.
    user = {k: batch[k][:3] for k in [*policy.row_shapes, "action"]}
    with torch.no_grad():
        loss, joint = original.joint_terms(user, {k: v[:5] for k, v in rows.items()})
    assert loss.ndim == 0 and torch.allclose(joint, targets[:5], atol=1e-4)


def test_a_steps_shares_on_two_processes_add_up_to_the_step(work):
    """SmolVLA's joint forward (user loss and fallback velocity) split between two processes' rows: its
    noise and Beta time drawn per row, its loss (a mean over the chunk steps that are not padding)
    weighted by each share's valid steps; the sum is the step's loss and gradient."""
    from prop_cli.train.policy import chunks, rows
    from tests.adapters.shares import split_matches_whole

    policy = load_checkpoint(work / "smolvla").policy
    batch = policy.batches(load_data(work / "user"), "--data")
    ends = torch.nonzero(batch["action_is_pad"].any(1)).flatten()
    user = rows(batch, torch.cat([torch.arange(3), ends[-3:]]))
    frames = rows(batch, torch.arange(2))
    fb, _ = policy.fallback_pool(frames, chunks(policy, frames), policy, torch.Generator().manual_seed(0))
    user.pop("episode_index")
    assert policy.joins_terms
    split_matches_whole(policy, user, rows(fb, torch.arange(4)), cut=3)


def test_the_original_shares_what_does_not_train_and_the_pool_fills_as_steps_draw(work):
    from prop_cli.train import User
    from prop_cli.train.policy import FallbackPool, PolicyTrainer

    loaded = load_checkpoint(work / "smolvla")
    own = {n for n, p in loaded.module.named_parameters() if p.requires_grad}  # LeRobot's own freezing
    assert own and len(own) < len(list(loaded.module.parameters()))
    cfg = PersonalizeConfig.of(**TINY)
    t = PolicyTrainer(loaded, [User(load_data(work / "user"), key())], cfg.train, cfg.mode, None)
    assert {n for n, p in t.module.named_parameters() if p.requires_grad} == own  # what LeRobot trains
    twin = dict(t.original.named_parameters())
    for n, p in t.module.named_parameters():  # one copy of every frozen tensor; the trained ones apart
        assert (twin[n] is p) == (n not in own) and torch.equal(twin[n], p)
    pool = t.fallback
    # Before a step, only the rows the per-row-draw probe ran (row_noise: rows 0-2, frame 0).
    filled = int(pool._have_target.sum())
    assert isinstance(pool, FallbackPool) and filled <= 3 and not pool._have_target[3:].any()
    rows, targets = pool.take(torch.tensor([9, 3, 9]))
    assert pool._have_target.sum() == filled + 2 and pool._have_chunk.sum() == 2  # rows 3, 9; frames 0, 1
    # The same rows and targets as the pool drawn whole before the steps (as prop did before).
    whole, eager = t.policy.fallback_pool(
        t.fb, chunks(t.original_policy, t.fb), t.original_policy, torch.Generator().manual_seed(0)
    )
    assert torch.equal(rows["t"], whole["t"][[9, 3, 9]])
    assert torch.allclose(targets, eager[[9, 3, 9]], atol=1e-5)


def test_under_bf16_frozen_weights_step_as_bf16_and_come_back_exactly(work):
    from prop_cli.train import User
    from prop_cli.train.policy import PolicyTrainer

    loaded = load_checkpoint(work / "smolvla")
    before = {n: p.detach().clone() for n, p in loaded.module.named_parameters() if not p.requires_grad}
    cfg = PersonalizeConfig.of(**(TINY | {"precision": "bf16"}))
    t = PolicyTrainer(loaded, [User(load_data(work / "user"), key())], cfg.train, cfg.mode, None)
    params = dict(t.module.named_parameters())
    assert before and all(params[n].dtype == torch.bfloat16 for n in before)  # frozen: bf16, shared
    assert all(p.dtype == torch.float32 for n, p in params.items() if n not in before)  # trained: fp32
    assert all(dict(t.original.named_parameters())[n] is params[n] for n in before)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        losses = t.step()
    t.finish()  # the report and the bundle see the checkpoint's own frozen weights again
    assert np.isfinite(list(losses.values())).all() and t.optim is None
    assert all(params[n].dtype == torch.float32 and torch.equal(params[n], before[n]) for n in before)


def test_each_frames_image_embedding_is_computed_once_within_the_memo(work):
    policy = load_checkpoint(work / "smolvla").policy
    batch = policy.batches(load_data(work / "user"), "--data")
    frames = {k: batch[k][[0, 1, 0, 2, 1]] for k in policy.row_shapes}
    vwe = policy.model.vlm_with_expert
    cls, real, calls = type(vwe), type(vwe).embed_image, []
    cls.embed_image = lambda self, image: calls.append(len(image)) or real(self, image)
    try:
        with torch.no_grad():
            plain = policy.chunk(frames)
            with policy.memo():  # the tiny policy trains its vision path: the memo stays out of the way
                assert torch.equal(policy.chunk(frames), plain) and calls == [5, 5]
            vision = [p for p in vwe.parameters() if p.requires_grad and "lm_expert" not in str(p.shape)]
            vwe.get_vlm_model().vision_model.requires_grad_(False)
            vwe.get_vlm_model().connector.requires_grad_(False)
            with policy.memo():  # frozen: each distinct frame's embedding once, then from the memo
                once = policy.chunk(frames)
                again = policy.chunk({k: v[[3, 1]] for k, v in frames.items()})
                assert calls == [5, 5, 3]
                hook = vwe.get_vlm_model().vision_model.register_forward_pre_hook(lambda m, a: None)
                policy.chunk({k: v[[3]] for k, v in frames.items()})  # a hook there (a key): no memo
                hook.remove()
                assert calls == [5, 5, 3, 1]
    finally:
        cls.embed_image = real
    assert vision and torch.allclose(once, plain, atol=1e-5)
    assert torch.allclose(again, plain[[3, 1]], atol=1e-5)


def test_built_without_random_init_its_buffers_are_a_normal_builds(work):
    """The policy is built without random initialisation (every weight is then loaded): what is not
    loaded (non-persistent buffers: rotary frequencies) is what a normal build computes."""
    module = load_checkpoint(work / "smolvla").module
    buffers_as_built(module)


def test_the_prefix_blocks_keys_and_values_are_computed_once_and_change_nothing(work, monkeypatch):
    """Within the memo, with the VLM frozen and unkeyed (LeRobot's train_expert_only), each frame's image
    and language tokens go through the VLM once (their keys and values kept), and a forward runs the state
    token and the expert only: its chunk, terms and gradients are LeRobot's own to float rounding. A VLM
    that trains, or a hook (a key) on it, turns the memo off."""
    from prop_adapters.lerobot import smolvla
    from prop_cli.train.policy import rows

    policy = load_checkpoint(work / "smolvla").policy
    batch = policy.batches(load_data(work / "user"), "--data")
    frames = rows(batch, torch.tensor([0, 1, 0, 2]))
    fb, _ = policy.fallback_pool(rows(batch, torch.arange(2)), batch["action"][:2], policy,
                                 torch.Generator().manual_seed(0))  # fmt: skip
    fb = rows(fb, torch.arange(5))
    vwe = policy.model.vlm_with_expert
    ran = []
    real = smolvla.after_block
    monkeypatch.setattr(smolvla, "after_block", lambda *a: ran.append(len(a[3])) or real(*a))

    def memo_runs():
        with policy.memo():
            out = memo_terms(policy, frames, fb)
            assert torch.equal(policy.chunk(frames), out[0])  # the second time from the memo: the same
            return out

    with policy.memo():  # the tiny policy trains its VLM: the memo stays out of the way
        policy.chunk(frames)
    assert ran == []
    vwe.vlm.requires_grad_(False)  # train_expert_only
    plain = memo_terms(policy, frames, fb)
    assert ran == []  # outside the memo: LeRobot's forward as it is
    memo = memo_runs()
    assert len(ran) == 3  # the chunk's prefix fill, the joint forward, the chunk again
    for a, b in zip(plain[:3], memo[:3]):
        assert torch.allclose(a, b, atol=1e-5)
    assert plain[3].keys() == memo[3].keys() and plain[3]
    assert all(torch.allclose(plain[3][n], memo[3][n], atol=1e-5) for n in plain[3])
    ran.clear()
    layer = vwe.get_vlm_model().text_model.layers[0].self_attn.q_proj
    hook = layer.register_forward_hook(lambda m, a, o: o)  # a key on the VLM: its tokens change with it
    try:
        memo_runs()
    finally:
        hook.remove()
    layer.weight.requires_grad_(True)  # a VLM layer that trains
    memo_runs()
    assert ran == []


def test_attack_audits_with_the_original_as_control(bundle, work):
    s = AuditSettings(probes=["null", "random", "hamming"], hamming=[1], per_distance=2, random=4,
                      samples=1000, noise_seed=3)  # fmt: skip
    report = api.audit_bundle(
        bundle, work / "user", s, key_files=[work / "k.bin"], original=str(work / "smolvla")
    )
    names = {g["name"]: g for g in report["groups"]}
    assert {"null", "random", "hamming 1"} <= set(names)
    assert all(g["control"]["available"] for g in names.values())


def test_sealed_smolvla_runs_the_original_without_its_key_and_audits(sealed, work):
    from prop_cli.run.policy import WrongKeyWarning, run_policy

    b = load_bundle(sealed)
    assert b.is_sealed and json.loads((sealed / "manifest.json").read_text())["model"]["type"] == "smolvla"
    data = load_data(work / "user")
    orig = load_checkpoint(work / "smolvla").policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        original = orig.post(orig.chunk({k: batch[k] for k in orig.row_shapes})).numpy()
    assert np.array_equal(run_policy(b, data, None), original)
    with pytest.warns(WrongKeyWarning):
        assert np.array_equal(run_policy(b, data, key(2), allow_unenrolled=True), original)
    assert not np.allclose(run_policy(b, data, key()), original, atol=1e-4)
    s = AuditSettings(probes=["null", "random"], random=4, samples=1000)
    report = api.audit_bundle(
        sealed, work / "user", s, key_files=[work / "k.bin"], original=str(work / "smolvla")
    )
    assert {"null", "random"} <= {g["name"] for g in report["groups"]}


def test_eval_needs_an_instruction_and_pairs_the_noise(sealed, work):
    few = EvalSettings(episodes=1, random_keys=1, neighbours=0, episodes_per_key=1, max_steps=6)
    with pytest.raises(Exception, match="--instruction"):
        api.eval_bundle(sealed, task.CAMERA_ENV_ID, few, obs_map=task.CAMERA_OBS_MAP, key_file=None)
    settings = EvalSettings(episodes=2, random_keys=1, neighbours=0, episodes_per_key=1, max_steps=6,
                            instruction="reach the target")  # fmt: skip
    report = api.eval_bundle(
        sealed, task.CAMERA_ENV_ID, settings, obs_map=task.CAMERA_OBS_MAP, metric=task.METRIC,
        original=str(work / "smolvla"), key_file=work / "k.bin",
    )  # fmt: skip
    c = report["conditions"]
    assert c["no_key"]["metric"] == c["original"]["metric"]  # sealed, no key: the original's actions


def test_a_sealed_peft_payload_loads_through_lerobots_peft_path(work, tmp_path, cli):
    """The opened payload as a peft LoRA adapter on LeRobot's SmolVLA (its default PEFT targets): the
    action equals `prop run --key-file` with the same noise seed."""
    pytest.importorskip("peft")
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from peft import PeftConfig, PeftModel

    r = cli("personalize", work / "smolvla", "--data", work / "user", "--key-file", work / "k.bin",
            "--out", tmp_path / "s", "--seal", "--payload", "peft-lora", "--steps", "8",
            "--user-rows", "8")  # fmt: skip
    assert r.code == 0, r.err
    r = cli("export", tmp_path / "s", "--peft", tmp_path / "adapter", "--key-file", work / "k.bin")
    assert r.code == 0, r.err
    r = cli("run", tmp_path / "s", "--input", work / "user", "--output", tmp_path / "y.npy",
            "--key-file", work / "k.bin", "--noise-seed", "4")  # fmt: skip
    assert r.code == 0, r.err
    y = np.load(tmp_path / "y.npy")
    config = PeftConfig.from_pretrained(str(tmp_path / "adapter"))
    base = config.base_model_name_or_path
    assert base == str((tmp_path / "s" / "lerobot").resolve())
    assert "lm_expert" in str(config.target_modules)  # a regex over the keyed layers
    cfg = PreTrainedConfig.from_pretrained(base)
    cfg.vlm_model_name = str(tmp_path / "s" / "lerobot" / "vlm")
    policy = SmolVLAPolicy.from_pretrained(base, config=cfg)
    policy = PeftModel.from_pretrained(policy, str(tmp_path / "adapter"), config=config).eval()
    pre, post = make_pre_post_processors(
        policy.config, pretrained_path=base,
        preprocessor_overrides={"tokenizer_processor": {"tokenizer_name": cfg.vlm_model_name}},
    )  # fmt: skip
    data = load_data(work / "user")
    obs = {k: torch.from_numpy(data.x[k][:1]) for k in INPUTS}
    obs["task"] = str(data.x["task"][0])
    policy.reset()
    torch.manual_seed(4)
    with torch.no_grad():
        action = post(policy.select_action(pre(obs)))[0].numpy()
    assert np.allclose(action, y[0, 0], atol=1e-5)


def test_a_swapped_tokenizer_in_a_sealed_bundle_is_refused_with_the_key(sealed, work, tmp_path):
    """Whoever can write the files swaps two words of the carried tokenizer (so the instruction maps to
    other tokens) and re-hashes the manifest: the user's record opens, but the bundle changed since the
    key was enrolled, so nothing runs under that key."""
    import shutil

    from prop_cli import constants as C
    from prop_cli.bundle.manifest import stamp
    from prop_cli.errors import PropError
    from prop_cli.files import dump_json, sha256_file
    from prop_cli.run.policy import run_policy

    planted = tmp_path / "s"
    shutil.copytree(sealed, planted)
    m = json.loads((planted / C.MANIFEST).read_text())
    assert "lerobot/vlm/tokenizer.json" in m[C.M_FILES]  # listed, so it is part of what a key enrolled
    f = planted / "lerobot" / "vlm" / "tokenizer.json"
    doc = json.loads(f.read_text())
    vocab = doc["model"]["vocab"]
    vocab["reach"], vocab["goal"] = vocab["goal"], vocab["reach"]
    f.write_text(json.dumps(doc))
    m[C.M_FILES] = {n: sha256_file(planted / n) for n in m[C.M_FILES]}
    (planted / C.MANIFEST).write_text(dump_json(stamp(m)))
    b = load_bundle(planted)
    data = load_data(work / "user")
    with pytest.raises(PropError, match="changed since this key was enrolled"):
        run_policy(b, data, key())
    run_policy(b, data, None)  # without a key: the bundle's base, as it now is


@pytest.mark.parametrize("name", ["config.json", "tokenizer_config.json"])
def test_a_vlm_file_naming_code_is_never_imported_and_the_key_refuses(name, sealed, work, tmp_path):
    """Whoever can write the files makes the carried VLM config (or tokenizer config) name a code
    module through transformers' `auto_map`, and re-hashes the manifest: nothing is imported (LeRobot
    and transformers never get trust_remote_code), and the user's key does not run."""
    import shutil
    import sys

    from prop_cli import constants as C
    from prop_cli.bundle.manifest import stamp
    from prop_cli.errors import PropError
    from prop_cli.files import dump_json, sha256_file
    from prop_cli.run.policy import run_policy

    planted = tmp_path / "s"
    shutil.copytree(sealed, planted)
    marker = tmp_path / "pwned"
    (tmp_path / "pwn_vlm.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nclass Anything: pass\n"
    )
    f = planted / "lerobot" / "vlm" / name
    doc = json.loads(f.read_text())
    doc["auto_map"] = {k: "pwn_vlm.Anything" for k in ("AutoConfig", "AutoTokenizer", "AutoProcessor")}
    f.write_text(json.dumps(doc))
    m = json.loads((planted / C.MANIFEST).read_text())
    m[C.M_FILES] = {n: sha256_file(planted / n) for n in m[C.M_FILES]}
    (planted / C.MANIFEST).write_text(dump_json(stamp(m)))
    sys.path.insert(0, str(tmp_path))
    try:
        data = load_data(work / "user")
        try:
            b = load_bundle(planted)
        except PropError:
            b = None  # refused while loading: fine, as long as nothing was imported
        if b is not None:
            with pytest.raises(PropError, match="changed since this key was enrolled"):
                run_policy(b, data, key())
        assert not marker.exists() and "pwn_vlm" not in sys.modules
    finally:
        sys.path.remove(str(tmp_path))


def test_force_replaces_smolvla_bundles_the_vlm_files_are_listed(bundle, sealed):
    """Issue 28: --force replaces only prop's bundles; a SmolVLA bundle's lerobot/vlm/ files are listed."""
    from prop_cli.files import BUNDLE

    assert BUNDLE.recognise(bundle) is None and BUNDLE.recognise(sealed) is None


# ---- issue 31: no prompt that runs code; nothing read from outside the bundle -------------------


def _planted(src, tmp_path, edit) -> object:
    """A copy of bundle ``src`` with ``edit(copy, manifest)`` applied, finished as an attacker would:
    every listed file's sha256 and the manifest digest recomputed with prop's own functions."""
    import shutil

    from prop_cli import constants as C
    from prop_cli.bundle.manifest import stamp
    from prop_cli.files import dump_json, sha256_file

    planted = tmp_path / "planted"
    shutil.copytree(src, planted)
    m = json.loads((planted / C.MANIFEST).read_text())
    edit(planted, m)
    m[C.M_FILES] = {n: sha256_file(planted / n) for n in m[C.M_FILES]}
    (planted / C.MANIFEST).write_text(dump_json(stamp(m)))
    return planted


def _vlm_naming_code(marker, listed: bool):
    """The carried VLM config names a module of the folder through transformers' auto_map (and a model
    type transformers does not know, so it does not fall back on its own class: it asks), and the module
    is dropped beside it, writing ``marker`` when imported; ``listed``: the attacker lists it too."""

    def edit(bundle, m):
        vlm = bundle / "lerobot" / "vlm"
        config = json.loads((vlm / "config.json").read_text())
        config["model_type"] = "pwn_vlm"
        config["auto_map"] = {"AutoConfig": "pwn_vlm.PwnConfig", "AutoProcessor": "pwn_vlm.PwnConfig"}
        (vlm / "config.json").write_text(json.dumps(config))
        (vlm / "pwn_vlm.py").write_text(
            f"open({str(marker)!r}, 'w').close()\n"
            "from transformers import PretrainedConfig\n"
            "class PwnConfig(PretrainedConfig):\n    model_type = 'pwn_vlm'\n"
        )
        if listed:
            m["files"]["lerobot/vlm/pwn_vlm.py"] = ""

    return edit


def _on_a_terminal(args: list, cwd, answer: bytes = b"y\n", timeout: float = 420) -> tuple[int, str]:
    """`prop ARGS` with a pseudo-terminal as its stdin, stdout and stderr, as a user at a terminal runs
    it; a question ending in "[y/N]" is answered ``answer`` (what the attacker hopes the user types).
    Returns the exit code and everything the terminal showed."""
    import os
    import pty
    import select
    import subprocess
    import sys
    import time

    master, slave = pty.openpty()
    env = os.environ | {"HF_HUB_OFFLINE": "1", "HF_MODULES_CACHE": str(cwd / "hf-modules")}
    cmd = [sys.executable, "-c", "from prop_cli.cli.main import main; main()", *map(str, args)]
    proc = subprocess.Popen(cmd, stdin=slave, stdout=slave, stderr=slave, cwd=cwd, env=env,
                            start_new_session=True)  # fmt: skip
    os.close(slave)
    shown, answered, deadline = b"", False, time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 1.0)
            if ready:
                try:
                    chunk = os.read(master, 4096)
                except OSError:  # EIO: the child closed the terminal
                    chunk = b""
                if not chunk and proc.poll() is not None:
                    break
                shown += chunk
                if b"[y/N]" in shown and not answered:
                    os.write(master, answer)
                    answered = True
            elif proc.poll() is not None:
                break
        else:
            proc.kill()
        return proc.wait(), shown.decode(errors="replace").replace("\r\n", "\n")
    finally:
        os.close(master)


@pytest.mark.parametrize("listed", [False, True], ids=["dropped", "listed"])
def test_a_vlm_naming_code_asks_nothing_on_a_terminal_and_runs_nothing(listed, sealed, work, tmp_path):
    """Issue 31, finding 1: on a terminal, transformers asked "Do you wish to run the custom code? [y/N]"
    and a "y" ran the attacker's module. Now the bundle is refused in one line before anything reads
    its VLM files: no question, no code, exit 2."""
    marker = tmp_path / "pwned"
    planted = _planted(sealed, tmp_path, _vlm_naming_code(marker, listed))
    code, shown = _on_a_terminal(["run", planted, "--input", work / "user", "--output", tmp_path / "y.npy"],
                                 tmp_path)  # fmt: skip
    assert "[y/N]" not in shown and "custom code" not in shown, shown
    assert not marker.exists() and not (tmp_path / "y.npy").exists(), shown
    lines = shown.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("prop: error:"), shown
    assert "lerobot/vlm/" in lines[0] and "tampered" in lines[0], shown


def test_vlm_code_is_refused_with_trust_remote_code_too(sealed, work, tmp_path, cli):
    """--trust-remote-code trusts import paths a manifest names, never code carried in a bundle's
    files: prop never writes any, so a bundle holding some was changed."""
    marker = tmp_path / "pwned"
    planted = _planted(sealed, tmp_path, _vlm_naming_code(marker, listed=True))
    for extra in ([], ["--trust-remote-code"]):
        r = cli("run", planted, "--input", work / "user", "--output", tmp_path / "y.npy", *extra)
        assert r.code == 2 and r.err.count("\n") == 1 and "lerobot/vlm/" in r.err, r.err
    assert not marker.exists() and not (tmp_path / "y.npy").exists()


@pytest.mark.parametrize("name", ["tokenizer.model", "generation_config.json", "sub/config.json"])
def test_a_file_the_manifest_does_not_list_beside_the_vlm_is_refused(name, bundle, work, tmp_path, cli):
    """transformers reads whatever files a model folder holds by name: one the manifest does not list
    is refused, naming it, before anything reads the folder."""

    def edit(b, m):
        f = b / "lerobot" / "vlm" / name
        f.parent.mkdir(exist_ok=True)
        f.write_bytes(b"{}")

    planted = _planted(bundle, tmp_path, edit)
    r = cli("run", planted, "--input", work / "user", "--output", tmp_path / "y.npy")
    assert r.code == 2 and r.err.count("\n") == 1, r.err
    assert f"lerobot/vlm/{name} is not listed" in r.err and "tampered" in r.err, r.err


def test_a_bundle_reads_its_vlm_from_itself_only(bundle, work, tmp_path, cli):
    """Without the carried vlm/, the policy's config.json names a VLM folder outside the bundle (the
    attacker's, here the original's): prop reads nothing there."""
    import shutil

    def edit(b, m):
        shutil.rmtree(b / "lerobot" / "vlm")
        m["files"] = {n: d for n, d in m["files"].items() if not n.startswith("lerobot/vlm/")}
        config = json.loads((b / "lerobot" / "config.json").read_text())
        (b / "lerobot" / "config.json").write_text(json.dumps(config | {"vlm_model_name": str(work / "vlm")}))

    planted = _planted(bundle, tmp_path, edit)
    r = cli("run", planted, "--input", work / "user", "--output", tmp_path / "y.npy")
    assert r.code == 2 and r.err.count("\n") == 1 and "vlm/config.json" in r.err, r.err
    assert str(work / "vlm") in r.err and not (tmp_path / "y.npy").exists()


def test_no_prompt_makes_transformers_refuse_without_asking(tmp_path, capsys):
    """The guard behind the checks (``no_prompt``, around every LeRobot load): a folder naming code
    reaching transformers anyway gets its refusal, with no question printed and nothing imported."""
    import builtins

    from transformers import AutoConfig

    from prop_adapters.base import no_prompt

    before = builtins.input
    marker = tmp_path / "pwned"
    folder = tmp_path / "vlm"
    folder.mkdir()
    config = {"model_type": "pwn_vlm", "auto_map": {"AutoConfig": "pwn_vlm.PwnConfig"}}
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "pwn_vlm.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    with no_prompt(), pytest.raises(ValueError, match="trust_remote_code"):
        AutoConfig.from_pretrained(str(folder))
    out = capsys.readouterr()
    assert "[y/N]" not in out.out + out.err and not marker.exists()
    assert builtins.input is before  # restored afterwards
