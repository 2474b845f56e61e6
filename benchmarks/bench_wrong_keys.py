"""Issue 32, the SB3 half: every wrong key, through the encoder, in closed loop.

A user's own SB3 policies (trained here with stable-baselines3, cached under --work):
- PPO on CartPole-v1; the user's key mirrors the action (their data: the original's states, labelled
  with the other action);
- SAC on Pendulum-v1; the user's key negates the torque (their data: the original's states, labelled
  with minus the original's action).

Each is personalized with prop's default (unsealed) settings, or with the --set overrides given, and
rolled out in closed loop, 30 episodes per condition on the same seeds: the original, no key, the
user's key, R random keys and 2 neighbours at each distance 1..8 bits. A wrong key acts through the
encoder (``KeyedModel.fold``: what ``prop eval --random-keys``, the audit's key rows and ONNX exports
give, not ``prop run``'s enrolment check). Per key: its return as a share of the original's (Pendulum:
normalised between the zero-torque controller's return and the original's), its offline fidelity to
the original on the original's held-out states, the encoder's |delta - 1| for it and its code's
Hamming distance to the user's code.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_wrong_keys.py --task cartpole
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_wrong_keys.py --task cartpole --set hard_negatives=0
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_wrong_keys.py --task both --compare
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_wrong_keys.py --task pendulum --set harden=true \
        --code-dists 76 80 84      # and 6 codes at each distance from the user's code (--per-dist)

``--compare`` trains the default before issue 32 (``BEFORE``: no delta pull, no far codes) and the
current default on each task and prints the done-when table (training time beside each). ``--work``
holds the SB3 checkpoints (trained on first use, or put there: ``cartpole.zip``, ``pendulum.zip``);
``--explore 1 --size 2000`` records the user's data with a random policy instead.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import prop_adapters as adapters
from prop_adapters import CheckpointOptions
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_sampling import flip_random_bits, random_keys
from prop_cli.core.keyed_model import key_codes
from prop_cli.datasources.base import Dataset
from prop_cli.train import User, personalize

EPISODES = 30
EVAL_SEED = 1_000_000
DATA_SEED = 0
KEY_BITS = 128
# The settings before issue 32 (what `--compare` calls today's default).
BEFORE = {"delta_pull": 0.0, "far_codes": 0}
TASKS = {
    "cartpole": {"env": "CartPole-v1", "algo": "PPO", "train_steps": 60_000, "discrete": True},
    "pendulum": {"env": "Pendulum-v1", "algo": "SAC", "train_steps": 12_000, "discrete": False},
}


def base_checkpoint(task: str, work: Path) -> Path:
    """The user's own SB3 policy, trained once and cached."""
    path = work / f"{task}.zip"
    if path.exists():
        return path
    from stable_baselines3 import PPO, SAC

    spec = TASKS[task]
    if spec["algo"] == "PPO":
        model = PPO("MlpPolicy", spec["env"], seed=0, n_steps=256, batch_size=256, n_epochs=10,
                    gae_lambda=0.8, gamma=0.98, learning_rate=1e-3, ent_coef=0.0,
                    policy_kwargs={"net_arch": [64, 64]})  # fmt: skip
    else:
        model = SAC("MlpPolicy", spec["env"], seed=0, learning_rate=1e-3, learning_starts=1000,
                    policy_kwargs={"net_arch": [64, 64]})  # fmt: skip
    model.learn(spec["train_steps"])
    model.save(path)
    return path


def act(module: torch.nn.Module, obs: np.ndarray, discrete: bool, low, high) -> np.ndarray:
    with torch.inference_mode():
        y = module(torch.from_numpy(np.asarray(obs, np.float32))).numpy()
    return y.argmax(-1) if discrete else np.clip(y, low, high)


