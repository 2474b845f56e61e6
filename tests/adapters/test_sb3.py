"""Stable-Baselines3 zips: read without unpickling, the actor rebuilt with SB3's names, round trips."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from torch import nn

from prop_adapters import activations, load_checkpoint
from prop_cli.bundle import load_bundle
from prop_cli.errors import PropError
from tests.conftest import FAST

POLICY_MODULES = {
    "actor_critic": ("stable_baselines3.common.policies", "ActorCriticPolicy"),
    "sac": ("stable_baselines3.sac.policies", "SACPolicy"),
    "td3": ("stable_baselines3.td3.policies", "TD3Policy"),
}


def _pickled(type_: str, **plain) -> dict:
    # What SB3 writes for a value it cloudpickles: the blob (junk here: prop must never read it),
    # the type, and the object's plain attributes beside it.
    return {":type:": f"<class '{type_}'>", ":serialized:": "bm90IGEgcGlja2xl", **plain}


def _box(shape: list[int], low: float, high: float) -> dict:
    n = int(np.prod(shape))
    return _pickled(
        "gymnasium.spaces.box.Box",
        dtype="float32",
        _shape=shape,
        low=str(np.full(n, low, np.float32)),
        high=str(np.full(n, high, np.float32)),
    )


def _mlp(sizes: list[int], act: type[nn.Module], last: type[nn.Module] | None = None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or last is not None:
            layers.append(act() if i < len(sizes) - 2 else last())
    return nn.Sequential(*layers)


def sb3_state(family: str, obs: int = 3, act: int = 2, discrete: bool = False) -> dict[str, torch.Tensor]:
    """A policy.pth state dict with SB3's MlpPolicy names and random weights."""
    torch.manual_seed(0)
    sd: dict[str, nn.Module | torch.Tensor] = {}
    if family == "actor_critic":
        mods = {
            "mlp_extractor.policy_net": _mlp([obs, 16, 16], nn.Tanh, nn.Tanh),
            "mlp_extractor.value_net": _mlp([obs, 16, 16], nn.Tanh, nn.Tanh),
            "action_net": nn.Linear(16, act),
            "value_net": nn.Linear(16, 1),
        }
    elif family == "sac":
        mods = {
            "actor.latent_pi": _mlp([obs, 16, 16], nn.ReLU, nn.ReLU),
            "actor.mu": nn.Linear(16, act),
            "actor.log_std": nn.Linear(16, act),
            "critic.qf0": _mlp([obs + act, 16, 1], nn.ReLU),
            "critic_target.qf0": _mlp([obs + act, 16, 1], nn.ReLU),
        }
    else:
        mods = {
            "actor.mu": _mlp([obs, 16, 16, act], nn.ReLU, nn.Tanh),
            "actor_target.mu": _mlp([obs, 16, 16, act], nn.ReLU, nn.Tanh),
            "critic.qf0": _mlp([obs + act, 16, 1], nn.ReLU),
        }
    for prefix, m in mods.items():
        sd.update({f"{prefix}.{k}": v.detach().clone() for k, v in m.state_dict().items()})
    if family == "actor_critic" and not discrete:
        sd["log_std"] = torch.zeros(act)
    return sd


def make_zip(
    path: Path,
    family: str = "actor_critic",
    *,
    obs: int = 3,
    act: int = 2,
    discrete: bool = False,
    state: dict | None = None,
    policy_class: str | None = None,
    policy_module: str | None = None,
    policy_kwargs: dict | None = None,
    extra_data: dict | None = None,
) -> Path:
    module, cls = POLICY_MODULES[family]
    data = {
        "policy_class": _pickled(
            "abc.ABCMeta",
            __module__=policy_module or module,
            __init__=f"<function {policy_class or cls}.__init__ at 0x7f00>",
        ),
        "policy_kwargs": policy_kwargs if policy_kwargs is not None else {},
        "observation_space": _box([obs], -1.0, 1.0),
        "action_space": _pickled("gymnasium.spaces.discrete.Discrete", dtype="int64", n=str(act), _shape=[])
        if discrete
        else _box([act], -2.0, 2.0),
        "use_sde": False,
        **(
            {"clip_range": _pickled("stable_baselines3.common.utils.FloatSchedule")}
            if family == "actor_critic"
            else {}
        ),
        **(extra_data or {}),
    }
    buf = io.BytesIO()
    torch.save(state if state is not None else sb3_state(family, obs, act, discrete), buf)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("data", json.dumps(data))
        z.writestr("policy.pth", buf.getvalue())
        z.writestr("_stable_baselines3_version", "2.9.2")
    return path


