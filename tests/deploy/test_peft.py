"""`prop export --peft`: a sealed user's peft-lora payload as a standard peft LoRA adapter.

peft lives in the LeRobot environment (LeRobot's own `peft` extra), so these run there
(scripts/test-lerobot.sh, which CI runs): an MLP, a convolutional model, and a LeRobot Diffusion policy
loaded through LeRobot's own PEFT path.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file
from torch import nn

pytest.importorskip("peft")
pytestmark = pytest.mark.lerobot

from prop_cli import constants as C  # noqa: E402
from tests.conftest import FAST, write_keys, write_user_data  # noqa: E402


def _peft_outputs(model: nn.Module, adapter, x: np.ndarray) -> np.ndarray:
    from peft import PeftModel

    wrapped = PeftModel.from_pretrained(model, str(adapter)).eval()
    with torch.no_grad():
        return wrapped(torch.from_numpy(x)).numpy()


def test_an_mlps_adapter_in_peft_acts_as_prop_run_with_the_key(tmp_path, cli):
    from prop_adapters import load_checkpoint

    rng = np.random.default_rng(0)
    write_user_data(tmp_path, 120, rng)
    write_keys(tmp_path, ("k.bin", "k2.bin"), rng)
    common = ["--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k.bin", *FAST]
    r = cli("personalize", tmp_path / "model.safetensors", *common, "--out", tmp_path / "s", "--seal",
            "--payload", "peft-lora", "--payload-rank", "2")  # fmt: skip
    assert r.code == 0, r.err
    r = cli("export", tmp_path / "s", "--peft", tmp_path / "adapter", "--key-file", tmp_path / "k.bin")
    assert r.code == 0, r.err
    assert "unencrypted" in r.err
    config = json.loads((tmp_path / "adapter" / C.PEFT_CONFIG).read_text())
    assert config["peft_type"] == "LORA" and config["r"] == 2 and config["lora_alpha"] == 2
    x = rng.uniform(-1, 1, (32, 4)).astype(np.float32)
    np.save(tmp_path / "x.npy", x)
    r = cli("run", tmp_path / "s", "--input", tmp_path / "x.npy", "--output", tmp_path / "y.npy",
            "--key-file", tmp_path / "k.bin")  # fmt: skip
    assert r.code == 0, r.err
    base = load_checkpoint(tmp_path / "model.safetensors").module  # a sealed bundle's base: the original
    ours = np.load(tmp_path / "y.npy")
    theirs = _peft_outputs(base, tmp_path / "adapter", x)
    np.testing.assert_allclose(theirs, ours, atol=1e-5)
    assert not np.allclose(ours, load_checkpoint(tmp_path / "model.safetensors").module(torch.from_numpy(x))
                           .detach().numpy(), atol=1e-3)  # fmt: skip
    key = (tmp_path / "k.bin").read_bytes()
    for f in (tmp_path / "adapter").iterdir():
        assert key not in f.read_bytes() and key.hex() not in f.read_bytes().decode("latin-1")
    # Refused, one line each, nothing written: another key, an existing folder, inside the bundle, the
    # unsealed bundle, a lora payload (its per-input delta is no LoRA).
    cases = [
        (["--peft", tmp_path / "a2", "--key-file", tmp_path / "k2.bin"], "opens no record"),
        (["--peft", tmp_path / "adapter", "--key-file", tmp_path / "k.bin"], "exists"),
        (["--peft", tmp_path / "s" / "adapter", "--key-file", tmp_path / "k.bin"], "--peft"),
    ]
    for args, words in cases:
        r = cli("export", tmp_path / "s", *args)
        assert r.code == 2 and words in r.err and len(r.err.strip().splitlines()) == 1, r.err
    assert not (tmp_path / "a2").exists() and not (tmp_path / "s" / "adapter").exists()
    r = cli("personalize", tmp_path / "model.safetensors", *common, "--out", tmp_path / "l", "--seal")
    assert r.code == 0, r.err
    r = cli("export", tmp_path / "l", "--peft", tmp_path / "a3", "--key-file", tmp_path / "k.bin")
    assert r.code == 2 and "--payload peft-lora" in r.err and not (tmp_path / "a3").exists()


def test_a_convolutions_adapter_is_peft_conv_lora(tmp_path, cli):
    from tests.fixtures_arch import TinyCNN, make_cnn

    torch.manual_seed(0)
    model = make_cnn()
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(tmp_path / "cnn.safetensors"))
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (64, *TinyCNN.input_shape)).astype(np.float32)
    with torch.no_grad():
        y = -model(torch.from_numpy(x)).numpy()
    np.savez(tmp_path / "d.npz", x=x, y=y.astype(np.float32))
    write_keys(tmp_path, ("k.bin",), rng)
    conv = next(n for n, m in model.named_modules() if isinstance(m, nn.Conv2d))
    r = cli("personalize", tmp_path / "cnn.safetensors", "--arch", "tests.fixtures_arch:make_cnn", "--layers",
            conv, "--data", tmp_path / "d.npz", "--key-file", tmp_path / "k.bin", "--out", tmp_path / "s",
            "--seal", "--payload", "peft-lora", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    r = cli("export", tmp_path / "s", "--peft", tmp_path / "adapter", "--key-file", tmp_path / "k.bin",
            "--trust-remote-code")  # fmt: skip
    assert r.code == 0, r.err
    w = load_file(str(tmp_path / "adapter" / C.PEFT_WEIGHTS))
    a = w[f"base_model.model.{conv}.lora_A.weight"]
    assert a.dim() == 4 and w[f"base_model.model.{conv}.lora_B.weight"].shape[2:] == (1, 1)
    np.save(tmp_path / "x.npy", x[:8])
    r = cli("run", tmp_path / "s", "--input", tmp_path / "x.npy", "--output", tmp_path / "y.npy",
            "--key-file", tmp_path / "k.bin", "--trust-remote-code")  # fmt: skip
    assert r.code == 0, r.err
    torch.manual_seed(0)
    base = make_cnn()
    base.load_state_dict(load_file(str(tmp_path / "cnn.safetensors")))
    np.testing.assert_allclose(_peft_outputs(base, tmp_path / "adapter", x[:8]), np.load(tmp_path / "y.npy"),
                               atol=1e-5)  # fmt: skip


def test_a_diffusion_adapter_loads_through_lerobots_peft_path(tmp_path_factory, cli):
    """LeRobot's make_policy with use_peft: the adapter's base path -> from_pretrained -> PeftModel. Its
    action equals `prop run --key-file` with the same noise seed."""
    pytest.importorskip("lerobot")
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors
    from peft import PeftConfig, PeftModel

    from examples import lerobot_reach_task as task
    from prop_cli.datasources import load_data

    d = tmp_path_factory.mktemp("peft-diffusion")
    task.record(d / "general", 2, 0, np.zeros(3, np.float32))
    task.record(d / "user", 2, 50_000, task.USER_OFFSET)
    task.train_base(d / "general", d / "diffusion", steps=3, kind="diffusion")
    write_keys(d, ("k.bin",), np.random.default_rng(2))
    r = cli("personalize", d / "diffusion", "--data", d / "user", "--key-file", d / "k.bin", "--out", d / "s",
            "--seal", "--payload", "peft-lora", "--steps", "20", "--user-rows", "8")  # fmt: skip
    assert r.code == 0, r.err
    r = cli("export", d / "s", "--peft", d / "adapter", "--key-file", d / "k.bin")
    assert r.code == 0, r.err
    r = cli("run", d / "s", "--input", d / "user", "--output", d / "y.npy", "--key-file", d / "k.bin",
            "--noise-seed", "4")  # fmt: skip
    assert r.code == 0, r.err
    y = np.load(d / "y.npy")
    # LeRobot's factory (use_peft): the base named in the adapter, then the adapter on it.
    config = PeftConfig.from_pretrained(str(d / "adapter"))
    assert config.base_model_name_or_path == str((d / "s" / "lerobot").resolve())
    policy = DiffusionPolicy.from_pretrained(config.base_model_name_or_path)
    policy = PeftModel.from_pretrained(policy, str(d / "adapter"), config=config).eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=config.base_model_name_or_path)
    data = load_data(d / "user")
    obs = {k: torch.from_numpy(data.x[k][:1]) for k in ("observation.state", "observation.environment_state")}
    policy.reset()
    torch.manual_seed(4)
    with torch.no_grad():
        action = post(policy.select_action(pre(obs)))[0].numpy()
    assert np.allclose(action, y[0, policy.config.n_obs_steps - 1], atol=1e-5)
