"""LeRobot pi0 and pi0.5 under prop (pytest -m lerobot; scripts/test-lerobot.sh).

A tiny pi0 and pi0.5 built here (examples/pi_tiny.py: 2-layer Gemmas and SigLIP with random weights, a
tokenizer built with `tokenizers`; nothing downloaded) on the MuJoCo reach's camera task (32 x 32 frames,
state, the task text as instruction). Every test runs both (ids ``pi0`` and ``pi05``).

LeRobot builds pi0 only at PaliGemma's sizes; a tiny one's config.json still names gemma_300m, so it
loads back as the tiny model only while ``pi_tiny.tiny()`` is active: the whole module runs under it
(``_tiny``), and every prop command runs in this process (the ``cli`` fixture, ``api``).
"""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from examples import pi_tiny  # noqa: E402
from prop_adapters import load_checkpoint  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import AuditSettings, EvalSettings, PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.datasources import load_data  # noqa: E402
from tests.adapters.shares import buffers_as_built, memo_terms  # noqa: E402

TINY = dict(steps=4, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=2, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
INPUTS = ("observation.state", task.CAMERA)
KINDS = ["pi0", "pi05"]
BITS = 32  # the smallest key: personalize and add-user run every 1-bit neighbour through the sampler


def key(seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, BITS).astype(np.uint8)


@pytest.fixture(scope="module", autouse=True)
def _tiny():
    with pi_tiny.tiny():
        yield


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The camera task's general and user data and the user's key file, shared by both policies."""
    d = tmp_path_factory.mktemp("pi-data")
    task.record(d / "general", 2, 0, np.zeros(3, np.float32), camera=True)
    task.record(d / "user", 2, 50_000, task.USER_OFFSET, camera=True)
    for name, seed in (("k.bin", 1), ("k2.bin", 2)):
        (d / name).write_bytes(np.packbits(key(seed)).tobytes())
        (d / name).chmod(0o600)
    return d


@dataclass
class Work:
    """One policy's set-up: ``kind`` (pi0 or pi05), its folder after 3 LeRobot training steps
    (``policy``), its tokenizer folder (``tok``), the shared data and key files, a folder of its own."""

    kind: str
    root: Path
    data: Path

    policy = property(lambda self: self.root / self.kind)
    tok = property(lambda self: self.root / "tok")
    general = property(lambda self: self.data / "general")
    user = property(lambda self: self.data / "user")
    key = property(lambda self: self.data / "k.bin")
    key2 = property(lambda self: self.data / "k2.bin")


@pytest.fixture(scope="module", params=KINDS)
def work(request, data, tmp_path_factory) -> Work:
    w = Work(request.param, tmp_path_factory.mktemp(request.param), data)
    built = pi_tiny.build_pi(w.kind, pi_tiny.build_tokenizer(w.tok), task.dataset_stats(w.general))
    task.train_base(w.general, w.policy, steps=3, built=built)
    return w


@pytest.fixture(scope="module")
def bundle(work):
    out = work.root / "bundle"
    api.personalize_checkpoint(
        str(work.policy), [(work.user, KeySource(key(), "file"))], out, PersonalizeConfig.of(**TINY),
        general=work.general,
    )  # fmt: skip
    return out


@pytest.fixture(scope="module")
def sealed(work):
    """Sealed, with the payload peft takes (`export --peft`): one sealed personalize per policy."""
    out = work.root / "sealed"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 8, "payload": "peft-lora"}))
    api.personalize_checkpoint(str(work.policy), [(work.user, KeySource(key(), "file"))], out, cfg)
    return out


def lerobot_policy(folder, tokenizer):
    """The policy in ``folder`` loaded by LeRobot itself, the tokenizer step reading ``tokenizer``."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    cfg = PreTrainedConfig.from_pretrained(str(folder))
    policy = get_policy_class(cfg.type).from_pretrained(str(folder), config=cfg).eval()
    pre, post = make_pre_post_processors(
        policy.config, pretrained_path=str(folder),
        preprocessor_overrides={"tokenizer_processor": {"tokenizer_name": str(tokenizer)}},
    )  # fmt: skip
    return policy, pre, post


def lerobot_actions(policy, pre, post, data, rows, seed: int) -> np.ndarray:
    """LeRobot's own select_action on ``rows`` of ``data`` (first of each chunk), noise seeded."""
    out = []
    for row in rows:
        policy.reset()
        obs = {k: torch.from_numpy(data.x[k][row : row + 1]) for k in INPUTS}
        obs["task"] = str(data.x["task"][row])
        torch.manual_seed(seed)
        with torch.no_grad():
            out.append(post(policy.select_action(pre(obs)))[0].numpy())
    return np.stack(out)


def test_pi0_keyed_layers_are_lerobots_peft_targets_and_inspect_shows_their_share(work, cli):
    info = api.inspect_checkpoint(str(work.policy))
    assert info["model"]["type"] == work.kind and info["model"]["chunk_size"] == 10
    keyed = {x["name"] for x in info["layers"] if x["keyed"]}
    policy = load_checkpoint(work.policy).module
    targets = policy._get_default_peft_targets()["target_modules"]
    assert keyed == {n for n, _ in policy.named_modules() if re.fullmatch(targets, n)}
    assert ("model.state_proj" in keyed) == (work.kind == "pi0")
    share = sum(p.numel() for n, m in policy.named_modules() if n in keyed for p in m.parameters())
    assert info["keyed_parameters"] == share and info["keyed_share"] == share / info["parameters"]
    r = cli("inspect", work.policy)
    assert r.code == 0 and work.kind in r.out
    assert f"{share:,} keyed ({100 * share / info['parameters']:.1f}%)" in r.out


def test_pi0_user_term_is_lerobots_own_loss_for_the_same_seed(work):
    """The user term equals LeRobot's PI0Policy/PI05Policy.forward under one seed (its noise, then its
    time; padded steps not masked), with fallback rows in the same forward or not; the deployed chunk
    is LeRobot's own sampler."""
    policy = load_checkpoint(work.policy).policy
    batch = policy.batches(load_data(work.user), "--data")
    user = {k: batch[k][25:31] for k in [*policy.row_shapes, "action", "action_is_pad"]}
    assert user["action_is_pad"].any()  # the episode's end: padded steps, which pi0 does not mask
    rows, targets = policy.fallback_pool({k: batch[k][:2] for k in policy.row_shapes}, batch["action"][:2],
                                         policy, torch.Generator().manual_seed(0))  # fmt: skip
    none = {k: v[:0] for k, v in rows.items()}
    for fallback in (none, {k: v[:5] for k, v in rows.items()}):
        torch.manual_seed(3)
        theirs = policy.policy.forward(dict(user))[0]
        torch.manual_seed(3)
        ours, out = policy.joint_terms(user, fallback)
        assert ours.item() == theirs.item()
        assert torch.allclose(out, targets[: len(out)], atol=1e-5)
    with torch.no_grad():
        chunks = policy.chunk({k: batch[k][:2] for k in policy.row_shapes})
        policy.policy.reset()
        torch.manual_seed(policy.noise_seed)
        own = policy.policy.predict_action_chunk({k: batch[k][1:2] for k in policy.row_shapes})
    assert torch.allclose(chunks[1:2], own, atol=1e-5)
    # The audit's gradient searches differentiate the chunk (LeRobot's sample_actions is no_grad).
    again = policy.chunk({k: batch[k][:2] for k in policy.row_shapes})
    assert again.requires_grad and torch.equal(again.detach(), chunks)


def test_pi0_built_without_random_init_its_buffers_are_a_normal_builds(work):
    """The policy is built without random initialisation (every weight is then loaded): what is not
    loaded (non-persistent buffers: rotary frequencies) is what a normal build computes."""
    module = load_checkpoint(work.policy).module
    buffers_as_built(module)


def test_pi0_prefix_memo_computes_each_frames_prefix_once_and_changes_nothing(work, monkeypatch):
    """Within the memo, with PaliGemma frozen and unkeyed (sealed, train_expert_only), each frame's
    prefix goes through PaliGemma once and a forward runs the expert over its cache: the chunk, the
    terms and the expert's gradients are LeRobot's own to float rounding. A PaliGemma that trains, or a
    hook (a key) on it, turns the memo off."""
    from prop_cli.train.policy import rows

    policy = load_checkpoint(work.policy).policy
    batch = policy.batches(load_data(work.user), "--data")
    frames = {k: batch[k][[0, 1, 0, 2]] for k in [*policy.row_shapes, "action", "action_is_pad"]}
    fb, _ = policy.fallback_pool(rows(batch, torch.arange(2)), batch["action"][:2], policy,
                                 torch.Generator().manual_seed(0))  # fmt: skip
    fb = rows(fb, torch.arange(5))
    pwe = policy.model.paligemma_with_expert
    lm = pwe.paligemma.model.language_model
    fills = []
    real = type(lm).forward
    fill = lambda self, **k: (self is lm and fills.append(len(k["inputs_embeds"]))) or real(self, **k)  # noqa: E731
    monkeypatch.setattr(type(lm), "forward", fill)  # the expert's Gemma has the class too: counted apart

    def memo_runs():
        with policy.memo():
            out = memo_terms(policy, frames, fb)
            again = policy.chunk(frames)
        assert torch.allclose(again, out[0], atol=1e-6)
        return out

    pwe.paligemma.requires_grad_(False)  # train_expert_only (a sealed run freezes it all)
    plain = memo_terms(policy, frames, fb)
    fills.clear()
    memo = memo_runs()
    assert fills == [3]  # one fill over the 3 distinct frames, then every forward from the memo
    for a, b in zip(plain[:3], memo[:3]):
        assert torch.allclose(a, b, atol=1e-5)
    assert plain[3].keys() == memo[3].keys() and plain[3]
    assert all(torch.allclose(plain[3][n], memo[3][n], atol=1e-5) for n in plain[3])
    hook = lm.layers[0].self_attn.q_proj.register_forward_hook(lambda m, a, o: o)  # a key on PaliGemma
    fills.clear()
    try:
        memo_runs()
    finally:
        hook.remove()
    assert fills == [4, 4]  # LeRobot's forward: the chunk's prefix fill, again for the chunk after
    lm.layers[0].self_attn.q_proj.weight.requires_grad_(True)  # PaliGemma trains (pi0's default)
    fills.clear()
    memo_runs()
    assert fills == [4, 4]


def test_pi0_bundle_carries_the_tokenizer_and_runs_as_lerobot(bundle, work, tmp_path, cli):
    tok = bundle / "lerobot" / "tokenizer"
    assert sorted(p.name for p in tok.iterdir()) == ["tokenizer.json", "tokenizer_config.json"]
    listed = json.loads((bundle / "manifest.json").read_text())["files"]
    assert "lerobot/tokenizer/tokenizer.json" in listed
    moved = work.root / "tok-elsewhere"  # the tokenizer folder the policy was made with is gone
    work.tok.rename(moved)
    try:
        ys = {}
        runs = (("no_key", []), ("again", []), ("key", ["--key-file", work.key]))
        for name, extra in runs:
            r = cli("run", bundle, "--input", work.user, "--output", tmp_path / f"{name}.npy",
                    "--noise-seed", 7, *extra)  # fmt: skip
            assert r.code == 0, r.err
            ys[name] = np.load(tmp_path / f"{name}.npy")
    finally:
        moved.rename(work.tok)
    data = load_data(work.user)
    assert ys["no_key"].shape == (len(data), 10, 3)
    assert np.array_equal(ys["no_key"], ys["again"])
    assert not np.allclose(ys["no_key"], ys["key"], atol=1e-3)
    # No key is the bundle's base in LeRobot itself, its tokenizer the bundle's.
    own = lerobot_actions(*lerobot_policy(bundle / "lerobot", tok), data, (0, 17), seed=7)
    assert np.allclose(own, ys["no_key"][[0, 17], 0], atol=1e-5)


def test_pi0_sealed_runs_the_original_without_its_key_and_audits(sealed, work):
    from prop_cli.run.policy import WrongKeyWarning, run_policy

    b = load_bundle(sealed)
    assert b.is_sealed and json.loads((sealed / "manifest.json").read_text())["model"]["type"] == work.kind
    data = load_data(work.user)
    orig = load_checkpoint(work.policy).policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        expected = orig.post(orig.chunk({k: batch[k] for k in orig.row_shapes})).numpy()
    assert np.array_equal(run_policy(b, data, None), expected)
    with pytest.warns(WrongKeyWarning):
        assert np.array_equal(run_policy(b, data, key(2), allow_unenrolled=True), expected)
    assert not np.allclose(run_policy(b, data, key()), expected, atol=1e-4)
    s = AuditSettings(probes=["null", "random"], random=4, samples=1000)
    report = api.audit_bundle(sealed, work.user, s, key_files=[work.key], original=str(work.policy))
    assert {"null", "random"} <= {g["name"] for g in report["groups"]}


def test_pi0_attack_audits_the_unsealed_bundle_with_the_original_as_control(bundle, work):
    s = AuditSettings(probes=["null", "random", "hamming"], hamming=[1], per_distance=2, random=4,
                      samples=1000, noise_seed=3)  # fmt: skip
    report = api.audit_bundle(bundle, work.user, s, key_files=[work.key], original=str(work.policy))
    names = {g["name"]: g for g in report["groups"]}
    assert {"null", "random", "hamming 1"} <= set(names)
    assert all(g["control"]["available"] for g in names.values())


def test_pi0_eval_needs_an_instruction_and_runs_the_original_without_a_key(sealed, work):
    few = EvalSettings(episodes=1, random_keys=1, neighbours=0, episodes_per_key=1, max_steps=4)
    with pytest.raises(Exception, match="--instruction"):
        api.eval_bundle(sealed, task.CAMERA_ENV_ID, few, obs_map=task.CAMERA_OBS_MAP, key_file=None)
    settings = EvalSettings(episodes=1, random_keys=1, neighbours=0, episodes_per_key=1, max_steps=4,
                            instruction=task.INSTRUCTION)  # fmt: skip
    report = api.eval_bundle(
        sealed, task.CAMERA_ENV_ID, settings, obs_map=task.CAMERA_OBS_MAP, metric=task.METRIC,
        original=str(work.policy), key_file=work.key,
    )  # fmt: skip
    c = report["conditions"]
    assert c["no_key"]["metric"] == c["original"]["metric"]


def test_pi0_add_and_remove_a_user_of_a_sealed_bundle(sealed, work, tmp_path, cli):
    s = tmp_path / "s"
    shutil.copytree(sealed, s)

    def run(*extra) -> np.ndarray:
        r = cli("run", s, "--input", work.user, "--output", tmp_path / "y.npy", "--force", *extra)
        assert r.code == 0, r.err
        return np.load(tmp_path / "y.npy")

    first = run("--key-file", work.key)
    r = cli("add-user", s, "--data", work.user, "--key-file", work.key2, "--steps", "4", "--json")
    assert r.code == 0, r.err
    assert json.loads(r.out)["users"] == 2
    none = run()
    assert not np.allclose(run("--key-file", work.key2), none, atol=1e-4)  # the new user's key acts
    assert np.array_equal(run("--key-file", work.key), first)  # the first user's is untouched
    r = cli("remove-user", s, "--key-file", work.key2)
    assert r.code == 0 and "(1 user left)" in r.err, r.err
    assert np.array_equal(run("--key-file", work.key2, "--allow-unenrolled-key"), none)


def test_pi0_a_peft_payload_loads_through_lerobots_peft_path(sealed, work, tmp_path, cli):
    """The opened payload as a peft LoRA adapter on LeRobot's own policy (its default PEFT targets):
    the action equals `prop run --key-file` with the same noise seed."""
    pytest.importorskip("peft")
    from peft import PeftConfig, PeftModel

    r = cli("export", sealed, "--peft", tmp_path / "adapter", "--key-file", work.key)
    assert r.code == 0, r.err
    r = cli("run", sealed, "--input", work.user, "--output", tmp_path / "y.npy", "--key-file", work.key,
            "--noise-seed", "4")  # fmt: skip
    assert r.code == 0, r.err
    y = np.load(tmp_path / "y.npy")
    config = PeftConfig.from_pretrained(str(tmp_path / "adapter"))
    base = config.base_model_name_or_path
    assert base == str((sealed / "lerobot").resolve())
    assert "gemma_expert" in str(config.target_modules)  # a regex over the keyed layers
    policy, pre, post = lerobot_policy(base, sealed / "lerobot" / "tokenizer")
    data = load_data(work.user)
    without = lerobot_actions(policy, pre, post, data, (0,), seed=4)
    policy = PeftModel.from_pretrained(policy, str(tmp_path / "adapter"), config=config).eval()
    with_adapter = lerobot_actions(policy, pre, post, data, (0,), seed=4)
    assert np.allclose(with_adapter, y[:1, 0], atol=1e-5)
    assert not np.allclose(with_adapter, without, atol=1e-4)  # the adapter is the user's key at work


def _planted(src, tmp_path, edit):
    """A copy of bundle ``src`` with ``edit(copy, manifest)`` applied and every listed file's sha256 and
    the manifest digest recomputed, as whoever can write the files would."""
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


def test_pi0_a_tokenizer_naming_code_is_refused_and_nothing_is_imported(sealed, work, tmp_path, cli):
    """The carried tokenizer config names a module through transformers' auto_map, dropped and listed
    beside it: refused in one line, --trust-remote-code or not, and nothing is imported."""
    marker = tmp_path / "pwned"

    def edit(b, m):
        tok = b / "lerobot" / "tokenizer"
        doc = json.loads((tok / "tokenizer_config.json").read_text())
        doc["auto_map"] = {"AutoTokenizer": ["pwn_tok.Pwn", None]}
        (tok / "tokenizer_config.json").write_text(json.dumps(doc))
        (tok / "pwn_tok.py").write_text(f"open({str(marker)!r}, 'w').close()\nclass Pwn: pass\n")
        m["files"]["lerobot/tokenizer/pwn_tok.py"] = ""

    planted = _planted(sealed, tmp_path, edit)
    for extra in ([], ["--trust-remote-code"]):
        r = cli("run", planted, "--input", work.user, "--output", tmp_path / "y.npy", *extra)
        assert r.code == 2 and r.err.count("\n") == 1 and "lerobot/tokenizer/" in r.err, r.err
    assert not marker.exists() and not (tmp_path / "y.npy").exists()


def test_pi0_a_tokenizer_file_outside_the_bundle_is_refused(sealed, work, tmp_path, cli):
    """Issue 42 finding 3: the carried tokenizer_config.json names "tokenizer_file": an absolute path, a
    relative one or a plain name (transformers reads those from the working folder). 0.2.0 loaded it with
    no key and no flag, and that unhashed file decided the token ids. Now refused in one line."""
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(sealed / "lerobot" / "tokenizer", elsewhere)
    for value in (str(elsewhere / "tokenizer.json"), "../../../elsewhere/tokenizer.json", "tokenizer.json"):

        def edit(b, m, value=value):
            f = b / "lerobot" / "tokenizer" / "tokenizer_config.json"
            f.write_text(json.dumps({**json.loads(f.read_text()), "tokenizer_file": value}))

        planted = _planted(sealed, tmp_path, edit)
        r = cli("run", planted, "--input", work.user, "--output", tmp_path / "y.npy")
        assert r.code == 2 and r.err.count("\n") == 1 and "names tokenizer_file" in r.err, r.err
        assert "tokenizer_config.json" in r.err and not (tmp_path / "y.npy").exists()
        shutil.rmtree(planted)


def test_pi0_a_bundle_reads_its_tokenizer_from_itself_only(bundle, work, tmp_path, cli):
    """Without the carried tokenizer/, the preprocessor names a folder outside the bundle (here the
    original's tokenizer): prop reads nothing there."""

    def edit(b, m):
        shutil.rmtree(b / "lerobot" / "tokenizer")
        m["files"] = {n: d for n, d in m["files"].items() if not n.startswith("lerobot/tokenizer/")}

    planted = _planted(bundle, tmp_path, edit)
    r = cli("run", planted, "--input", work.user, "--output", tmp_path / "y.npy")
    assert r.code == 2 and r.err.count("\n") == 1 and "tokenizer/tokenizer_config.json" in r.err, r.err
    assert str(work.tok) in r.err and not (tmp_path / "y.npy").exists()


def test_pi0_a_folder_whose_tokenizer_is_not_here_is_refused_in_one_line(work, tmp_path, cli):
    folder = tmp_path / "policy"
    shutil.copytree(work.policy, folder)
    f = folder / "policy_preprocessor.json"
    doc = json.loads(f.read_text())
    for step in doc["steps"]:
        if step["registry_name"] == "tokenizer_processor":
            step["config"]["tokenizer_name"] = "google/paligemma-3b-pt-224"
    f.write_text(json.dumps(doc))
    r = cli("inspect", folder)
    assert r.code == 2 and r.err.count("\n") == 1, r.err
    assert "paligemma-3b-pt-224" in r.err and "not on this machine" in r.err and "hf download" in r.err


def test_pi0_a_config_claiming_other_sizes_is_refused_before_anything_is_built(work, tmp_path, cli):
    """pi0 moves its model to config.device, which the meta-device shape check must survive: a
    config.json claiming other shapes than the weights is one line, nothing allocated (a real
    PaliGemma config claims billions of parameters)."""
    folder = tmp_path / "policy"
    shutil.copytree(work.policy, folder)
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps(config | {"max_action_dim": 6}))
    r = cli("inspect", folder)
    assert r.code == 2 and r.err.count("\n") == 1, r.err
    assert "do not fit the policy config.json describes" in r.err and "nothing was built" in r.err