def _ref(family: str, sd: dict, x: torch.Tensor, act=torch.tanh) -> torch.Tensor:
    """The deterministic action, written out by hand from SB3's definitions."""

    def lin(name, z):
        return z @ sd[name + ".weight"].T + sd[name + ".bias"]

    if family == "actor_critic":
        h = act(lin("mlp_extractor.policy_net.2", act(lin("mlp_extractor.policy_net.0", x))))
        return lin("action_net", h)
    if family == "sac":
        h = act(lin("actor.latent_pi.2", act(lin("actor.latent_pi.0", x))))
        a = torch.tanh(lin("actor.mu", h))
    else:
        h = act(lin("actor.mu.2", act(lin("actor.mu.0", x))))
        a = torch.tanh(lin("actor.mu.4", h))
    return -2.0 + 0.5 * (a + 1.0) * 4.0  # rescaled to the Box [-2, 2]


# ---- hand-built zips (always run) ----------------------------------------------------------------


@pytest.mark.parametrize(
    "family,act,actor_keys",
    [
        (
            "actor_critic",
            torch.tanh,
            ["mlp_extractor.policy_net.0", "mlp_extractor.policy_net.2", "action_net"],
        ),
        ("sac", torch.relu, ["actor.latent_pi.0", "actor.latent_pi.2", "actor.mu"]),
        ("td3", torch.relu, ["actor.mu.0", "actor.mu.2", "actor.mu.4"]),
    ],
)
def test_actor_names_forward_and_extra(tmp_path, family, act, actor_keys):
    sd = sb3_state(family)
    loaded = load_checkpoint(make_zip(tmp_path / "m.zip", family, state=sd))
    expected = {f"{k}.{p}" for k in actor_keys for p in ("weight", "bias")}
    assert set(loaded.module.state_dict()) == expected
    assert set(loaded.extra) == set(sd) - expected  # critic / value / log_std ride along untouched
    for k, v in loaded.extra.items():
        assert torch.equal(v, sd[k])
    assert loaded.input_shape == (3,)
    assert loaded.spec["adapter"] == "sb3" and loaded.spec["family"] == family
    json.dumps(loaded.spec)
    x = torch.randn(5, 3)
    with torch.no_grad():
        torch.testing.assert_close(loaded.module(x), _ref(family, sd, x, act))


def test_discrete_actions_give_logits_and_algorithm_names(tmp_path):
    sd = sb3_state("actor_critic", act=4, discrete=True)
    loaded = load_checkpoint(make_zip(tmp_path / "m.zip", discrete=True, act=4, state=sd))
    assert loaded.spec["action"] == {"space": "Discrete", "n": 4}
    assert loaded.spec["algorithm"] == "PPO"
    x = torch.randn(5, 3)
    torch.testing.assert_close(loaded.module(x).detach(), _ref("actor_critic", sd, x))
    a2c = make_zip(tmp_path / "a2c.zip", discrete=True, act=4, state=sd, extra_data={})
    data = json.loads(zipfile.ZipFile(a2c).read("data"))
    data.pop("clip_range")
    with zipfile.ZipFile(tmp_path / "a2c2.zip", "w") as z:
        z.writestr("data", json.dumps(data))
        z.writestr("policy.pth", zipfile.ZipFile(a2c).read("policy.pth"))
    assert load_checkpoint(tmp_path / "a2c2.zip").spec["algorithm"] == "A2C"


def test_activation_from_policy_kwargs_and_override(tmp_path):
    sd = sb3_state("actor_critic")
    kwargs = _pickled("dict", activation_fn="<class 'torch.nn.modules.activation.ReLU'>")
    path = make_zip(tmp_path / "m.zip", state=sd, policy_kwargs=kwargs)
    loaded = load_checkpoint(path)
    assert loaded.spec["activation"] == "relu"
    x = torch.randn(5, 3)
    torch.testing.assert_close(loaded.module(x).detach(), _ref("actor_critic", sd, x, torch.relu))
    assert load_checkpoint(path, activation="relu").spec["activation"] == "relu"  # agreeing: fine
    # Issue 10, fix 7: an --activation other than the zip's would build a different network.
    with pytest.raises(PropError, match="--activation tanh contradicts .*relu"):
        load_checkpoint(path, activation="tanh")
    odd = make_zip(tmp_path / "odd.zip", state=sd, policy_kwargs={"activation_fn": "<class 'my.Swish'>"})
    with pytest.raises(PropError, match="Swish is not one prop can rebuild") as e:
        load_checkpoint(odd)
    assert "--activation" not in str(e.value)  # no hint to pick a "closest" one


