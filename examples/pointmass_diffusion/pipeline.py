"""Steps of examples/pointmass_diffusion (see __main__), each over a task module (world.TASKS: task.py
reach, task_waypoint.py, task_slow.py; ``t``, default reach)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from examples.lerobot_common import DIFFUSION, PERSONALIZE_BATCH, lerobot_train_args, original_controller
from examples.pointmass_diffusion import task as pm
from examples.pointmass_diffusion import world

BIN = Path(sys.executable).parent
BASE_EPISODES, USER_EPISODES = 100, 20
BASE_SEED, USER_SEED, JUDGE_SEED = 0, 50_000, 1_000_000
EPISODES = 20
N_RANDOM, N_NEIGHBOURS, MAX_FLIP = 16, 16, 8  # the MetaWorld example's wrong keys
TRAIN = [
    "--policy.type=diffusion",
    "--policy.down_dims=[32,64,128]",
    *DIFFUSION,
    "--policy.pretrained_backbone_weights=null",
    "--policy.optimizer_lr=5e-4",
    "--policy.scheduler_warmup_steps=30",
    "--steps=300",
    "--batch_size=32",
]
# prop personalize: the LeRobot examples' Eq. 8 batch (examples/lerobot_common.py), 900 steps: at 300, even
# --delta-pull 100 left every wrong key drifting from the goal (examples/RESULTS.md, "Point mass", round 2).
PERSONALIZE = ["--steps", "900", *PERSONALIZE_BATCH]


def policy_dir(out: Path) -> Path:
    return out / "train" / "checkpoints" / "last" / "pretrained_model"


def run(cmd: list, log: Path) -> None:
    print("$ " + " ".join(map(str, cmd)), flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        subprocess.run(list(map(str, cmd)), check=True, stdout=f, stderr=subprocess.STDOUT)


def prop(*args) -> str:
    print("$ prop " + " ".join(map(str, args)), flush=True)
    cmd = [sys.executable, "-m", "prop_cli.cli.main", *map(str, args)]
    return subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True).stdout


def check_task(out: Path, t=pm) -> None:
    """out/task.json names the task the folder holds: another task's folder is refused in one line."""
    marker = out / "task.json"
    if marker.is_file():
        held = json.loads(marker.read_text()).get("task")
        if held != t.NAME:
            why = f"holds task {held!r}, not {t.NAME!r}: pass --task {held} or another --out"
            sys.exit(f"prop: error: {out} {why}")
    else:
        out.mkdir(parents=True, exist_ok=True)
        marker.write_text(json.dumps({"task": t.NAME}))


def train_args(t=pm) -> list[str]:
    """TRAIN with the task's own lerobot-train steps (``TRAIN_STEPS``; reach: TRAIN's 300)."""
    steps = getattr(t, "TRAIN_STEPS", None)
    return [a if steps is None or not a.startswith("--steps=") else f"--steps={steps}" for a in TRAIN]


def step_record(out: Path, t=pm) -> None:
    for name, n, seed, user in (
        ("base", BASE_EPISODES, BASE_SEED, False),
        ("user", USER_EPISODES, USER_SEED, True),
    ):
        root, done = out / name, out / f"{name}.json"
        if done.is_file():
            print(f"record: {root} done")
            continue
        shutil.rmtree(root, ignore_errors=True)
        t0 = time.perf_counter()
        counts = world.record(t, root, n, seed, user)
        counts["seconds"] = round(time.perf_counter() - t0, 1)
        done.write_text(json.dumps(counts))
        print(f"record: {root}: {counts}", flush=True)


def step_train(out: Path, t=pm) -> None:
    if (policy_dir(out) / "model.safetensors").is_file():
        print(f"train: {policy_dir(out)} done")
        return
    shutil.rmtree(out / "train", ignore_errors=True)
    t0 = time.perf_counter()
    job = "pointmass-diffusion" if t is pm else f"pointmass-{t.NAME}-diffusion"
    args = lerobot_train_args("local/base", out / "base", train_args(t), out / "train", job)
    run([BIN / "lerobot-train", *args], out / "train.log")
    (out / "train.json").write_text(json.dumps({"seconds": round(time.perf_counter() - t0, 1)}))
    print(f"train: {time.perf_counter() - t0:.0f} s", flush=True)


