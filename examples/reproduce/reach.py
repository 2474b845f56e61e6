"""Reinforcement learning (paper Sec. "Reinforcement Learning"): PandaReach-v3, joint control, PPO.

- Environment: panda-gym's ``PandaReach-v3`` with ``control_type="joints"`` (7 joint-angle deltas),
  stepped for a fixed 50-step horizon through the unwrapped env (the env's own success termination is
  ignored, so an episode can go on towards a goal other than the displayed one). Policy input: the
  end-effector position and velocity and the goal g (9 numbers).
- Reward: the paper's dense progress reward ||ee - g*|| - ||ee' - g*||, divided by the episode's
  initial distance (normalised: an episode's return is 1 - d_final / d_initial; 1 = reached, 0 = no
  progress). General objective g* = g; personalized g* = A g + c, a fixed affine map (90-degree turn
  about the vertical axis, z mirrored inside the goal box).
- Base: a PPO policy trained here (``ppo``). PRoP fine-tunes it under keys with Eq. 8 and L' = the PPO
  objective: PPO's clipped loss for the user's key on rollouts of the user's key towards A g + c, and
  distillation to the pretrained policy's mean action for K1 / K2 / null keys on visited states. The
  baselines (key-as-input MLP, state-conditioned CVAE) get the same loss and the same env steps,
  starting from scratch: their general behaviour comes from the same distillation (DAgger-style on the
  states the pretrained policy and the user-key policy visit).
- Columns: mean normalised reward of deterministic rollouts with random keys, one-bit neighbours and
  the user's key, scored against g (general row) and A g + c (personalized row).
"""

from __future__ import annotations

import copy
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from examples.reproduce import baselines, common, ppo
from prop_cli import constants as C
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_sampling import KeySampler
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.core.layers import select_layers
from prop_cli.errors import PropError

HORIZON = 50
OBS = 9
ACT = 7
BASE_HIDDEN = 128
TOTAL_PARAMS = 100_000  # the paper: ~100k weights per method
REWARD_SCALE = 10.0  # per-step reward = 10 x progress / initial distance: an episode sums to <= 10
METHODS = (common.PROP_HASHED, "MLP", "CVAE")
FINETUNE_LR = 1e-3  # fine-tuning under keys, every method (PRoP seed 0: user-key reward 0.34 at 3e-4, 0.41)
WARMUP = 1500  # baselines: supervised steps imitating the pretrained policy before PPO (no env steps)


def goal_transform(g: np.ndarray) -> np.ndarray:
    """A g + c: (x, y, z) -> (-y, x, 0.3 - z); maps the goal box [-.15, .15]^2 x [0, .3] onto itself."""
    return np.array([-g[1], g[0], 0.3 - g[2]], dtype=np.float32)