@pytest.mark.parametrize("name", sorted(activations.BY_CLASS_NAME))
def test_every_activation_sb3_can_use_rebuilds_exactly(tmp_path, name):
    """SB3's create_mlp builds activation_fn() between Linear layers: the rebuilt actor must be equal."""
    cls = getattr(nn, name)
    sd = sb3_state("actor_critic")
    kwargs = _pickled("dict", activation_fn=f"<class 'torch.nn.modules.activation.{name}'>")
    loaded = load_checkpoint(make_zip(tmp_path / "m.zip", state=sd, policy_kwargs=kwargs))
    policy_net = _mlp([3, 16, 16], cls, cls)
    policy_net.load_state_dict({k.removeprefix("mlp_extractor.policy_net."): v for k, v in sd.items()
                                if k.startswith("mlp_extractor.policy_net.")})  # fmt: skip
    head = nn.Linear(16, 2)
    head.load_state_dict({"weight": sd["action_net.weight"], "bias": sd["action_net.bias"]})
    x = torch.randn(64, 3) * 3
    with torch.no_grad():
        assert torch.equal(loaded.module(x), head(policy_net(x)))


def test_personalize_keeps_every_policy_tensor_with_sb3_names(tmp_path, cli, workdir):
    sd = sb3_state("actor_critic", obs=4)
    path = make_zip(tmp_path / "ppo.zip", obs=4, state=sd)
    r = cli("inspect", path, "--json")
    assert r.code == 0, r.err
    info = json.loads(r.out)
    assert info["adapter"] == "sb3"
    assert [(x["name"], x["keyed"]) for x in info["layers"]] == [
        ("mlp_extractor.policy_net.0", False),
        ("mlp_extractor.policy_net.2", True),
        ("action_net", True),
    ]
    out = tmp_path / "b.prop"
    r = cli(
        "personalize",
        path,
        "--data",
        workdir / "mine.npz",
        "--key-file",
        workdir / "k.bin",
        "--out",
        out,
        *FAST,
    )
    assert r.code == 0, r.err
    base = load_file(str(out / "base.safetensors"))
    assert {k: (v.shape, v.dtype) for k, v in base.items()} == {k: (v.shape, v.dtype) for k, v in sd.items()}
    for k in ("value_net.weight", "mlp_extractor.value_net.0.weight", "log_std"):
        assert torch.equal(base[k], sd[k])
    bundle = load_bundle(out)
    assert bundle.manifest["model"]["adapter"] == "sb3"
    assert set(bundle.loaded.extra) == set(sd) - set(bundle.loaded.module.state_dict())
    r = cli(
        "run",
        out,
        "--input",
        workdir / "x.npy",
        "--key-file",
        workdir / "k.bin",
        "--output",
        tmp_path / "y.npy",
    )
    assert r.code == 0, r.err
    assert np.load(tmp_path / "y.npy").shape == (8, 2)