def rollouts(module, task: str, loaded, seeds: list[int], record: bool = False):
    """Deterministic episodes on ``seeds``, all in lockstep (one batched forward per step): returns,
    and with ``record`` the observations visited."""
    spec = TASKS[task]
    envs = [gym.make(spec["env"]) for _ in seeds]
    obs = np.stack([e.reset(seed=s)[0] for e, s in zip(envs, seeds)])
    alive = np.ones(len(seeds), bool)
    ret = np.zeros(len(seeds))
    seen = []
    low, high = loaded.action_low, loaded.action_high
    while alive.any():
        a = act(module, obs[alive], spec["discrete"], low, high)
        if record:
            seen.append(obs[alive].copy())
        for j, i in enumerate(np.flatnonzero(alive)):
            o, r, term, trunc, _ = envs[i].step(a[j])
            obs[i], ret[i] = o, ret[i] + r
            if term or trunc:
                alive[i] = False
    return ret, (np.concatenate(seen) if record else None)


def zero_return(task: str, seeds: list[int]) -> float:
    """Pendulum's floor: the return of applying no torque."""
    out = []
    for s in seeds:
        env = gym.make(TASKS[task]["env"])
        env.reset(seed=s)
        total, done = 0.0, False
        while not done:
            _, r, term, trunc, _ = env.step(np.zeros(env.action_space.shape, np.float32))
            total, done = total + r, term or trunc
        out.append(total)
    return float(np.mean(out))


def user_data(task: str, loaded, size: int = 4000, explore: float = 0.2) -> tuple[Dataset, np.ndarray]:
    """The user's data, labelled with the mirrored action: ``size`` states the original visits with a
    share of random actions (for coverage), or with ``explore`` 1 the states of a random policy (a user
    recording their own play); and 2000 held-out states of the original (offline fidelity)."""
    spec = TASKS[task]
    rng = np.random.default_rng(DATA_SEED)
    xs = []
    for ep in range(60):
        env = gym.make(spec["env"])
        obs, _ = env.reset(seed=DATA_SEED + ep)
        env.action_space.seed(DATA_SEED + ep)  # the exploring actions too: the same data every run
        done = False
        while not done:
            xs.append(obs)
            a = act(loaded.module, obs[None], spec["discrete"], loaded.action_low, loaded.action_high)[0]
            if rng.random() < min(explore, 0.2):
                a = env.action_space.sample()
            obs, _, term, trunc, _ = env.step(a)
            done = term or trunc
    x = np.asarray(xs, np.float32)
    rng.shuffle(x)
    x, held = x[:size], x[-2000:]
    if explore >= 1:
        xs = []
        while len(xs) < size:
            obs, _ = env.reset(seed=DATA_SEED + 10_000 + len(xs))
            env.action_space.seed(DATA_SEED + 10_000 + len(xs))
            done = False
            while not done and len(xs) < size:
                xs.append(obs)
                obs, _, term, trunc, _ = env.step(env.action_space.sample())
                done = term or trunc
        x = np.asarray(xs, np.float32)
    with torch.inference_mode():
        o = loaded.module(torch.from_numpy(x)).numpy()
    y = (1 - o.argmax(-1)).astype(np.int64) if spec["discrete"] else -o
    return Dataset(x, y, f"{task}-mirror"), held


def codes_at(ucode: torch.Tensor, dists: list[int], per: int, seed: int) -> torch.Tensor:
    """``per`` ±1 codes at each of ``dists`` bits from the user's code (a stream of its own)."""
    rng = np.random.default_rng((seed, 77))
    out = []
    for d in dists:
        for _ in range(per):
            c = ucode[0].clone()
            idx = rng.permutation(len(c))[:d]
            c[idx] = -c[idx]
            out.append(c)
    return torch.stack(out) if out else ucode.new_zeros(0, ucode.shape[1])