class ReachEnv:
    def __init__(self) -> None:
        try:
            import gymnasium as gym
            import panda_gym  # noqa: F401 - registers the Panda envs
        except ImportError as e:
            raise PropError(
                f"reach needs panda-gym ({e.name} is not installed)", "pip install -e '.[rl]'"
            ) from None
        self.env = gym.make("PandaReach-v3", control_type="joints", reward_type="dense").unwrapped

    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        obs, _ = self.env.reset(seed=int(seed))
        return self._vec(obs), obs["desired_goal"].astype(np.float32), obs["achieved_goal"].astype(np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        obs, *_ = self.env.step(np.clip(action, -1.0, 1.0).astype(np.float32))
        return self._vec(obs), obs["achieved_goal"].astype(np.float32)

    @staticmethod
    def _vec(obs: dict) -> np.ndarray:
        return np.concatenate([obs["observation"], obs["desired_goal"]]).astype(np.float32)

    def close(self) -> None:
        self.env.close()


def rollout(env: ReachEnv, policy, seeds: list[int], personal: bool, std: np.ndarray | None, rng) -> dict:
    """Fixed-horizon episodes; ``policy(obs (9,)) -> mean action (7,)``; Gaussian noise when ``std``."""
    e = len(seeds)
    obs = np.zeros((HORIZON, e, OBS), np.float32)
    act = np.zeros((HORIZON, e, ACT), np.float32)
    rew = np.zeros((HORIZON, e), np.float32)
    final = np.zeros((e, OBS), np.float32)
    score = {"general": np.zeros(e), "personal": np.zeros(e)}
    for i, s in enumerate(seeds):
        o, g, ee = env.reset(s)
        gp = goal_transform(g)
        target = gp if personal else g
        d0 = {"general": np.linalg.norm(ee - g), "personal": np.linalg.norm(ee - gp)}
        prev = start = max(float(np.linalg.norm(ee - target)), 1e-3)
        for t in range(HORIZON):
            a = policy(o)
            if std is not None:
                a = a + std * rng.standard_normal(ACT).astype(np.float32)
            obs[t, i], act[t, i] = o, a
            o, ee = env.step(a)
            d = float(np.linalg.norm(ee - target))
            rew[t, i] = REWARD_SCALE * (prev - d) / start
            prev = d
        final[i] = o
        score["general"][i] = 1 - np.linalg.norm(ee - g) / max(d0["general"], 1e-3)
        score["personal"][i] = 1 - np.linalg.norm(ee - gp) / max(d0["personal"], 1e-3)
    return {"obs": obs, "act": act, "rew": rew, "final": final, "score": score}


def _np_policy(fn):
    def run(o: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return fn(torch.from_numpy(o)[None])[0].numpy()

    return run


class _Episodes:
    """Seeds of training episodes, disjoint from the evaluation seeds."""

    def __init__(self, start: int) -> None:
        self.next = start

    def take(self, n: int) -> list[int]:
        out = list(range(self.next, self.next + n))
        self.next += n
        return out


def _ppo_batch(data: dict, critic: nn.Module, log_std: torch.Tensor, mean_fn, cfg: ppo.PPOConfig) -> dict:
    x = torch.from_numpy(data["obs"])
    with torch.no_grad():
        val = critic(x).squeeze(-1).numpy()
        last = critic(torch.from_numpy(data["final"])).squeeze(-1).numpy()
        adv = ppo.gae(data["rew"], val, last, cfg.gamma, cfg.lam)
        ret = adv + val
        flat_x = x.reshape(-1, OBS)
        act = torch.from_numpy(data["act"]).reshape(-1, ACT)
        old = ppo.gaussian_logp(mean_fn(flat_x), log_std, act)
    a = torch.from_numpy(adv).reshape(-1)
    return {
        "x": flat_x,
        "act": act,
        "old": old,
        "adv": (a - a.mean()) / (a.std() + 1e-8),
        "ret": torch.from_numpy(ret).reshape(-1),
    }


def _update(batch: dict, params, mean_fn, critic, log_std, cfg: ppo.PPOConfig, opt, extra=None, rng=None):
    n = len(batch["x"])
    for _ in range(cfg.epochs):
        for idx in np.array_split(rng.permutation(n), max(1, n // cfg.minibatch)):
            i = torch.from_numpy(idx)
            loss = ppo.ppo_terms(
                mean_fn(batch["x"][i]), log_std, batch["act"][i], batch["old"][i], batch["adv"][i],
                critic(batch["x"][i]).squeeze(-1), batch["ret"][i], cfg,
            )  # fmt: skip
            if extra is not None:
                loss = loss + extra()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(params, 1.0)
            opt.step()


def pretrain(
    env: ReachEnv, iters: int, seed: int, cfg: ppo.PPOConfig, log
) -> tuple[nn.Sequential, nn.Module, torch.Tensor, list]:
    """PPO from scratch towards g; returns actor, critic, log_std and the score per iteration."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    actor, critic = ppo.mlp(OBS, BASE_HIDDEN, ACT), ppo.mlp(OBS, 64, 1)
    log_std = nn.Parameter(torch.full((ACT,), cfg.init_log_std))
    params = [*actor.parameters(), *critic.parameters(), log_std]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    eps = _Episodes(1_000_000 * (seed + 1))
    curve = []
    for it in range(iters):
        data = rollout(env, _np_policy(actor), eps.take(cfg.rollout // HORIZON), False,
                       log_std.detach().exp().numpy(), rng)  # fmt: skip
        curve.append(float(data["score"]["general"].mean()))
        _update(_ppo_batch(data, critic, log_std.detach(), actor, cfg), params, actor, critic, log_std, cfg,
                opt, rng=rng)  # fmt: skip
        if it % 5 == 4 or it == iters - 1:
            log(f"  reach pretrain {it + 1}/{iters}: training score {curve[-1]:.3f}")
    return actor.eval(), critic, log_std.detach(), curve


class _KeyedActor:
    """One interface over PRoP (KeyedModel on the pretrained actor) and the baselines (key as input)."""

    def __init__(self, method: str, base: nn.Sequential, enc_hidden: int, budget: int, seed: int) -> None:
        self.method = method
        self.prop = method.startswith("PRoP")
        self.encoding = "hashed" if method == common.PROP_HASHED else "raw"
        torch.manual_seed(seed)
        if self.prop:
            module = copy.deepcopy(base)
            names = select_layers(module)
            mods = dict(module.named_modules())
            enc = KeyEncoder(common.KEY_BITS, [mods[n].in_features for n in names], [enc_hidden], 2.0)
            self.km = KeyedModel(module, enc, names)
            self.model = self.km
        else:
            arch, self.encoding = baselines.split_name(method)
            self.model = baselines.build(arch, OBS, common.KEY_BITS, ACT, budget, seed)

    def params(self) -> list[torch.Tensor]:
        return list(self.model.parameters())

    def n_params(self) -> int:
        return baselines.n_params(self.model)

    def rows(self, x: torch.Tensor, codes: torch.Tensor, key_index: torch.Tensor, null: int) -> torch.Tensor:
        """Output of row r = (x[r], codes[key_index[r]]); key_index == len(codes) is the null key."""
        if self.prop:
            return self.km.run_rows(x, self.km.layer_deltas(codes, null=null), key_index)
        full = torch.cat([codes, torch.zeros(null, codes.shape[1])]) if null else codes
        out, _ = self.model(x, full[key_index])
        return out

    def mean_fn(self, code: torch.Tensor):
        return lambda x: self.rows(x, code.reshape(1, -1), torch.zeros(len(x), dtype=torch.long), 0)

    def policy(self, bits: np.ndarray):
        code = key_codes(bits, self.encoding)
        if self.prop:
            return _np_policy(self.km.fold(code).eval())
        self.model.eval()
        return _np_policy(self.mean_fn(code))


def finetune(
    method, env, base, base_log_std, critic0, pool, key, iters, seed, enc_hidden, budget, cfg, log, warmup=0
):
    """Eq. 8 with L' = PPO: user key rollouts towards A g + c; fallback keys distilled to the base."""
    rng = np.random.default_rng(seed + 11)
    pc = PersonalizeConfig.of(seed=seed)
    ka = _KeyedActor(method, base, enc_hidden, budget, seed)
    critic = copy.deepcopy(critic0)
    log_std = nn.Parameter(base_log_std.clone())
    params = [*ka.params(), *critic.parameters(), log_std]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    sampler = KeySampler([key], pc.mode.hamming_radius, rng)
    user_code = key_codes(key, ka.encoding)
    with torch.no_grad():
        pool_t = torch.from_numpy(pool)
        pool_targets = base(pool_t)

    def fallback() -> torch.Tensor:
        m = pc.mode
        sampled = np.concatenate([sampler.neighbours(m.neighbour_keys), sampler.random(m.random_keys)])
        k, s = len(sampled), pc.mode.samples_per_key
        pick = torch.from_numpy(rng.integers(0, len(pool_t), k * s + pc.mode.null_rows))
        key_index = torch.cat([torch.arange(k).repeat_interleave(s), torch.full((pc.mode.null_rows,), k)])
        out = ka.rows(pool_t[pick], key_codes(sampled, ka.encoding), key_index, pc.mode.null_rows)
        err = ((out - pool_targets[pick]) ** 2).mean(-1)
        return err[: k * s].mean() + pc.mode.null_weight * err[k * s :].mean()

    if not ka.prop:  # from scratch: first learn the pretrained behaviour (fallback terms only, no env steps)
        for _ in range(warmup):
            loss = fallback()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    eps = _Episodes(2_000_000 * (seed + 1))
    mean_fn = ka.mean_fn(user_code)
    # Eval mode throughout: PPO's likelihood ratio needs a deterministic mean, so the CVAE runs with
    # z = mu here (no sampling, no KL term); PRoP's and the MLP's modules have no train-time behaviour.
    ka.model.eval()
    for it in range(iters):
        data = rollout(env, _np_policy(mean_fn), eps.take(cfg.rollout // HORIZON), True,
                       log_std.detach().exp().numpy(), rng)  # fmt: skip
        batch = _ppo_batch(data, critic, log_std.detach(), mean_fn, cfg)
        _update(batch, params, mean_fn, critic, log_std, cfg, opt, extra=fallback, rng=rng)
        if it % 5 == 4 or it == iters - 1:
            score = data["score"]["personal"].mean()
            log(f"  reach {method} {it + 1}/{iters}: user-key training score {score:.3f}")
    return ka


def evaluate(ka: _KeyedActor, env: ReachEnv, key: np.ndarray, episodes: int, rng) -> dict:
    seeds = list(range(episodes))  # the same evaluation goals for every method and column
    keysets = {
        "random": rng.integers(0, 2, (episodes, len(key)), dtype=np.uint8),
        "hamming1": np.repeat(key[None], episodes, 0),
        "user": key[None].repeat(episodes, 0),
    }
    keysets["hamming1"][np.arange(episodes), rng.choice(len(key), episodes, replace=False)] ^= 1
    cells: dict = {"general": {}, "personal": {}}
    for col, bits in keysets.items():
        g, p = [], []
        for s, b in zip(seeds, bits):
            r = rollout(env, ka.policy(b), [s], False, None, rng)
            g.append(r["score"]["general"][0])
            p.append(r["score"]["personal"][0])
        cells["general"][col], cells["personal"][col] = float(np.mean(g)), float(np.mean(p))
    return cells


def t2_leakage(ka: _KeyedActor, actor_path: Path, key: np.ndarray, states: np.ndarray, work: Path, budget):
    """Write PRoP's actor as a real bundle and run the audit's T2 latent search on visited states.

    The owner's targets are their key's actions (the personalized policy), the reference the base.
    """
    import prop_adapters as adapters
    from prop_cli.bundle import describe_layers, load_bundle, write_unsealed

    loaded = adapters.load_checkpoint(str(actor_path))
    loaded.module.load_state_dict(ka.km.module.state_dict())
    km = KeyedModel(loaded.module, ka.km.encoder, ka.km.layer_names)
    manifest = {
        C.M_MODEL: loaded.spec,
        C.M_KEYED_LAYERS: describe_layers(km),
        C.M_KEY: {
            "bits": common.KEY_BITS,
            "encoding": ka.encoding,
            "users": 1,
            "source": "file",
            "kdf": None,
        },
        C.M_ENCODER: {
            "hidden": [ka.km.encoder.net[0].out_features],
            "scale": ka.km.encoder.scale,
            "activation": "tanh",
            "output": "1 + scale * tanh",
        },  # fmt: skip
        C.M_CONFIG: {"objective": "PPO (examples.reproduce.reach)"},
        C.M_TASK: "regression",
        C.M_IO: {"input_shape": [OBS], "checkpoint": str(actor_path)},
        C.M_METRICS: {},
    }
    write_unsealed(work / "reach.prop", loaded=loaded, keyed=km, manifest=manifest, keys=[key], force=True)
    bundle = load_bundle(work / "reach.prop")
    with torch.no_grad():
        y = ka.km.fold(key_codes(key, ka.encoding))(torch.from_numpy(states)).numpy()
    return common.t2_leakage(bundle, states, y, key, actor_path, budget)["leakage"]


def run(out: Path, quick: bool, seeds: int | None, log=print) -> list[dict]:
    pre_iters, ft_iters, episodes, warmup = (1, 1, 2, 20) if quick else (30, 15, 20, WARMUP)
    cfg = ppo.PPOConfig(rollout=100, minibatch=50, epochs=1) if quick else ppo.PPOConfig()
    ft_cfg = dataclasses.replace(cfg, lr=FINETUNE_LR)
    n_seeds = seeds or (1 if quick else 2)
    budget = common.Budget(t2_restarts=4, t2_steps=100) if not quick else common.Budget(
        t2_restarts=2, t2_steps=10, t2_samples=64)  # fmt: skip
    env = ReachEnv()
    per_seed, params, curves = [], {}, []
    t0 = time.perf_counter()
    torch.set_flush_denormal(True)
    # One pretrained policy (seed 0): the checkpoint every user starts from; seeds vary the user's key,
    # the fine-tuning and the baselines' initialisation.
    work = out / "work" / "reach"
    work.mkdir(parents=True, exist_ok=True)
    actor, critic, log_std, curve = pretrain(env, pre_iters, 0, cfg, log)
    curves.append(curve)
    actor_path = work / "actor.safetensors"
    save_file({k: v.contiguous() for k, v in actor.state_dict().items()}, str(actor_path),
              metadata={"activation": "tanh"})  # fmt: skip
    # Fallback inputs: states the pretrained policy visits (it is what everyone else gets).
    pool_seeds = list(range(3_000_000, 3_000_000 + max(2, episodes * 2)))
    pool = rollout(env, _np_policy(actor), pool_seeds, False, None, np.random.default_rng(0))
    pool = pool["obs"].reshape(-1, OBS)
    base_eval = evaluate_base(actor, env, episodes)
    for seed in range(n_seeds):
        key = common.user_key(seed)
        base_total = baselines.n_params(actor)
        feats = 2 * BASE_HIDDEN
        enc = min(range(8, 1025), key=lambda e: abs(base_total + 129 * e + e * feats + feats - TOTAL_PARAMS))
        res: dict = {"_params": {}, "_seconds": {}}
        for m in METHODS:
            t1 = time.perf_counter()
            ka = finetune(
                m,
                env,
                actor,
                log_std,
                critic,
                pool,
                key,
                ft_iters,
                seed,
                enc,
                TOTAL_PARAMS,
                ft_cfg,
                log,
                warmup,
            )
            cells = evaluate(ka, env, key, episodes, np.random.default_rng(seed + 5))
            if ka.prop:
                st_seeds = list(range(4_000_000, 4_000_000 + min(10, episodes)))
                states = rollout(env, ka.policy(key), st_seeds, False, None, np.random.default_rng(0))
                states = states["obs"].reshape(-1, OBS)
                cells["leakage"] = {"t2": t2_leakage(ka, actor_path, key, states, work, budget)}
                res["_params"][m] = base_total + baselines.n_params(ka.km.encoder)
            else:
                res["_params"][m] = ka.n_params()
            res[m] = cells
            res["_seconds"][m] = time.perf_counter() - t1
            log(f"  reach seed {seed} {m}: {res['_seconds'][m]:.1f} s")
        params = res["_params"]
        per_seed.append(res)
    env.close()
    base_scores = base_eval
    return [
        {
            "name": "reach",
            "title": "Reinforcement learning, PandaReach-v3 (joints, dense reward), key 128 bits",
            "objective": "normalised reward (1 - final / initial distance to the goal)",
            "higher_is_better": True,
            "row_labels": {
                "general": "general (reward towards g)",
                "personal": "personalized (reward towards A g + c)",
                "leakage": "leakage (shared metric)",
            },
            **common.seed_fields(per_seed, params, METHODS),
            "pretrain_curves": curves,
            "notes": [
                f"Pretrained PPO policy (no key, one for all seeds), {pre_iters} x {cfg.rollout} env steps: "
                "deterministic normalised reward "
                f"{base_scores['general']:.3f} towards g, {base_scores['personal']:.3f} towards A g + c.",
                f"Each method: {ft_iters} x {cfg.rollout} env steps of PPO (lr {FINETUNE_LR}) under the "
                f"user's key + Eq. 8 fallback distillation; {episodes} evaluation episodes per column. "
                f"Seconds: {time.perf_counter() - t0:.0f}.",
                "PRoP uses prop's default hashed key encoding here; the baselines get the paper's raw bits. "
                f"Baselines start from scratch with {warmup} supervised steps imitating the pretrained "
                "policy "
                "under K1/K2/null keys (Eq. 8's fallback terms, no env steps), standing in for PRoP's "
                "pretrained start; then the same PPO + fallback loop as PRoP.",
                "T2 latent: the audit's direct delta search on states the user's policy visits; leakage "
                "against the user key's actions.",
                "Parameters: " + ", ".join(f"{m} {n}" for m, n in params.items()),
            ],
        }
    ]


def evaluate_base(actor: nn.Module, env: ReachEnv, episodes: int) -> dict:
    r = rollout(env, _np_policy(actor), list(range(episodes)), False, None, np.random.default_rng(0))
    return {k: float(v.mean()) for k, v in r["score"].items()}
