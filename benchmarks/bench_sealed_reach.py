"""What sealing costs on reach (PandaReach-v3, joint control, PPO): sealed payloads against unsealed PRoP.

    python -m benchmarks.bench_sealed_reach [--seeds 0 1] [--iters 15] [--episodes 20]

Uses examples/reproduce/reach.py: the same env, pretrained PPO policy (30 iterations, seed 0), PPO
settings, env-step budget and evaluation goals as the paper reproduction. A sealed user's payload
(prop_cli.core.payload) is attached to the frozen pretrained actor and trained with the PPO loss on the
user's rollouts towards A g + c, with no fallback term (a wrong key opens nothing and runs the
original). The payload is then sealed into a real bundle (prop_cli.bundle.write_sealed) and
evaluated through ``KeyedPolicy`` with the user's key, and with wrong keys (which must give the
original's actions exactly). Unsealed PRoP: reach.finetune (Eq. 8 with L' = PPO), the reproduction's.
Score: the mean normalised reward of deterministic rollouts towards A g + c (personalized) and g
(general). Needs the `rl` extra (panda-gym). Takes ~10 CPU-minutes with two seeds.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

import prop_adapters as adapters
from examples.reproduce import common, ppo, reach
from prop_cli import constants as C
from prop_cli.bundle import load_bundle, write_sealed
from prop_cli.config import PersonalizeConfig
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.run.policy import KeyedPolicy, WrongKeyWarning

PAYLOADS = {"lora r4": ("lora", 4, 3e-3), "full": ("full", 0, 1e-3)}  # --lr to change the rates


def train_payload(env, actor, log_std0, critic0, spec: PayloadSpec, lr: float, iters: int, seed: int, cfg):
    rng = np.random.default_rng(seed + 11)
    torch.manual_seed(seed)
    module = copy.deepcopy(actor).eval().requires_grad_(False)
    payload = Payload(spec, torch.Generator().manual_seed(seed))
    critic = copy.deepcopy(critic0)
    log_std = nn.Parameter(log_std0.clone())
    opt = torch.optim.Adam(
        [
            {"params": list(payload.parameters()), "lr": lr},
            {"params": [*critic.parameters(), log_std], "lr": cfg.lr},
        ]
    )
    eps = reach._Episodes(2_000_000 * (seed + 1))
    with payload.attached(module) as m:
        params = [*payload.parameters(), *critic.parameters(), log_std]
        for _ in range(iters):
            data = reach.rollout(
                env, reach._np_policy(m), eps.take(cfg.rollout // reach.HORIZON), True,
                log_std.detach().exp().numpy(), rng,
            )  # fmt: skip
            batch = reach._ppo_batch(data, critic, log_std.detach(), m, cfg)
            reach._update(batch, params, m, critic, log_std, cfg, opt, rng=rng)
    return payload.eval()


def scores(env, fn, episodes: int) -> dict:
    r = reach.rollout(env, fn, list(range(episodes)), False, None, np.random.default_rng(0))
    return {k: float(v.mean()) for k, v in r["score"].items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--iters", type=int, default=15)
    ap.add_argument("--pretrain", type=int, default=30)
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--lr", nargs=2, type=float, metavar=("LORA", "FULL"), help="payload learning rates")
    a = ap.parse_args(argv)
    if a.lr:
        PAYLOADS["lora r4"] = ("lora", 4, a.lr[0])
        PAYLOADS["full"] = ("full", 0, a.lr[1])
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    cfg = ppo.PPOConfig()
    ft_cfg = dataclasses.replace(cfg, lr=reach.FINETUNE_LR)
    env = reach.ReachEnv()
    actor, critic, log_std, _ = reach.pretrain(env, a.pretrain, 0, cfg, lambda *_: None)
    actor.eval()
    pool_seeds = list(range(3_000_000, 3_000_000 + max(2, a.episodes * 2)))
    pool = reach.rollout(env, reach._np_policy(actor), pool_seeds, False, None, np.random.default_rng(0))
    pool = pool["obs"].reshape(-1, reach.OBS)
    base = scores(env, reach._np_policy(actor), a.episodes)
    print(f"base: personalized {base['personal']:.3f} general {base['general']:.3f}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="prop-reach-") as tmp:
        ckpt = Path(tmp) / "actor.safetensors"
        save_file(
            {k: v.contiguous() for k, v in actor.state_dict().items()},
            str(ckpt),
            metadata={"activation": "tanh"},
        )
        loaded = adapters.load_checkpoint(str(ckpt), adapters.CheckpointOptions())
        mods = dict(loaded.module.named_modules())
        from prop_cli.core.layers import select_layers

        layers = [
            {"name": n, "in_features": mods[n].in_features, "out_features": mods[n].out_features}
            for n in select_layers(loaded.module, None, None)
        ]
        for seed in a.seeds:
            key = common.user_key(seed)
            for name, (kind, rank, lr) in PAYLOADS.items():
                t0 = time.perf_counter()
                spec = PayloadSpec(kind, layers, rank)
                payload = train_payload(env, actor, log_std, critic, spec, lr, a.iters, seed, ft_cfg)
                seconds = time.perf_counter() - t0
                out = Path(tmp) / f"{seed}-{kind}.prop"
                manifest = {
                    C.M_MODEL: loaded.spec,
                    C.M_KEYED_LAYERS: [{"name": x["name"], "features": x["in_features"]} for x in layers],
                    C.M_PAYLOAD: spec.to_dict(),
                    C.M_KEY: {"bits": len(key), "users": 1, "source": "file", "kdf": None},
                    C.M_CONFIG: PersonalizeConfig.of(
                        seal=True, payload=kind, payload_rank=max(rank, 1)
                    ).to_dict(),
                    C.M_TASK: "regression",
                    C.M_IO: {"input_shape": [reach.OBS], "checkpoint": str(ckpt)},
                }
                write_sealed(out, loaded=loaded, manifest=manifest, users=[(payload, {}, key)])
                bundle = load_bundle(out)
                user = scores(env, KeyedPolicy(bundle, key), a.episodes)
                rng = np.random.default_rng(seed + 5)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", WrongKeyWarning)
                    wrong = [
                        KeyedPolicy(bundle, k, allow_unenrolled=True)
                        for k in rng.integers(0, 2, (5, len(key)), dtype=np.uint8)
                    ]
                obs = pool[:256].astype(np.float32)
                identical = all(np.array_equal(w(obs), KeyedPolicy(bundle, None)(obs)) for w in wrong)
                rows.append({"seed": seed, "method": f"sealed {name}", "user": user, "seconds": seconds,
                             "wrong_identical": identical})  # fmt: skip
                print(seed, rows[-1], flush=True)
            t0 = time.perf_counter()
            base_total = sum(p.numel() for p in actor.parameters())
            feats = 2 * reach.BASE_HIDDEN
            enc = min(
                range(8, 1025),
                key=lambda e: abs(base_total + 129 * e + e * feats + feats - reach.TOTAL_PARAMS),
            )
            args = (env, actor, log_std, critic, pool, key, a.iters, seed, enc, reach.TOTAL_PARAMS, ft_cfg)
            ka = reach.finetune(common.PROP_HASHED, *args, lambda *_: None)
            seconds = time.perf_counter() - t0
            rng = np.random.default_rng(seed + 5)
            rand = [scores(env, ka.policy(b), 5) for b in rng.integers(0, 2, (5, len(key)), dtype=np.uint8)]
            user = scores(env, ka.policy(key), a.episodes)
            rand_personal = float(np.mean([r["personal"] for r in rand]))
            rows.append(
                {"seed": seed, "method": "unsealed PRoP", "user": user, "seconds": seconds,
                 "random_keys_personal": rand_personal}
            )  # fmt: skip
            print(seed, rows[-1], flush=True)
    env.close()
    print()
    print(
        "| method | personalized reward (user key) | general reward (user key) | vs unsealed "
        "| wrong keys = original | train s |"
    )
    print("|---|---|---|---|---|---|")
    ref = np.mean([r["user"]["personal"] for r in rows if r["method"] == "unsealed PRoP"])
    for m in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == m]
        pers = np.mean([r["user"]["personal"] for r in sel])
        gain, ref_gain = pers - base["personal"], ref - base["personal"]
        same = "yes" if all(r.get("wrong_identical", False) for r in sel) else "n/a (unsealed)"
        print(
            f"| {m} | {pers:.3f} | {np.mean([r['user']['general'] for r in sel]):.3f} | "
            f"{100 * (gain - ref_gain) / abs(ref_gain):+.0f}% of PRoP's gain over the base | {same} | "
            f"{np.mean([r['seconds'] for r in sel]):.0f} |"
        )
    print(f"| base (no key) | {base['personal']:.3f} | {base['general']:.3f} | | | |")


if __name__ == "__main__":
    main()