def _name(base: str, variant: str) -> str:
    return f"{base}-{variant}" if variant else base


def step_personalize(out: Path, variant: str = "", extra: list[str] | None = None) -> None:
    key = out / "user.key"
    if not key.is_file():
        prop("keygen", key)
    dest = out / _name("bundle", variant)
    if (dest / "manifest.json").is_file():
        print(f"personalize: {dest} done")
        return
    shutil.rmtree(dest, ignore_errors=True)
    t0 = time.perf_counter()
    report = json.loads(
        prop(
            "personalize",
            policy_dir(out),
            "--data",
            out / "user",
            "--key-file",
            key,
            "--out",
            dest,
            *PERSONALIZE,
            *(extra or []),
            "--general-data",
            out / "base",
            "--json",
        )
    )
    report["seconds"] = round(time.perf_counter() - t0, 1)
    (out / f"{_name('bundle', variant)}.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"personalize: {dest} {report['seconds']} s", flush=True)


def conditions(key: np.ndarray) -> list[dict]:
    from examples.lerobot_wrong_keys import key_conditions

    wrong = key_conditions(key, N_RANDOM, N_NEIGHBOURS, MAX_FLIP, 0)  # random keys: the same with or without
    rnd = [w for w in wrong if w["group"] == "random"]  # neighbours (one stream per group)
    nb = [w for w in wrong if w["group"] == "neighbour"]
    return [
        {"name": "original", "group": "original"},
        {"name": "no_key", "group": "no_key"},
        {"name": "user_key", "group": "user_key"},
        *[{"name": f"random-{i + 1:02d}", **w} for i, w in enumerate(rnd)],
        *[{"name": f"neighbour-{i + 1:02d}", **w} for i, w in enumerate(nb)],
    ]


def controller(out: Path, variant: str, c: dict):
    import warnings

    from prop_cli.bundle import load_bundle
    from prop_cli.core.key_files import key_for_bundle
    from prop_cli.run import KeyedPolicy

    if c["group"] == "original":
        return original_controller(policy_dir(out))
    bundle = load_bundle(out / _name("bundle", variant))
    if c["group"] == "no_key":
        return KeyedPolicy(bundle, None)
    if c["group"] == "user_key":
        return KeyedPolicy(bundle, key_for_bundle(bundle.manifest, out / "user.key"))
    with warnings.catch_warnings():  # through the encoder, unchecked: what someone holding the files runs
        warnings.simplefilter("ignore")
        return KeyedPolicy(bundle, c["bits"], method=True)


def user_bits(out: Path, variant: str) -> np.ndarray:
    from prop_cli.bundle import load_bundle
    from prop_cli.core.key_files import key_for_bundle

    return key_for_bundle(load_bundle(out / _name("bundle", variant)).manifest, out / "user.key")


def judge_dir(out: Path, variant: str = "", offset: int = 0) -> Path:
    """Where the judged conditions of a block of seeds lie: judge[-variant]/ for the seeds from
    ``JUDGE_SEED`` (offset 0), judge[-variant]/offset-N/ for those from ``JUDGE_SEED + N``."""
    folder = out / _name("judge", variant)
    return folder / f"offset-{offset}" if offset else folder


def step_judge(out: Path, variant: str = "", n: int = EPISODES, t=pm, offset: int = 0) -> None:
    """Every condition on the same seeds ``JUDGE_SEED + offset`` ... ``+ offset + n - 1`` (one batch, the
    same sampler noise, drawn from ``offset``): judge_dir(out, variant, offset)/NAME.json. The original
    is judged once per block (judge_dir(out, "", offset)/original.json) and shared by the variants."""
    judged = judge_dir(out, variant, offset)
    judged.mkdir(parents=True, exist_ok=True)
    seeds = [JUDGE_SEED + offset + i for i in range(n)]
    for c in conditions(user_bits(out, variant)):
        path = (judge_dir(out, "", offset) if c["group"] == "original" else judged) / f"{c['name']}.json"
        if path.is_file():
            done = [e["seed"] for e in json.loads(path.read_text())["episodes"]]
            if done != seeds:
                why = f"holds seeds {done[0]}..{done[-1]} ({len(done)}), not {seeds[0]}..{seeds[-1]} ({n})"
                sys.exit(f"prop: error: {path} {why}: pass --episodes {len(done)} or another --seed-offset")
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        eps = world.rollouts(t, controller(out, variant, c), seeds, batch_seed=offset)
        seconds = round(time.perf_counter() - t0, 1)
        row = dict(name=c["name"], group=c["group"], id=c.get("id"), episodes=eps, seconds=seconds)
        path.write_text(json.dumps(row, indent=1))
        print(
            f"judge {c['name']:10s} success {sum(e['success'] for e in eps)}/{n}  distance "
            f"{np.mean([e['distance'] for e in eps]):.4f}  lean {np.mean([e['lean'] for e in eps]):+.4f}  "
            f"({row['seconds']} s)",
            flush=True,
        )


def _sample(diffusion, batch: dict, seed: int, along: list | None = None) -> dict:
    """LeRobot's ``conditional_sample`` step by step (its scheduler, its prior and step noise drawn from
    torch's generator seeded with ``seed``): each step's (x_t, t, the U-Net's prediction). ``along``:
    another run's steps, on whose x_t this model's prediction is also taken (a one-step error)."""
    import torch

    c = diffusion.config
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        torch.manual_seed(seed)
        cond = diffusion._prepare_global_conditioning(batch)
        n = cond.shape[0]
        x = torch.randn((n, c.horizon, c.action_feature.shape[0]))
        sched = diffusion.noise_scheduler
        sched.set_timesteps(diffusion.num_inference_steps)
        steps, at = [], []
        for k, t in enumerate(sched.timesteps):
            tt = torch.full((n,), int(t), dtype=torch.long)
            eps = diffusion.unet(x, tt, global_cond=cond)
            steps.append({"x": x, "t": int(t), "eps": eps})
            if along is not None:
                at.append(diffusion.unet(along[k]["x"], tt, global_cond=cond))
            x = sched.step(eps, t, x).prev_sample
    return {"steps": steps, "chunk": x, "at": at}


def step_drift(out: Path, variant: str = "", t=pm) -> None:
    """Per denoising step, how far each key's noise prediction is from the original's on the original's
    own sampler states (one-step error), how far its own sampler's state ends from the original's (the
    error compounded over the steps), and the executed actions' bias along the user's offset (x), on the
    closed-loop observations of the original's judged episodes: out/drift[-variant].json."""

    dest = out / f"{_name('drift', variant)}.json"
    if dest.is_file():
        print(f"drift: {dest} done")
        return
    ctl = original_controller(policy_dir(out))
    original = ctl.module.diffusion
    seen: list[dict] = []
    generate = original.generate_actions

    def record(batch, noise=None):
        seen.append({k: v.clone() for k, v in batch.items()})
        return generate(batch, noise=noise)

    original.generate_actions = record
    world.rollouts(t, ctl, [JUDGE_SEED + i for i in range(EPISODES)])
    original.generate_actions = generate
    c = original.config
    start, stop = c.n_obs_steps - 1, c.n_obs_steps - 1 + c.n_action_steps
    refs = [_sample(original, b, 7 + i) for i, b in enumerate(seen)]
    rows = []
    for cnd in conditions(user_bits(out, variant))[1:]:
        model = controller(out, variant, cnd).module.diffusion
        one, gap, bias, size = [], [], [], []
        for i, b in enumerate(seen):
            run = _sample(model, b, 7 + i, along=refs[i]["steps"])
            ref = refs[i]
            one.append(
                [
                    float(
                        (a - s["eps"]).flatten(1).norm(dim=1).mean() / s["eps"].flatten(1).norm(dim=1).mean()
                    )
                    for a, s in zip(run["at"], ref["steps"])
                ]
            )
            gap.append(
                [
                    float((r["x"] - s["x"]).flatten(1).norm(dim=1).mean())
                    for r, s in zip(run["steps"][1:], ref["steps"][1:])
                ]
                + [float((run["chunk"] - ref["chunk"]).flatten(1).norm(dim=1).mean())]
            )
            d = run["chunk"][:, start:stop] - ref["chunk"][:, start:stop]
            bias.append(float(d[..., 0].mean()))
            size.append(float(d.norm(dim=-1).mean()))
        rows.append(
            {
                "name": cnd["name"],
                "group": cnd["group"],
                "one_step": np.mean(one, 0).round(5).tolist(),
                "gap": np.mean(gap, 0).round(5).tolist(),
                "action_bias_x": round(float(np.mean(bias)), 5),
                "action_change": round(float(np.mean(size)), 5),
            }
        )
        print(
            f"drift {cnd['name']:10s} one-step {rows[-1]['one_step'][0]:.4f}..{rows[-1]['one_step'][-1]:.4f} "
            f"chunk gap {rows[-1]['gap'][-1]:.4f} action change {rows[-1]['action_change']:.4f} "
            f"bias x {rows[-1]['action_bias_x']:+.4f}",
            flush=True,
        )
    timesteps = [s["t"] for s in refs[0]["steps"]]
    first = sum(bool((b["observation.state"][:, 0] == b["observation.state"][:, -1]).all()) for b in seen)
    report = {
        "timesteps": timesteps,
        "train_timesteps": int(original.noise_scheduler.config.num_train_timesteps),
        "calls": len(seen),
        "calls_with_repeated_history": first,
        "rows": rows,
    }
    dest.write_text(json.dumps(report, indent=1))


def code_distances(out: Path, variant: str = "") -> dict[str, int]:
    """Per wrong key (``conditions``), how many bits of its encoder input differ from the user's: the
    bundle's key encoding applied to both (hashed, the default: their SHAKE-256 codes; raw: the bits)."""
    from prop_cli import constants as C
    from prop_cli.bundle.read import read_manifest
    from prop_cli.core.key_files import key_for_bundle
    from prop_cli.core.keyed_model import key_codes

    manifest = read_manifest(out / _name("bundle", variant))  # the manifest only: no LeRobot needed
    encoding = manifest[C.M_KEY].get("encoding", C.KEY_ENCODINGS[0])
    user = key_for_bundle(manifest, out / "user.key")
    mine = key_codes(user, encoding)[0]
    wrong = conditions(user)[3:]
    codes = key_codes(np.stack([c["bits"] for c in wrong]), encoding)
    return {c["name"]: int((code != mine).sum()) for c, code in zip(wrong, codes)}


def spearman(x, y, permutations: int = 20_000, seed: int = 0) -> tuple[float, float]:
    """Spearman's rank correlation of ``x`` and ``y`` (average ranks for ties) and its two-sided
    permutation p (``permutations`` shuffles of ``y``, seeded; at least 1 / (permutations + 1))."""

    def ranks(v) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        order = v.argsort(kind="stable")
        r = np.empty(len(v))
        r[order] = np.arange(len(v), dtype=float)
        for value in np.unique(v):  # ties: their mean rank
            r[v == value] = r[v == value].mean()
        return (r - r.mean()) / (np.linalg.norm(r - r.mean()) or 1.0)

    rx, ry = ranks(x), ranks(y)
    rho = float(rx @ ry)
    shuffled = np.random.default_rng(seed).permuted(np.tile(ry, (permutations, 1)), axis=1)
    beyond = int((np.abs(shuffled @ rx) >= abs(rho) - 1e-12).sum())
    return rho, (beyond + 1) / (permutations + 1)


def code_table(out: Path, v: str, t=pm, offsets: list[int] | None = None) -> None:
    """The wrong keys' mean final distance and lean against their code distance to the user's code
    (``code_distances``, Spearman over the keys), and the keys by code distance."""
    if not (out / _name("bundle", v) / "manifest.json").is_file() or not (out / "user.key").is_file():
        return
    codes = code_distances(out, v)
    table = summary(out, v, None, t, offsets)["rows"]
    rows = {r["name"]: r for r in table if r["name"] in codes}
    if len(rows) < 3:
        return
    names = sorted(rows, key=lambda n: (codes[n], n))
    d = [codes[n] for n in names]
    ref = next(r["distance"] for r in table if r["name"] == "original")
    far, near = [n for n in names if codes[n] >= 69], [n for n in names if codes[n] <= 60]

    def extra(keys: list[str]) -> str:
        return f"{np.mean([rows[n]['distance'] for n in keys]) - ref:+.4f}" if keys else "none"

    (rd, pd), (rl, pl) = (spearman(d, [rows[n][k] for n in names]) for k in ("distance", "lean"))
    judged = seeds_label(offsets, rows[names[0]]["n"])
    print(
        f"\n{t.NAME}: {_name('bundle', v)}, {len(names)} wrong keys ({judged}): code distance to the user's "
        f"code (bits) against the mean final distance, Spearman {rd:+.2f} (permutation p {pd:.2g}), against "
        f"the lean {rl:+.2f} (p {pl:.2g}); extra final distance against the original: keys at >= 69 bits "
        f"({len(far)}) {extra(far)}, at <= 60 bits ({len(near)}) {extra(near)}"
    )
    print("keys by code distance: " + ", ".join(f"{n} {codes[n]}" for n in names))


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of k successes in n (95% at z = 1.96)."""
    if n == 0:
        return (float("nan"), float("nan"))
    centre, spread = (k + z * z / 2) / (n + z * z), z * math.sqrt(k * (n - k) / n + z * z / 4) / (n + z * z)
    return (max(0.0, centre - spread), min(1.0, centre + spread))


def sign_p(a: int, b: int) -> float:
    """Two-sided exact sign test: ``a`` and ``b`` pairs on either side, ties left out."""
    n = a + b
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(0, min(a, b) + 1)) / 2**n
    return min(1.0, 2 * tail)


def _load(folder: Path) -> dict[str, dict]:
    return {r["name"]: r for r in (json.loads(f.read_text()) for f in sorted(folder.glob("*.json")))}


def judged(out: Path, variant: str = "", offsets: list[int] | None = None) -> tuple[dict, list[str]]:
    """The original and the variant's conditions judged on every block of seeds in ``offsets`` (default
    [0]), each condition's episodes the blocks' in order; a condition missing from a block is left out
    and named in the second value returned. Blocks that share a seed are refused in one line."""
    offsets = offsets or [0]
    blocks = [_load(judge_dir(out, "", o)) | _load(judge_dir(out, variant, o)) for o in offsets]
    names = [n for n in blocks[0] if all(n in b for b in blocks[1:])]
    rows = {n: blocks[0][n] | {"episodes": [e for b in blocks for e in b[n]["episodes"]]} for n in names}
    for n, r in rows.items():
        seeds = [e["seed"] for e in r["episodes"]]
        if len(set(seeds)) < len(seeds):
            flags = " ".join(f"--seed-offset {o}" for o in offsets)
            sys.exit(f"prop: error: {flags}: {n}'s blocks share seeds; pass blocks that do not overlap")
    return rows, sorted({n for b in blocks for n in b} - set(names))


def _at(rows: dict[str, dict], threshold: float | None, user_by_distance: bool = True) -> dict[str, dict]:
    """The judged rows with success (and the user's criterion where ``user_by_distance``: the task's
    ``USER_BY_DISTANCE``) re-read from the final distances at ``threshold`` (None: as judged, the task's
    ``THRESHOLD``)."""
    if threshold is None:
        return rows

    def at(e: dict) -> dict:
        user = {"user": int(e["user_distance"] < threshold)} if user_by_distance else {}
        return e | {"success": int(e["distance"] < threshold)} | user

    return {n: r | {"episodes": [at(e) for e in r["episodes"]]} for n, r in rows.items()}


def pooled(rows: dict[str, dict], table: list[dict], group: str, alpha: float = 0.05) -> dict | None:
    """One group of wrong keys (random, neighbour) pooled: success (Wilson 95%) and its ratio to the
    original's, episodes lost and gained against the original on the same seeds (exact sign test: the
    paired test), how many keys end farther and lean more than the original (a sign test over the keys: a
    systematic drift), the per-episode paired distances, whether the group meets the issue's bar (every
    key >= 0.9x, pooled >= 0.95x), and the keys whose own paired sign test has p < ``alpha`` (``worse``:
    more episodes lost than gained, ``better``: the other way). None when the group was not judged."""
    wrong = [t for t in table if t["group"] == group]
    if not wrong:
        return None
    ref = rows["original"]["episodes"]
    k0 = sum(e["success"] for e in ref)
    d0, l0 = np.mean([e["distance"] for e in ref]), np.mean([e["lean"] for e in ref])
    kw, nw = sum(t["k"] for t in wrong), sum(t["n"] for t in wrong)
    lost, gained = sum(t["lost"] for t in wrong), sum(t["gained"] for t in wrong)
    near = {e["seed"]: e["distance"] for e in ref}
    per_seed = [e["distance"] - near[e["seed"]] for t in wrong for e in rows[t["name"]]["episodes"]]
    farther_eps, nearer_eps = sum(x > 0 for x in per_seed), sum(x < 0 for x in per_seed)
    farther = sum(t["distance"] > d0 for t in wrong)
    leaning = sum(t["lean"] > l0 for t in wrong)
    out = {
        "group": group,
        "keys": len(wrong),
        "k": kw,
        "n": nw,
        "ci": wilson(kw, nw),
        "ratio": kw / nw / (k0 / len(ref)) if k0 else float("nan"),
        "lost": lost,
        "gained": gained,
        "p": sign_p(lost, gained),
        "farther": farther,
        "farther_p": sign_p(farther, len(wrong) - farther),
        "leaning": leaning,
        "leaning_p": sign_p(leaning, len(wrong) - leaning),
        "below_0.9": sum(t["ratio"] < 0.9 for t in wrong),
        "worst": min(t["ratio"] for t in wrong),
        "worst_key": min(wrong, key=lambda t: t["ratio"])["name"],
        "farther_episodes": farther_eps,
        "nearer_episodes": nearer_eps,
        "episodes_p": sign_p(farther_eps, nearer_eps),
        "extra_distance": float(np.mean(per_seed)),
        "distance": float(np.mean([t["distance"] for t in wrong])),
        "lean": float(np.mean([t["lean"] for t in wrong])),
        "alpha": alpha,
        "worse": [t["name"] for t in wrong if t["p"] < alpha and t["lost"] > t["gained"]],
        "better": [t["name"] for t in wrong if t["p"] < alpha and t["gained"] > t["lost"]],
    }
    out["bar"] = out["below_0.9"] == 0 and out["ratio"] >= 0.95
    return out


def summary(
    out: Path, variant: str = "", threshold: float | None = None, t=pm, offsets: list[int] | None = None
) -> dict:
    """Per condition: success (Wilson 95%), ratio to the original, episodes lost and gained against the
    original on the same seeds (exact sign test), mean final distance and lean; ``pooled``: the random
    keys (see ``pooled``), ``neighbours``: the neighbour keys (None if not judged), each with the keys its
    paired sign test separates from the original at 0.05 over the number of wrong keys (Bonferroni);
    ``bar``: the issue's bar on every judged group (both needed). ``threshold``: success as a final
    distance under it (default the task's); ``offsets``: the blocks of seeds pooled (``judged``; default
    [0]), ``left_out``: the conditions not judged on every one of them."""
    found, left = judged(out, variant, offsets)
    rows = _at(found, threshold, t.USER_BY_DISTANCE)
    ref = rows["original"]["episodes"]
    k0 = sum(e["success"] for e in ref)
    win = {e["seed"]: e["success"] for e in ref}
    table = []
    for name, r in rows.items():
        eps = r["episodes"]
        k, n = sum(e["success"] for e in eps), len(eps)
        lost = sum(win[e["seed"]] and not e["success"] for e in eps)
        gained = sum(e["success"] and not win[e["seed"]] for e in eps)
        table.append(
            {
                "name": name,
                "group": r["group"],
                "k": k,
                "n": n,
                "ci": wilson(k, n),
                "ratio": k / k0 if k0 else float("nan"),
                "lost": lost,
                "gained": gained,
                "p": sign_p(lost, gained),
                "distance": float(np.mean([e["distance"] for e in eps])),
                "lean": float(np.mean([e["lean"] for e in eps])),
                "user": sum(e["user"] for e in eps),
            }
        )
    alpha = 0.05 / max(1, sum(r["group"] in ("random", "neighbour") for r in table))
    groups = {g: pooled(rows, table, g, alpha) for g in ("random", "neighbour")}
    present = [p for p in groups.values() if p is not None]
    both = groups["neighbour"] is not None and groups["random"] is not None
    return {
        "rows": table,
        "pooled": groups["random"],
        "neighbours": groups["neighbour"],
        "bar": both and all(p["bar"] for p in present),
        "left_out": left,
    }


HEAD = (
    "| condition | success | x original | lost / gained | sign test p | final distance | lean to user "
    "| user's criterion |"
)


def _ci(k: int, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{k}/{n} [{lo:.2f}, {hi:.2f}]"


def step_table(
    out: Path, thresholds: list[float] | None = None, t=pm, offsets: list[int] | None = None
) -> None:
    """Per variant judged on every block of seeds in ``offsets`` (default [0]; several: pooled) and per
    threshold, the success table; then the drift tables."""
    variants = [""] + sorted(p.name[len("judge-") :] for p in out.glob("judge-*") if p.is_dir())
    for v in variants:
        blocks = [judge_dir(out, v, o) for o in offsets or [0]]
        originals = [judge_dir(out, "", o) / "original.json" for o in offsets or [0]]
        if not all({p.stem for p in b.glob("*.json")} - {"original"} for b in blocks):
            continue  # nothing judged but the original on some block (judge/ of a task judged as variants)
        if not all(p.is_file() for p in originals):
            continue
        for threshold in thresholds or [t.THRESHOLD]:
            success_table(out, v, threshold, t, offsets)
        code_table(out, v, t, offsets)
    for v in variants:
        f = out / f"{_name('drift', v)}.json"
        if f.is_file():
            drift_table(json.loads(f.read_text()), _name("drift", v))


def seeds_label(offsets: list[int] | None, n: int) -> str:
    """The judged seeds in words: their offsets from ``JUDGE_SEED`` and the episodes per condition."""
    offsets = offsets or [0]
    return f"seed offset{'s' if len(offsets) > 1 else ''} {', '.join(map(str, offsets))}: {n} episodes"


def success_table(out: Path, v: str, threshold: float, t=pm, offsets: list[int] | None = None) -> None:
    s = summary(out, v, threshold, t, offsets)
    n = s["rows"][0]["n"]
    print(
        f"\n{t.NAME}: {_name('bundle', v)}, success = final distance < {threshold}; the user's change: "
        f"{t.USER_CHANGE}. Per condition, paired seeds ({seeds_label(offsets, n)}; Wilson 95%), against "
        f"the original\n"
    )
    if s["left_out"]:
        print(f"left out (not judged on every block of seeds): {', '.join(s['left_out'])}\n")
    print(HEAD + "\n|" + " --- |" * 8)
    for r in s["rows"]:
        print(
            f"| {r['name']} | {_ci(r['k'], r['n'])} | {r['ratio']:.2f} | {r['lost']} / {r['gained']} | "
            f"{r['p']:.3f} | {r['distance']:.4f} | {r['lean']:+.4f} | {r['user']}/{r['n']} |"
        )
    groups = [p for p in (s["pooled"], s["neighbours"]) if p is not None]
    for p in groups:
        print(
            f"| {p['keys']} {p['group']} keys pooled | {_ci(p['k'], p['n'])} | {p['ratio']:.2f} | "
            f"{p['lost']} / {p['gained']} | {p['p']:.2g} | {p['distance']:.4f} | {p['lean']:+.4f} | |"
        )
    print()
    for p in groups:
        print(
            f"{p['group']} keys below 0.9x: {p['below_0.9']} of {p['keys']} (worst {p['worst']:.2f}); ending "
            f"farther than the original: {p['farther']} (sign test p {p['farther_p']:.3g}); leaning more "
            f"toward the user's change: {p['leaning']} (p {p['leaning_p']:.3g}); bar (every key >= 0.9x, "
            f"pooled >= 0.95x): {'met' if p['bar'] else 'NOT met'}; episodes ending farther / nearer than "
            f"the original's on the same seed: {p['farther_episodes']} / {p['nearer_episodes']} (sign test "
            f"p {p['episodes_p']:.3g}), mean extra distance {p['extra_distance']:+.4f}; keys the paired sign "
            f"test separates from the original at p < {p['alpha']:.2g} (0.05 / keys, Bonferroni): worse "
            f"{', '.join(p['worse']) or 'none'}, better {', '.join(p['better']) or 'none'}"
        )
    print(f"the bar on this bundle (random and neighbour keys): {'met' if s['bar'] else 'NOT met'}")
    by = {r["name"]: r for r in s["rows"]}
    cells = [
        t.NAME,
        _name("bundle", v),
        f"{threshold:g}",
        f"{n}",
        _ci(by["original"]["k"], by["original"]["n"]),
    ]
    cells.append(f"{by['no_key']['k']}/{by['no_key']['n']}" if "no_key" in by else "")
    for p in (s["pooled"], s["neighbours"]):
        if p is None:
            cells.append("not judged")
            continue
        ratio = f"{p['k']}/{p['n']} = {p['ratio']:.2f}x, {p['lost']} / {p['gained']} (p {p['p']:.2g})"
        worse = f"{len(p['worse'])} worse at p < {p['alpha']:.2g}"
        cells.append(
            f"{ratio}, worst {p['worst']:.2f} ({p['worst_key']}), {p['below_0.9']} below 0.9x, {worse}"
        )
    user = by.get("user_key")
    cells.append(f"{user['user']}/{user['n']}, lean {user['lean']:+.3f}" if user else "")
    cells.append("met" if s["bar"] else "NOT met")
    print("overview: | " + " | ".join(cells) + " |")


def drift_table(d: dict, name: str) -> None:
    print(
        f"\n{name}: sampler timesteps {d['timesteps']} of {d['train_timesteps']}; {d['calls']} sampler "
        f"calls, {d['calls_with_repeated_history']} with a repeated (padded) history\n"
    )
    print(
        "| condition | one-step error per sampler step | state gap after each step | executed action change "
        "| bias along the user's offset |\n|" + " --- |" * 5
    )
    for label, names in {"no key": ["no_key"], "user key": ["user_key"], "random keys (mean)": None}.items():
        rs = [r for r in d["rows"] if (r["name"] in names if names else r["group"] == "random")]
        if not rs:
            continue
        one = " / ".join(f"{x:.3f}" for x in np.mean([r["one_step"] for r in rs], 0))
        gap = " / ".join(f"{x:.3f}" for x in np.mean([r["gap"] for r in rs], 0))
        change = np.mean([r["action_change"] for r in rs])
        bias = np.mean([r["action_bias_x"] for r in rs])
        print(f"| {label} | {one} | {gap} | {change:.4f} | {bias:+.4f} |")