def test_integer_targets_for_a_box_policy_are_regression(tmp_path, cli):
    """Issue 10, fix 2: y = zeros(N, int) for a Box policy gave "personalization 1.0000 (accuracy)"."""
    path = make_zip(tmp_path / "ppo.zip", obs=3, act=1)
    x = np.random.default_rng(0).uniform(-1, 1, (60, 3)).astype(np.float32)
    np.savez(tmp_path / "d.npz", x=x, y=np.round(np.linspace(-2, 2, 60)).astype(np.int64))  # rounded torques
    (tmp_path / "k.bin").write_bytes(bytes(range(16)))
    (tmp_path / "k.bin").chmod(0o600)
    r = cli("personalize", path, "--data", tmp_path / "d.npz", "--key-file", tmp_path / "k.bin", "--out",
            tmp_path / "b.prop", "--json", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    assert json.loads(r.out)["task"] == "regression"
    r = cli("inspect", path, "--json")
    model = json.loads(r.out)["model"]
    assert model["action_low"] == [-2.0] and model["outputs"] == "continuous" and model["algorithm"] == "PPO"


def test_targets_outside_the_recorded_bounds_are_refused(tmp_path, cli):
    """Issue 10, fix 6: targets beyond the checkpoint's action bounds passed silently."""
    path = make_zip(tmp_path / "sac.zip", "sac", obs=3, act=2)
    x = np.random.default_rng(0).uniform(-1, 1, (60, 3)).astype(np.float32)
    y = np.zeros((60, 2), np.float32)
    y[7, 1] = 3.0  # the Box is [-2, 2]
    np.savez(tmp_path / "d.npz", x=x, y=y)
    (tmp_path / "k.bin").write_bytes(bytes(range(16)))
    (tmp_path / "k.bin").chmod(0o600)
    r = cli("personalize", path, "--data", tmp_path / "d.npz", "--key-file", tmp_path / "k.bin", "--out",
            tmp_path / "b.prop", *FAST)  # fmt: skip
    assert r.code == 2 and r.err.count("\n") == 1, r.err
    assert "outside the action bounds" in r.err and "low [-2.0, -2.0], high [2.0, 2.0]" in r.err
    assert "row 7, output 1: 3" in r.err and not (tmp_path / "b.prop").exists()


# ---- bad input: one line, exit 2, nothing written -----------------------------------------------


def _bad(cli, tmp_path, path, *extra) -> str:
    """The error line; checks inspect and personalize both fail with it and write nothing."""
    out = tmp_path / "never.prop"
    r = cli("inspect", path, *extra)
    assert r.code == 2 and r.err.count("\n") == 1 and r.err.startswith("prop: error:"), r.err
    np.savez(tmp_path / "d.npz", x=np.zeros((20, 3), np.float32), y=np.zeros((20, 2), np.float32))
    (tmp_path / "k.bin").write_bytes(bytes(16))
    (tmp_path / "k.bin").chmod(0o600)
    r2 = cli(
        "personalize",
        path,
        "--data",
        tmp_path / "d.npz",
        "--key-file",
        tmp_path / "k.bin",
        "--out",
        out,
        *extra,
    )
    assert r2.code == 2 and r2.err.strip() == r.err.strip() and not out.exists(), r2.err
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith((".never", "never"))) == []
    return r.err


def test_zip_that_is_not_sb3(cli, tmp_path):
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as z:
        z.writestr("readme.txt", "hello")
    assert "not a Stable-Baselines3 model" in _bad(cli, tmp_path, tmp_path / "other.zip")
    (tmp_path / "junk.zip").write_bytes(b"not a zip at all")
    assert "not a readable zip" in _bad(cli, tmp_path, tmp_path / "junk.zip")
    with zipfile.ZipFile(tmp_path / "nojson.zip", "w") as z:
        z.writestr("data", "{{{")
        z.writestr("policy.pth", b"")
    assert "not a JSON object" in _bad(cli, tmp_path, tmp_path / "nojson.zip")


@pytest.mark.parametrize(
    "kwargs,named",
    [
        ({"policy_class": "ActorCriticCnnPolicy"}, "CnnPolicy on a float32 observation"),
        ({"policy_class": "MultiInputActorCriticPolicy"}, "MultiInputPolicy with a Box observation space"),
        (
            {
                "policy_module": "sb3_contrib.common.recurrent.policies",
                "policy_class": "RecurrentActorCriticPolicy",
            },
            "RecurrentActorCriticPolicy from sb3_contrib",
        ),
        ({"extra_data": {"use_sde": True}}, "gSDE"),
    ],
)
def test_unsupported_policy_is_named_with_what_is_supported(cli, tmp_path, kwargs, named):
    err = _bad(cli, tmp_path, make_zip(tmp_path / "m.zip", **kwargs))
    assert named in err and "is not supported" in err and "PPO and A2C (Box or Discrete" in err


def test_unsupported_spaces_and_extra_tensors(tmp_path):
    sd = sb3_state("sac")
    with pytest.raises(PropError, match="Discrete action space.*not supported"):
        load_checkpoint(make_zip(tmp_path / "a.zip", "sac", discrete=True, state=sd))
    sd["actor.features_extractor.cnn.0.weight"] = torch.zeros(4, 3, 3, 3)  # a CNN in an MlpPolicy
    with pytest.raises(PropError, match="does not fit SB3's SACPolicy"):
        load_checkpoint(make_zip(tmp_path / "b.zip", "sac", state=sd))
    del sd["actor.features_extractor.cnn.0.weight"]
    sd["adapter.0.weight"] = torch.zeros(4, 3)
    with pytest.raises(PropError, match="beyond SB3's own"):
        load_checkpoint(make_zip(tmp_path / "c.zip", "sac", state=sd))