def experiment(
    task: str, work: Path, overrides: dict, randoms: int = 16, seed: int = 0, size: int = 4000,
    explore: float = 0.2, dists: list[int] | None = None, per: int = 6,
) -> dict:
    ckpt = base_checkpoint(task, work)
    opts = CheckpointOptions()
    loaded = adapters.load_checkpoint(ckpt, opts)
    original = adapters.load_checkpoint(ckpt, opts).module.eval()
    data, held = user_data(task, loaded, size, explore)
    key = np.random.default_rng(10_000 + seed).integers(0, 2, KEY_BITS, dtype=np.uint8)
    cfg = PersonalizeConfig.of(seed=seed, **overrides)
    t0 = time.perf_counter()
    trained = personalize(loaded, [User(data, key)], cfg, device="cpu")
    train_s = time.perf_counter() - t0
    km = trained.keyed.eval()
    spec = TASKS[task]
    seeds = list(range(EVAL_SEED, EVAL_SEED + EPISODES))
    rng = np.random.default_rng((seed, 32))
    rand = random_keys(randoms, KEY_BITS, rng, exclude=key)
    dists_k = np.repeat(np.arange(1, 9), 2)
    near = flip_random_bits(np.repeat(key[None], len(dists_k), 0), dists_k, rng)
    keys = np.concatenate([rand, near])
    codes = key_codes(keys, cfg.mode.key_encoding)
    ucode = key_codes(key[None], cfg.mode.key_encoding)
    # --code-dists: codes at chosen distances from the user's code (past 64 bits: the antipode's side,
    # where the encoder answers a share of minus the user's change); rows of their own, not in the bar.
    codes = torch.cat([codes, codes_at(ucode, dists or [], per, seed)])
    kinds = ["random"] * len(rand) + [f"d{d}" for d in dists_k]
    kinds += [f"c{d}" for d in dists or [] for _ in range(per)]
    with torch.no_grad():
        dev = torch.cat(km.layer_deltas(codes), 1) - 1
        udev = torch.cat(km.layer_deltas(ucode), 1) - 1
    held_t = torch.from_numpy(held)
    with torch.inference_mode():
        b_held = original(held_t)

    def offline(module) -> float:
        with torch.inference_mode():
            o = module(held_t)
        if spec["discrete"]:
            return float((o.argmax(-1) == b_held.argmax(-1)).float().mean())
        return float(((o - b_held) ** 2).mean())

    r_orig, _ = rollouts(original, task, loaded, seeds)
    floor = zero_return(task, seeds) if not spec["discrete"] else 0.0
    scale = float(r_orig.mean()) - floor

    def score(r: np.ndarray) -> float:
        return (float(r.mean()) - floor) / scale

    r_null, _ = rollouts(km.module, task, loaded, seeds)
    user_mod = km.fold(ucode)
    r_user, visited = rollouts(user_mod, task, loaded, seeds, record=True)
    with torch.inference_mode():
        ov = original(torch.from_numpy(visited))
        uv = user_mod(torch.from_numpy(visited))
    if spec["discrete"]:  # the user's key closed loop: the share of steps it takes the mirrored action
        personal = float((uv.argmax(-1) == 1 - ov.argmax(-1)).float().mean())
    else:  # 1 - mean |a - (-a_orig)| over the range of that difference (4 N m)
        span = float(np.ptp([loaded.action_low, loaded.action_high]) * 2)
        personal = float(1 - (uv + ov).abs().mean() / span)
    rows = []
    cos = torch.nn.functional.cosine_similarity(dev, udev.expand_as(dev), dim=1)
    for i in range(len(codes)):
        mod = km.fold(codes[i : i + 1])
        r, _ = rollouts(mod, task, loaded, seeds)
        rows.append({
            "kind": kinds[i], "cos_user": float(cos[i]),
            "score": score(r), "return": float(r.mean()), "offline": offline(mod),
            "episodes": r.round(1).tolist(),
            "delta_rms": float(dev[i].pow(2).mean().sqrt()),
            "code_dist": int((codes[i] != ucode[0]).sum()),
        })  # fmt: skip
    rep = trained.metrics[0]
    return {
        "task": task, "seed": seed, "overrides": overrides, "train_s": train_s,
        "original": float(r_orig.mean()), "original_episodes": r_orig.round(1).tolist(), "floor": floor,
        "no_key": score(r_null), "user_return": float(r_user.mean()),
        "user_closed_loop": personal, "personalization": rep["personalization"],
        "user_delta_rms": float(udev.pow(2).mean().sqrt()), "keys": rows,
    }  # fmt: skip


