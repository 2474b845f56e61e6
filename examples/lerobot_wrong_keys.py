"""Wrong keys through the encoder, in closed loop (issue 32): does every key that is not the user's drive
an unsealed LeRobot bundle like the original? (figures in examples/RESULTS.md, "Wrong keys in closed
loop (issue 32)").

    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m examples.lerobot_reach --policy diffusion \
        --out out/lerobot-reach-diffusion --no-attack --no-sealed
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m examples.lerobot_wrong_keys --policy diffusion \
        --out out/lerobot-reach-diffusion

It takes a run of examples/lerobot_reach.py (its --out: the datasets, the original policy, user.key and
the unsealed bundle), so a re-measurement after a change of the method trains nothing but the bundle:
``--personalize NAME "FLAGS"`` first trains out/NAME with the example's settings and FLAGS on top (the
last value of a repeated flag wins), timed, then measures it.

A tiny pi0 or pi0.5 (examples/pi_tiny.py) loads only under its size patch: for them the whole measurement
runs under ``pi_tiny.tiny()``, and ``--personalize`` trains through ``python -m examples.pi_tiny`` as the
example does.

Every condition runs the same ``--episodes`` seeds (from 1,000,000, as `prop eval`) and the same noise
(a sampling policy's noise seed 0): the original, the bundle without a key, the user's key, ``--random-keys``
random keys and ``--neighbours`` keys 1..``--max-flip`` bits from the user's (distances in turn). Each
wrong key runs every seed: a key is judged on the same starting states as the original. Wrong keys go
through the encoder (``KeyedPolicy(..., method=True)``, what `prop eval --random-keys` and the audit
measure and what an export answers), not through prop's check, which runs the base for a key enrolled
in nothing.

The report (--json) is rewritten after every condition, marked ``"partial"`` until the last: a run stopped
early keeps every key measured so far. The wrong keys run interleaved (random 1, neighbour 1, random 2,
...), so a stopped run has as many of each group.

Per key it prints success (reaching the goal), the user's preference, the return, the ratio of its
success to the original's, and the gate of issue 32: every wrong key >= 0.9x the original's success and
their pooled mean >= 0.95x. With ``--offline-frames N`` it also gives each key's offline figures on N
frames of the user's and of the general data (whole chunks in normalised units, docs/metrics.md:
fidelity mse against the original, leakage towards the user's chunks, personalization on the user's
frames: 1 - mse(key, user) / mse(original, user)) and what the encoder makes of
it (the code's Hamming distance to the user's code, the rms of delta - 1 over the keyed features, and
the cosine of its delta - 1 with the user's), to see what the failing keys have in common.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from examples import lerobot_reach as reach
from examples import lerobot_reach_task as task

SEED = 1_000_000  # prop eval's first evaluation seed (recording used 0-79 and 50,000-50,019)
EVERY, POOLED = 0.9, 0.95  # issue 32's gate: each wrong key, and their pooled mean, against the original


def key_conditions(key: np.ndarray, n_random: int, n_neighbours: int, max_flip: int, seed: int) -> list[dict]:
    """The wrong keys: random keys (named by their bits) and neighbours at distances 1..max_flip in turn
    (named by distance and flipped positions only)."""
    from prop_cli.core.key_sampling import flip_random_bits, random_keys

    # One stream per group: the first n keys of a larger draw are the keys of a smaller one (a cheaper run
    # measures a subset of a full run's keys).
    rng = np.random.default_rng((seed, 32, 0))
    out = [{"group": "random", "bits": b, "id": {"bits": "".join(map(str, b))}}
           for b in random_keys(n_random, len(key), rng, exclude=key)]  # fmt: skip
    rng = np.random.default_rng((seed, 32, 1))
    distances = np.array([1 + i % max_flip for i in range(n_neighbours)])
    for d, b in zip(distances, flip_random_bits(np.repeat(key[None], n_neighbours, 0), distances, rng)):
        out.append({"group": "neighbour", "bits": b,
                    "id": {"distance": int(d), "flipped": np.flatnonzero(b != key).tolist()}})  # fmt: skip
    return out


def episodes(env, controller, seeds: list[int], features: list[str], obs_map: dict[str, str]) -> list[dict]:
    """One episode per seed over the recorded horizon (acting on after the task's `terminated`, as the
    example's `prop eval --ignore-terminated`): success at the end, the user's preference, the return."""
    out = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        controller.reset(seed)
        total, info, observations = 0.0, {}, [obs]
        for _ in range(task.HORIZON):
            x = {}
            for f in features:
                v = obs[obs_map.get(f, f)]
                x[f] = v if np.asarray(v).dtype == np.uint8 else np.asarray(v, np.float32)
            obs, reward, _, _, info = env.step(controller.select_action(x))
            total += float(reward)
            observations.append(obs)
        out.append({"success": float(info.get("is_success", 0.0)), "return": total,
                    "preference": task.user_preference({"observations": observations})})  # fmt: skip
    return out


def summary(results: list[dict]) -> dict:
    out: dict = {"episodes": len(results)}
    for f in ("success", "preference", "return"):
        v = np.array([r[f] for r in results], float)
        se = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else 0.0
        out[f] = {"mean": float(v.mean()), "se": se}
    out["per_episode_success"] = [int(r["success"]) for r in results]
    return out


class Offline:
    """Each key's chunks on fixed frames of the user's and the general data, against the original's."""

    def __init__(self, bundle, original, out: Path, frames: int) -> None:
        from prop_cli.datasources import load_data

        self.policy, self.bundle = bundle.loaded.policy, bundle
        self.sets = {}
        for name, folder in (("user", "reach-user"), ("general", "reach-general")):
            batch = self.policy.batches(load_data(out / folder), "--data")
            n = len(batch["episode_index"])
            idx = torch.from_numpy(np.unique(np.linspace(0, n - 1, min(frames, n)).round().astype(np.int64)))
            feats = {k: batch[k].index_select(0, idx) for k in self.policy.row_shapes}
            self.sets[name] = (feats, batch["action"].index_select(0, idx))
        self.base = {name: self.chunks(original.module, name) for name in self.sets}

    @torch.no_grad()
    def chunks(self, module, name: str) -> torch.Tensor:
        return self.policy.on(module).chunk(self.sets[name][0])

    def __call__(self, module) -> dict:
        from prop_cli.core import metrics

        out = {}
        for name, (_, p) in self.sets.items():
            o, b = self.chunks(module, name)[None], self.base[name]
            out[f"fidelity_{name}"] = float(metrics.fidelity(o, b, "regression")[0])
            if name == "user":
                out["leakage_user"] = float(metrics.leakage(o, p, b, "regression")[0])
                # 1 - mse(key, user) / mse(original, user), personalize's figure, on these frames
                out["personalization_user"] = metrics.personalization(o[0], p, b, "regression")
        return out


def encoder_view(bundle, key: np.ndarray):
    """What the encoder makes of a key, next to the user's: the code's Hamming distance (fraction of
    bits), the rms of delta - 1 (how far the keyed layers move), and the cosine of delta - 1 with the
    user's (whether the move points the user's way)."""
    from prop_cli.core.keyed_model import key_codes

    keyed, enc = bundle.mode.keyed, bundle.mode.encoding
    user_code = key_codes(key, enc)

    @torch.no_grad()
    def view(bits: np.ndarray) -> dict:
        code = key_codes(bits, enc)
        d, u = keyed.encoder.latent(code)[0] - 1, keyed.encoder.latent(user_code)[0] - 1
        return {"code_distance": float((code != user_code).float().mean()),
                "delta_rms": float(d.pow(2).mean().sqrt()),
                "delta_cos_user": float(torch.nn.functional.cosine_similarity(d, u, dim=0))}  # fmt: skip

    return view


def measure(args: argparse.Namespace, save=None) -> dict:
    """Roll out every key condition (a tiny pi0 / pi0.5 under examples.pi_tiny's size patch, which its
    original and bundle need to load); ``save(report)`` after each, the report so far (``"partial"``)."""
    if args.policy not in reach.PI:
        return _measure(args, save)
    from examples.pi_tiny import tiny

    with tiny():
        return _measure(args, save)


def interleaved(wrong: list[dict]) -> list[dict]:
    """The wrong keys in the order they are rolled out: random 1, neighbour 1, random 2, ... (each group's
    own order), so that a run stopped early has measured as many keys of each group."""
    groups = [[w for w in wrong if w["group"] == g] for g in ("random", "neighbour")]
    out = []
    for i in range(max(map(len, groups), default=0)):
        out += [g[i] for g in groups if i < len(g)]
    return out


def _measure(args: argparse.Namespace, save=None) -> dict:
    import warnings

    from prop_cli.bundle import load_bundle
    from prop_cli.bundle.read import rebuild_original
    from prop_cli.core.key_files import key_for_bundle
    from prop_cli.run import KeyedPolicy
    from prop_cli.run.envs import make_env
    from prop_cli.run.policy import seed_noise
    from prop_cli.run.rollout import parse_obs_map

    out, kind = args.out, args.policy
    bundle = load_bundle(out / args.bundle)
    if bundle.is_sealed:
        sys.exit(f"error: {out / args.bundle} is sealed: its wrong keys run the original exactly; "
                 "give an unsealed bundle")
    key = key_for_bundle(bundle.manifest, out / "user.key")
    camera = task.CAMERA in bundle.loaded.policy.input_features
    sim = task.sim_of(out / "reach-general")  # the run's simulator, as its datasets were recorded
    task.require_sim(sim)
    env_id, obs_map = task.env_id(sim, camera), (task.CAMERA_OBS_MAP if camera else task.OBS_MAP)
    instruction = task.INSTRUCTION if kind in reach.VLA else None
    if kind in reach.VLA:
        obs_map = task.SMOLVLA_OBS_MAP
    obs_map = parse_obs_map(obs_map)
    original = rebuild_original(bundle, str(out / kind))
    for loaded in (bundle.loaded, original):
        seed_noise(loaded, 0)
        if instruction is not None:
            loaded.policy.instruction = instruction
    env = make_env(env_id)
    features = list(bundle.loaded.policy.input_features)
    seeds = [SEED + i for i in range(args.episodes)]
    wrong = key_conditions(key, args.random_keys, args.neighbours, args.max_flip, args.key_seed)
    view = encoder_view(bundle, key)
    offline = Offline(bundle, original, out, args.offline_frames) if args.offline_frames else None
    rows: list[dict] = []
    meta = {"bundle": str(out / args.bundle), "policy": kind, "env": env_id, "seeds": [seeds[0], seeds[-1]]}

    def run(name: str, group: str, controller, module=None, ident=None, bits=None) -> None:
        t = time.perf_counter()
        row = {"name": name, "group": group} | summary(episodes(env, controller, seeds, features, obs_map))
        row["seconds"] = round(time.perf_counter() - t, 2)
        if ident is not None:
            row["key"] = ident
        if bits is not None:
            row |= view(bits)
        if offline is not None and module is not None:
            row |= offline(module)
        rows.append(row)
        if save is not None:
            save(gate(rows) | meta | {"rows": rows, "partial": True})
        print(f"  {name:24s} success {row['success']['mean']:.2f}  preference {row['preference']['mean']:.2f}"
              f"  ({row['seconds']:.1f} s)", file=sys.stderr, flush=True)  # fmt: skip

    run("original", "original", original.policy.controller(original.module.eval()), original.module)
    run("no key", "no_key", KeyedPolicy(bundle, None, noise_seed=0, instruction=instruction),
        bundle.loaded.module)  # fmt: skip
    user = KeyedPolicy(bundle, key, noise_seed=0, instruction=instruction)
    run("user key", "user_key", user, user.module, bits=key)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        n_random = 0
        for w in interleaved(wrong):
            ctl = KeyedPolicy(bundle, w["bits"], method=True, noise_seed=0, instruction=instruction)
            n_random += w["group"] == "random"
            name = f"random {n_random}" if w["group"] == "random" else f"neighbour d={w['id']['distance']}"
            run(name, w["group"], ctl, ctl.module, ident=w["id"], bits=w["bits"])
    env.close()
    return gate(rows) | meta | {"rows": rows, "partial": False}


def gate(rows: list[dict]) -> dict:
    """Issue 32's gate on success (each wrong key >= EVERY x the original's, their pooled mean >= POOLED x),
    each row's ratio, the worst wrong key and the pooled means of random keys and of neighbours."""
    first = next(r for r in rows if r["group"] == "original")
    base, ref = first["success"]["mean"], np.array(first["per_episode_success"])
    wrong = [r for r in rows if r["group"] in ("random", "neighbour")]
    for r in rows:
        r["ratio"] = r["success"]["mean"] / base if base else None
        # paired on the same starting states: episodes the original reached and this key did not, and back
        mine = np.array(r["per_episode_success"])
        r["lost"], r["gained"] = int(((ref == 1) & (mine == 0)).sum()), int(((ref == 0) & (mine == 1)).sum())
    pooled = {g: float(np.mean([r["success"]["mean"] for r in wrong if r["group"] == g] or [np.nan]))
              for g in ("random", "neighbour")}  # fmt: skip
    paired = {g: sign_test([r for r in wrong if g == "all" or r["group"] == g])
              for g in ("random", "neighbour", "all")}  # fmt: skip
    all_wrong = float(np.mean([r["success"]["mean"] for r in wrong])) if wrong else float("nan")
    worst = min(wrong, key=lambda r: r["success"]["mean"]) if wrong else None
    failing = [r["name"] for r in wrong if r["success"]["mean"] < EVERY * base]
    return {
        "original_success": base,
        "pooled": pooled | {"all": all_wrong, "ratio": all_wrong / base if base else None},
        "worst": None if worst is None else {"name": worst["name"], "success": worst["success"]["mean"],
                                              "ratio": worst["ratio"], "key": worst.get("key")},
        "failing": failing,
        "passes": bool(wrong) and not failing and all_wrong >= POOLED * base,
        "paired": paired,
        "predicts": predictors(wrong),
    }  # fmt: skip


def sign_test(rows: list[dict]) -> dict:
    """The rows' episodes lost and gained against the original on the same seeds, pooled, and the exact
    two-sided sign test of the two counts (ties, both reaching or both missing, left out): whether the
    keys lose more episodes than they gain beyond chance."""
    from scipy.stats import binomtest

    lost, gained = sum(r["lost"] for r in rows), sum(r["gained"] for r in rows)
    p = float(binomtest(lost, lost + gained, 0.5).pvalue) if lost + gained else 1.0
    return {"lost": lost, "gained": gained, "p": p}


def predictors(wrong: list[dict]) -> dict:
    """Whether a wrong key's offline figures rank it as closed loop does: Spearman's rho of each figure
    with the key's episodes lost against the original, over the wrong keys (None where either is
    constant)."""
    from scipy.stats import spearmanr

    lost = [r["lost"] for r in wrong]
    out = {}
    for k in ("fidelity_user", "fidelity_general", "leakage_user", "delta_rms", "delta_cos_user"):
        vals = [r.get(k) for r in wrong]
        if len(wrong) > 2 and None not in vals and len(set(lost)) > 1 and len(set(vals)) > 1:
            out[k] = float(spearmanr(vals, lost).statistic)
        else:
            out[k] = None
    return out


def _x(ratio: float | None) -> str:
    return "n/a: the original never succeeds" if ratio is None else f"{ratio:.2f}x"


def table(report: dict) -> str:
    rows = report["rows"]
    offline = "fidelity_user" in rows[-1]
    head = ["key", "success", "ratio", "lost / gained", "preference", "return", "code dist", "delta rms",
            "cos user"]  # fmt: skip
    if offline:
        head += ["fid user", "fid general", "leak user", "pers user"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for r in rows:
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
        cells = [r["name"], f"{r['success']['mean']:.2f}", ratio, f"{r['lost']} / {r['gained']}",
                 f"{r['preference']['mean']:.2f}", f"{r['return']['mean']:.1f}"]  # fmt: skip
        cells += [f"{r[k]:.3f}" if k in r else "" for k in ("code_distance", "delta_rms", "delta_cos_user")]
        if offline:
            offline_figures = ("fidelity_user", "fidelity_general", "leakage_user", "personalization_user")
            cells += [f"{r[k]:.4f}" if k in r else "" for k in offline_figures]
        lines.append("| " + " | ".join(cells) + " |")
    p, w = report["pooled"], report["worst"]
    if w is None:  # the user's key, no key and the original only (--random-keys 0 --neighbours 0)
        lines.append(f"\noriginal {report['original_success']:.2f}; no wrong keys measured: no gate")
        return "\n".join(lines)
    lines.append(
        f"\noriginal {report['original_success']:.2f}; pooled random {p['random']:.2f}, neighbours "
        f"{p['neighbour']:.2f}, all {p['all']:.2f} ({_x(p['ratio'])}); worst {w['name']} {w['success']:.2f} "
        f"({_x(w['ratio'])}); failing (< {EVERY}x): {', '.join(report['failing']) or 'none'}; gate "
        f"(each >= {EVERY}x, pooled >= {POOLED}x): {'PASS' if report['passes'] else 'FAIL'}"
    )
    if report["paired"]["all"]["lost"] + report["paired"]["all"]["gained"]:
        pairs = [f"{g} {s['lost']} / {s['gained']} (p {s['p']:.2g})" for g, s in report["paired"].items()]
        lines.append("episodes lost / gained against the original, pooled (sign test): " + ", ".join(pairs))
    rho = {k: v for k, v in report["predicts"].items() if v is not None}
    if rho:
        lines.append("Spearman rho with episodes lost, over the wrong keys: "
                     + ", ".join(f"{k} {v:+.2f}" for k, v in rho.items()))  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="a run of examples.lerobot_reach (its --out)")
    ap.add_argument("--policy", choices=sorted(reach.SETTINGS), default="act")
    ap.add_argument("--bundle", default="bundle", help="the unsealed bundle's folder in --out")
    ap.add_argument("--personalize", metavar="FLAGS", default=None,
                    help="first train --out/BUNDLE: the example's personalize settings, then these flags")
    ap.add_argument("--episodes", type=int, default=30, help="episodes per key (the same seeds for each)")
    ap.add_argument("--random-keys", type=int, default=16)
    ap.add_argument("--neighbours", type=int, default=16, help="keys 1..--max-flip bits from the user's")
    ap.add_argument("--max-flip", type=int, default=8)
    ap.add_argument("--key-seed", type=int, default=0, help="seed of the wrong keys drawn")
    ap.add_argument("--offline-frames", type=int, default=128,
                    help="frames of the user's and the general data for each key's offline figures (0: none)")
    ap.add_argument("--json", type=Path, default=None, help="default --out/wrong-keys-BUNDLE.json")
    ap.add_argument("--from-json", type=Path, default=None,
                    help="roll out nothing: gate and print the table of this earlier report")  # fmt: skip
    args = ap.parse_args(argv)
    if args.from_json is not None:
        report = json.loads(args.from_json.read_text())
        report |= gate(report["rows"])
        print(table(report))
        return report
    if min(args.episodes, args.max_flip) < 1 or min(args.random_keys, args.neighbours) < 0:
        ap.error("--episodes and --max-flip must be >= 1, --random-keys and --neighbours >= 0")
    trained = None
    if args.personalize is not None:
        conf = reach.SETTINGS[args.policy]["personalize"]
        t = time.perf_counter()
        report = json.loads(reach.prop(
            "personalize", args.out / args.policy, "--data", args.out / "reach-user", "--key-file",
            args.out / "user.key", "--general-data", args.out / "reach-general",
            "--out", args.out / args.bundle,
            *conf, *shlex.split(args.personalize), "--force", "--json", capture=True, kind=args.policy,
        ))  # fmt: skip
        trained = {"flags": args.personalize, "seconds": round(time.perf_counter() - t, 1),
                   "offline": report["metrics"][0]}  # fmt: skip
    t = time.perf_counter()
    path = args.json or args.out / f"wrong-keys-{args.bundle}.json"

    def save(report: dict) -> None:  # whole or not at all: a stopped run leaves its last complete report
        report["seconds"] = round(time.perf_counter() - t, 1)
        if trained is not None:
            report["personalize"] = trained
        part = path.with_name(path.name + ".part")
        part.write_text(json.dumps(report, indent=1))
        os.replace(part, path)

    report = measure(args, save)
    save(report)
    print(table(report))
    print(f"wrote {path} ({report['seconds']} s)", file=sys.stderr)
    return report


if __name__ == "__main__":
    main()