def test_pi0_weights_load_with_lerobots_key_fixes(work, tmp_path):
    """A checkpoint converted from openpi (keys without the policy's `model.` prefix, pi0.5's time MLP
    under pi0's name) loads as PI0Policy.from_pretrained loads it: the same weights."""
    from safetensors.torch import load_file, save_file

    folder = tmp_path / "policy"
    shutil.copytree(work.policy, folder)
    weights = load_file(str(folder / "model.safetensors"))
    renamed = {k.removeprefix("model."): v for k, v in weights.items()}
    if work.kind == "pi05":
        renamed = {k.replace("time_mlp_", "action_time_mlp_"): v for k, v in renamed.items()}
    save_file(renamed, str(folder / "model.safetensors"))
    loaded = load_checkpoint(folder).module.state_dict()
    assert set(loaded) == set(weights) and all(torch.equal(loaded[k], weights[k]) for k in weights)


def test_pi0_sealed_bf16_keeps_the_original_bit_for_bit(work, tmp_path):
    """--seal --precision bf16: the frozen base is held as bf16 while the payload trains and read back
    from the checkpoint after: the bundle's base is the original's tensors exactly, a wrong key runs the
    original exactly, the user's key moves the actions."""
    from safetensors.torch import load_file

    from prop_cli.run.policy import WrongKeyWarning, run_policy

    if work.kind != "pi0":
        pytest.skip("the recipe is pi0's and pi0.5's alike; one policy is enough")
    original = load_file(str(work.policy / "model.safetensors"))
    assert any(v.dtype == torch.float32 for v in original.values())  # there is something to cast
    out = tmp_path / "sealed-bf16"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 4, "precision": "bf16"}))
    api.personalize_checkpoint(str(work.policy), [(work.user, KeySource(key(), "file"))], out, cfg)
    base = load_file(str(out / "lerobot" / "model.safetensors"))
    assert base.keys() == original.keys()
    assert all(base[k].dtype == original[k].dtype and torch.equal(base[k], original[k]) for k in base)
    b, data = load_bundle(out), load_data(work.user)
    orig = load_checkpoint(work.policy).policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        expected = orig.post(orig.chunk({k: batch[k] for k in orig.row_shapes})).numpy()
    with pytest.warns(WrongKeyWarning):
        wrong = run_policy(b, data, key(2), allow_unenrolled=True)
    assert np.array_equal(wrong, expected)
    assert np.array_equal(run_policy(b, data, None), expected)
    assert not np.allclose(run_policy(b, data, key()), expected, atol=1e-4)