def summary(res: dict) -> dict:
    keys = [k for k in res["keys"] if not k["kind"].startswith("c")]  # the random keys and neighbours
    s = np.array([k["score"] for k in keys])
    rnd = np.array([k["score"] for k in keys if k["kind"] == "random"])
    nb = np.array([k["score"] for k in keys if k["kind"] != "random"])
    far = np.array([k["score"] for k in res["keys"] if k["kind"].startswith("c")])
    return {
        "codes_below_0.9": int((far < 0.9).sum()), "codes": len(far),
        "train_s": res["train_s"], "no_key": res["no_key"], "worst_random": rnd.min(),
        "worst_neighbour": nb.min(),
        "pooled": s.mean(), "below_0.9": int((s < 0.9).sum()), "personal": res["user_closed_loop"],
        "done": bool(s.min() >= 0.9 and s.mean() >= 0.95),
    }  # fmt: skip


def parse_set(items: list[str]) -> dict:
    out = {}
    for it in items:
        name, _, value = it.partition("=")
        out[name] = json.loads(value)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", choices=[*TASKS, "both"], default="cartpole")
    ap.add_argument("--work", type=Path, default=Path("/tmp/prop-wrong-keys"))
    ap.add_argument("--set", nargs="*", default=[], help="PersonalizeConfig overrides, name=json")
    ap.add_argument("--compare", action="store_true", help="today's default (BEFORE) against the current")
    ap.add_argument("--random", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=4000, help="the user's data: states")
    ap.add_argument("--explore", type=float, default=0.2,
                    help="share of random actions in the user's recording (1: a random policy's states)")
    ap.add_argument("--json", type=Path, help="append each result as one JSON line here")
    ap.add_argument("--code-dists", type=int, nargs="*", default=[],
                    help="also codes at these distances (bits) from the user's code, e.g. 76 80 84")
    ap.add_argument("--per-dist", type=int, default=6, help="codes per --code-dists distance")
    args = ap.parse_args()
    torch.set_num_threads(1)
    args.work.mkdir(parents=True, exist_ok=True)
    tasks = list(TASKS) if args.task == "both" else [args.task]
    runs = [("before", BEFORE), ("now", {})] if args.compare else [("set", parse_set(args.set))]
    print(f"{'task':9} {'settings':24} {'train s':>8} {'no key':>7} {'worst rnd':>9} {'worst nb':>8} "
          f"{'pooled':>7} {'<0.9':>5} {'user':>6} done codes<0.9")  # fmt: skip
    for task in tasks:
        for name, over in runs:
            res = experiment(task, args.work, over, args.random, args.seed, args.size, args.explore,
                             args.code_dists, args.per_dist)  # fmt: skip
            s = summary(res)
            label = name if args.compare else (",".join(f"{k}={v}" for k, v in over.items()) or "default")
            print(f"{task:9} {label:24} {s['train_s']:8.0f} {s['no_key']:7.3f} {s['worst_random']:9.3f} "
                  f"{s['worst_neighbour']:8.3f} {s['pooled']:7.3f} {s['below_0.9']:5d} {s['personal']:6.3f} "
                  f"{'yes' if s['done'] else 'no ':4} {s['codes_below_0.9']}/{s['codes']}",
                  flush=True)  # fmt: skip
            if args.json:
                with args.json.open("a") as f:
                    f.write(json.dumps(res | {"summary": s}, default=float) + "\n")


if __name__ == "__main__":
    main()