def test_pickled_objects_in_policy_pth_are_refused(tmp_path):
    import datetime

    path = make_zip(tmp_path / "m.zip", state={"when": datetime.datetime(2020, 1, 1)})
    with pytest.raises(PropError, match="never unpickles"):
        load_checkpoint(path)


def test_arch_does_not_apply_to_zips(cli, tmp_path):
    err = _bad(cli, tmp_path, make_zip(tmp_path / "m.zip"), "--arch", "x.y:z")
    assert "--arch" in err


# ---- real Stable-Baselines3 models (only where it is installed) ---------------------------------


@pytest.mark.parametrize(
    "algo,env",
    [
        ("PPO", "Pendulum-v1"),
        ("PPO", "CartPole-v1"),
        ("A2C", "Pendulum-v1"),
        ("SAC", "Pendulum-v1"),
        ("TD3", "Pendulum-v1"),
    ],
)
def test_real_sb3_model_round_trip(tmp_path, cli, algo, env):
    sb3 = pytest.importorskip("stable_baselines3")
    cls = getattr(sb3, algo)
    kwargs = {"buffer_size": 10, "learning_starts": 0} if algo in ("SAC", "TD3") else {}
    small = {"net_arch": [32, 32]} if algo in ("SAC", "TD3") else {"net_arch": {"pi": [32, 32], "vf": [32]}}
    model = cls("MlpPolicy", env, policy_kwargs=small, seed=0, device="cpu", **kwargs)
    path = tmp_path / f"{algo}.zip"
    model.save(path)

    loaded = load_checkpoint(path)
    assert loaded.spec["algorithm"] == algo
    obs = np.random.default_rng(0).uniform(-1, 1, (16, *loaded.input_shape)).astype(np.float32)
    with torch.no_grad():
        mine = loaded.module(torch.from_numpy(obs)).numpy()
    action, _ = model.predict(obs, deterministic=True)
    if env == "CartPole-v1":
        np.testing.assert_array_equal(mine.argmax(-1), action)
    elif algo in ("PPO", "A2C"):
        with torch.no_grad():
            mean = model.policy.get_distribution(torch.from_numpy(obs)).distribution.mean.numpy()
        np.testing.assert_allclose(mine, mean, rtol=1e-5, atol=1e-6)  # predict's pre-clipping mean
        np.testing.assert_allclose(np.clip(mine, -2, 2), action, rtol=1e-5, atol=1e-6)
    else:
        np.testing.assert_allclose(mine, action, rtol=1e-5, atol=1e-6)

    # Personalize, then drop the bundle's base weights back into SB3 under its own names.
    y = np.zeros(len(obs), np.int64) if env == "CartPole-v1" else -mine
    np.savez(tmp_path / "mine.npz", x=np.repeat(obs, 8, 0), y=np.repeat(y, 8, 0))
    (tmp_path / "k.bin").write_bytes(bytes(range(16)))
    (tmp_path / "k.bin").chmod(0o600)
    out = tmp_path / "b.prop"
    r = cli(
        "personalize",
        path,
        "--data",
        tmp_path / "mine.npz",
        "--key-file",
        tmp_path / "k.bin",
        "--out",
        out,
        "--steps",
        "20",
        "--device",
        "cpu",
    )
    assert r.code == 0, r.err
    base = load_file(str(out / "base.safetensors"))
    assert set(base) == set(model.policy.state_dict())
    model.policy.load_state_dict(base, strict=True)
    bundle = load_bundle(out)
    with torch.no_grad():
        again = bundle.keyed.module(torch.from_numpy(obs)).numpy()
    action, _ = model.predict(obs, deterministic=True)
    if env == "CartPole-v1":
        np.testing.assert_array_equal(again.argmax(-1), action)
    elif algo in ("SAC", "TD3"):
        np.testing.assert_allclose(again, action, rtol=1e-5, atol=1e-6)
    else:
        np.testing.assert_allclose(np.clip(again, -2, 2), action, rtol=1e-5, atol=1e-6)