def test_pi0_gradient_checkpointing_trains_the_same_model(work, bundle, sealed, tmp_path, monkeypatch):
    """A config with LeRobot's gradient_checkpointing: sealed, the payload trains through LeRobot's own
    forward, its layers recomputed in the backward pass (the checkpoints are taken) and the same payload
    comes out; unsealed, prop's keyed forward runs as without it (its rows' keys are set only during the
    forward, so it is not recomputed): the same bundle."""
    from safetensors.torch import load_file

    from prop_cli.run.policy import run_policy

    if work.kind != "pi0":
        pytest.skip("pi0.5 runs the same forward; one policy is enough")
    folder = tmp_path / "policy"
    shutil.copytree(work.policy, folder)
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps(config | {"gradient_checkpointing": True}))
    calls, checkpoint = [], torch.utils.checkpoint.checkpoint
    counted = lambda *a, **k: calls.append(1) or checkpoint(*a, **k)  # noqa: E731
    monkeypatch.setattr(torch.utils.checkpoint, "checkpoint", counted)
    users = [(work.user, KeySource(key(), "file"))]
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 8, "payload": "peft-lora"}))  # as ``sealed``
    api.personalize_checkpoint(str(folder), users, tmp_path / "sealed", cfg)
    assert len(calls) >= cfg.train.steps * 2  # every step's layers (2 per tiny Gemma), at least
    data = load_data(work.user)
    ours, theirs = (run_policy(load_bundle(b), data, key()) for b in (tmp_path / "sealed", sealed))
    assert np.allclose(ours, theirs, atol=1e-5)
    out = tmp_path / "bundle"
    api.personalize_checkpoint(str(folder), users, out, PersonalizeConfig.of(**TINY), general=work.general)
    files = sorted(p.relative_to(bundle) for p in bundle.rglob("*.safetensors"))
    assert files and files == sorted(p.relative_to(out) for p in out.rglob("*.safetensors"))
    for f in files:
        a, b = load_file(str(bundle / f)), load_file(str(out / f))
        assert a.keys() == b.keys() and all(torch.allclose(a[k], b[k], atol=1e-6) for k in a), f
