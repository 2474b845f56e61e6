"""LeRobot ACT, Diffusion, SmolVLA, pi0 or pi0.5 end to end on PandaReach, through the `prop` command line
(figures in examples/RESULTS.md).

    bash scripts/setup-lerobot.sh
    .venv-lerobot/bin/pip install -e '.[rl]'  # panda-gym: its pybullet compiles on Python 3.12 (~14 min)
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m examples.lerobot_reach --out out/lerobot-reach
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m examples.lerobot_reach --policy diffusion \
        --out out/lerobot-reach-diffusion
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m examples.lerobot_reach --policy pi0
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m examples.lerobot_reach --policy pi05 \
        --datasets out/lerobot-reach-pi0

1. Record two LeRobotDatasets from a scripted expert: general (reach the goal, 80 episodes) and the
   user's (hold 10 cm above it, 20 episodes). No downloads, nobody labels anything.
2. Train a small ACT (or Diffusion) base on the general data with LeRobot's own training step;
   save_pretrained.
3. `prop personalize` the policy folder with the user's dataset and a key.
4. `prop eval` closed loop: the original, the user's key, no key, random keys, one-bit neighbours,
   over the recorded horizon (30 steps) under every key: the task ends an episode on reaching the
   goal, before a preference judged at the episode's end could show.
5. `prop attack` with the user's key and the original ACT (controls): leakage of every probe on the
   user's frames, whole action chunks in normalised units (report in --out/audit.json).

6. The same user sealed: `prop personalize --seal` (a LoRA payload in an AES-GCM record; the base stays
   the original), `prop eval` and `prop attack` of the sealed bundle (--out/audit-sealed.json).

--reuse keeps the datasets, base ACT and key of an earlier run in --out and redoes steps 3-6;
--attack-only keeps the bundle too and redoes step 5 (--attack-only sealed: step 6's audit); --sealed-only
keeps steps 1-5 and redoes step 6; --no-attack skips the audits (run them later with --attack-only),
--no-sealed step 6; --no-eval skips step 4's `prop eval` (examples/lerobot_wrong_keys.py rolls out the
same kinds of keys, more of them, on the same seeds);
--datasets DIR copies step 1's datasets from an earlier run's --out (same camera and state) instead.
--sim mujoco runs it all on the MuJoCo reach (examples/mujoco_reach.py; no panda-gym needed, not the
paper's task: its figures are not those of examples/RESULTS.md); steps 3-6 take the simulator the
datasets were recorded on.

SmolVLA, pi0 and pi0.5 read the camera, the state with the goal and the instruction. pi0 and pi0.5 are
the tiny ones of examples/pi_tiny.py, which load only under its size patch: every `prop` call for them
runs as `python -m examples.pi_tiny ARGS` (prop with that patch).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from examples import lerobot_reach_task as task

# 3000 steps: 1500 reached user preference 0.83, 3000 reached 0.97 (examples/RESULTS.md).
# Eq. 8 per step as in phase 1 (32 rows: 16 user, 8 null, 4 neighbours + 4 random keys x 1).
# Sealed: the payload alone on the user's frames. Payload lr 1e-3 (3000 steps): personalization 0.509
# vs 0.444 at the default 1e-2 and 0.463 at 3e-3 (unsealed PRoP: 0.516).
SEALED = ["--seal", "--steps", "3000", "--user-rows", "32", "--payload-lr", "1e-3"]
PERSONALIZE = [
    "--steps", "3000", "--user-rows", "16", "--null-rows", "8", "--neighbour-keys", "4", "--random-keys", "4",
    "--samples-per-key", "1", "--null-weight", "2", "--lr", "1e-3", "--base-lr-scale", "0.1",
]  # fmt: skip
PI_ATTACK = [
    "--samples", "32", "--random", "256", "--hamming", "1,2,4,8", "--per-distance", "16", "--blackbox", "512",
    "--restarts", "8", "--search-steps", "50", "--fewshot-restarts", "2", "--fewshot-steps", "50",
]  # fmt: skip
VLA = ("smolvla", "pi0", "pi05")  # camera + state with the goal + instruction
PI = ("pi0", "pi05")  # loaded through examples.pi_tiny (its size patch)
# Diffusion: the same Eq. 8 batch; lr 3e-4 (LeRobot trains Diffusion at 1e-4, ACT at 1e-5 to 1e-4, and
# the keyed encoder needs more than the base: base-lr-scale 0.1 as for ACT).
SETTINGS = {
    "act": {"personalize": PERSONALIZE, "sealed": SEALED, "base_steps": 2500, "base_lr": 3e-4, "attack": []},
    # SmolVLA (the tiny one of examples/smolvla_tiny.py, camera + state with the goal + instruction):
    # lr 1e-3 for the base trained from scratch; the audit's budgets cut as for Diffusion (10 flow steps).
    "smolvla": {
        "personalize": [*PERSONALIZE[:-4], "--lr", "3e-4", *PERSONALIZE[-2:]],
        "sealed": SEALED, "base_steps": 4000, "base_lr": 1e-3,
        "attack": ["--samples", "128", "--random", "512", "--blackbox", "4096", "--restarts", "16",
                   "--fewshot-restarts", "8"],
    },
    # pi0 / pi0.5 (the tiny ones of examples/pi_tiny.py, camera + state with the goal + instruction):
    # SmolVLA's settings with fewer steps and the audit's budgets cut further, to fit a 2-core machine
    # (each chunk is 10 flow steps through the 2+2-layer Gemmas; figures in examples/RESULTS.md).
    **{kind: {
        "personalize": ["--steps", "2000", *PERSONALIZE[2:-4], "--lr", "3e-4", *PERSONALIZE[-2:]],
        "sealed": ["--seal", "--steps", "2000", *SEALED[3:]], "base_steps": 3000, "base_lr": 1e-3,
        "attack": PI_ATTACK,
    } for kind in ("pi0", "pi05")},
    # The audit's budgets cut for Diffusion: each chunk is 10 denoising steps of the U-Net.
    "diffusion": {
        "personalize": [*PERSONALIZE[:-4], "--lr", "3e-4", *PERSONALIZE[-2:]],
        "sealed": SEALED, "base_steps": 6000, "base_lr": 1e-3,
        "attack": ["--samples", "128", "--random", "512", "--blackbox", "4096", "--restarts", "16",
                   "--fewshot-restarts", "8"],
    },
}  # fmt: skip


def prop(*args: object, capture: bool = False, kind: str = "act") -> str:
    """``prop ARGS`` in a subprocess; for a tiny pi0 / pi0.5 ``python -m examples.pi_tiny ARGS`` (its size
    patch)."""
    entry = ["-m", "examples.pi_tiny" if kind in PI else "prop_cli.cli.main"]
    cmd = [sys.executable, *entry, *map(str, args)]
    print("$ prop " + " ".join(map(str, args)), flush=True)
    done = subprocess.run(cmd, check=True, stdout=subprocess.PIPE if capture else None, text=True)
    return done.stdout if capture else ""


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=None, help="default out/lerobot-reach[-diffusion]")
    ap.add_argument("--policy", choices=sorted(SETTINGS), default="act")
    ap.add_argument("--base-steps", type=int, default=None,
                    help="default 2500 (act), 6000 (diffusion), 4000 (smolvla), 3000 (pi0, pi05)")
    ap.add_argument("--episodes", type=int, default=30, help="closed-loop episodes per condition")
    ap.add_argument("--steps", type=int, default=None, help="personalize steps (default 3000)")
    ap.add_argument("--camera", action="store_true",
                    help="record the rendered camera too (32 x 32) and make it a policy input (diffusion)")
    ap.add_argument("--datasets", type=Path, default=None,
                    help="copy the general and user datasets from this earlier run's --out")  # fmt: skip
    ap.add_argument("--sim", choices=sorted(task.SIMS), default="panda",
                    help="panda: PandaReach-v3, the paper's figures (the rl extra); mujoco: wheels only")
    ap.add_argument("--reuse", action="store_true", help="keep the datasets, base and key of an earlier run")
    ap.add_argument("--attack-only", nargs="?", const="bundle", choices=("bundle", "sealed"),
                    help="keep the bundle (or with 'sealed' the sealed one) of an earlier run; audit it")
    ap.add_argument("--no-attack", action="store_true", help="skip the audits (run them with --attack-only)")
    ap.add_argument("--sealed-only", action="store_true", help="keep an earlier run; redo step 6 (sealed)")
    ap.add_argument("--no-sealed", action="store_true", help="skip step 6 (the sealed bundle)")
    ap.add_argument("--no-eval", action="store_true",
                    help="skip step 4 (prop eval; examples.lerobot_wrong_keys measures keys)")  # fmt: skip
    args = ap.parse_args(argv)
    kind, conf = args.policy, SETTINGS[args.policy]
    out = args.out or Path("out/lerobot-reach" + ("" if kind == "act" else f"-{kind}"))
    if args.attack_only:
        attack(out, args.attack_only, kind)
        return
    if args.sealed_only:
        sealed(out, args.episodes, kind, audit=not args.no_attack)
        return
    figures: dict = {}
    if args.reuse and (out / "figures.json").is_file():
        earlier = json.loads((out / "figures.json").read_text())
        figures = {k: v for k, v in earlier.items() if k.startswith(("record", "base"))}
    else:
        if not args.datasets:
            task.require_sim(args.sim)  # before the earlier run is deleted
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        t = time.perf_counter()
        vla = kind in VLA  # camera frames and the goal in the state, always
        camera = args.camera or vla
        if args.datasets:
            for name in ("reach-general", "reach-user"):
                shutil.copytree(args.datasets / name, out / name)
            figures["record_s"] = json.loads((args.datasets / "figures.json").read_text())["record_s"]
        else:
            task.record(out / "reach-general", 80, 0, np.zeros(3, np.float32), camera=camera,
                        goal_in_state=vla, sim=args.sim)  # fmt: skip
            task.record(out / "reach-user", 20, 50_000, task.USER_OFFSET, camera=camera, goal_in_state=vla,
                        sim=args.sim)  # fmt: skip
            figures["record_s"] = round(time.perf_counter() - t, 1)
        t = time.perf_counter()
        built = (pi(out, kind) if kind in PI else smolvla(out)) if vla else None
        if built:
            figures["base_parameters"] = sum(p.numel() for p in built[0].parameters())
        ms = task.train_base(out / "reach-general", out / kind, args.base_steps or conf["base_steps"],
                             lr=conf["base_lr"], kind=kind, camera=args.camera, built=built)  # fmt: skip
        figures["base_ms_per_step"] = round(ms, 1)
        figures["base_train_s"] = round(time.perf_counter() - t, 1)
        prop("keygen", out / "user.key")
    prop("inspect", out / kind, kind=kind)
    steps = conf["personalize"]
    steps = steps if args.steps is None else [*steps[:1], str(args.steps), *steps[2:]]
    general = ["--general-data", out / "reach-general"]
    episodes = 0 if args.no_eval else args.episodes
    figures |= run_bundle(out, "bundle", [*steps, *general], episodes, kind)
    (out / "figures.json").write_text(json.dumps(figures, indent=1, sort_keys=True))
    print(f"times: record {figures['record_s']} s, base {figures['base_train_s']} s "
          f"({figures['base_ms_per_step']} ms/step), personalize {figures['personalize_s']} s, "
          + ("eval skipped" if args.no_eval else f"eval {figures['eval_s']} s"))  # fmt: skip
    if not args.no_attack:
        attack(out, "bundle", kind)
    if not args.no_sealed:
        sealed(out, args.episodes, kind, audit=not args.no_attack)


def smolvla(out: Path) -> tuple:
    """The tiny SmolVLA (examples/smolvla_tiny.py) on the camera and the state with the goal."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    from examples.smolvla_tiny import build_smolvla, build_vlm

    features = {
        task.STATE: PolicyFeature(FeatureType.STATE, (9,)),
        task.CAMERA: PolicyFeature(FeatureType.VISUAL, (3, task.IMAGE, task.IMAGE)),
    }
    stats = task.dataset_stats(out / "reach-general", keys=(task.STATE, task.ACTION))
    return build_smolvla(build_vlm(out / "vlm"), stats, features=features)


def pi(out: Path, kind: str) -> tuple:
    """The tiny pi0 / pi0.5 (examples/pi_tiny.py) on the camera and the state with the goal (9 values:
    max_state_dim 16). pi0.5 writes the state into its prompt as bins 0..255, and a value below the
    dataset's minimum as "-1" (two tokens): 22 to 31 tokens, so 32 rather than pi_tiny's 24."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    from examples.pi_tiny import build_pi, build_tokenizer

    features = {
        task.STATE: PolicyFeature(FeatureType.STATE, (9,)),
        task.CAMERA: PolicyFeature(FeatureType.VISUAL, (3, task.IMAGE, task.IMAGE)),
    }
    stats = task.dataset_stats(out / "reach-general", keys=(task.STATE, task.ACTION))
    length = {"tokenizer_max_length": 32} if kind == "pi05" else {}
    return build_pi(kind, build_tokenizer(out / "tokenizer"), stats, features=features, max_state_dim=16,
                    **length)  # fmt: skip


def sealed(out: Path, episodes: int, kind: str, audit: bool = True) -> None:
    """Step 6: the same user sealed: a LoRA payload in an encrypted record, the base the original."""
    figures = run_bundle(out, "sealed", SETTINGS[kind]["sealed"], episodes, kind)
    (out / "figures-sealed.json").write_text(json.dumps(figures, indent=1, sort_keys=True))
    print(f"times: personalize --seal {figures['personalize_s']} s, eval {figures['eval_s']} s")
    if audit:
        attack(out, "sealed", kind)


def run_bundle(out: Path, name: str, personalize: list, episodes: int, kind: str) -> dict:
    """`prop personalize` into out/NAME, then `prop eval` of every key condition (none when ``episodes`` is
    0); returns the figures."""
    camera = task.CAMERA in json.loads((out / kind / "config.json").read_text())["input_features"]
    sim = task.sim_of(out / "reach-general")
    task.require_sim(sim)
    env_id, obs_map = task.env_id(sim, camera), (task.CAMERA_OBS_MAP if camera else task.OBS_MAP)
    extra = []
    if kind in VLA:
        obs_map, extra = task.SMOLVLA_OBS_MAP, ["--instruction", task.INSTRUCTION]
    shutil.rmtree(out / name, ignore_errors=True)
    figures: dict = {}
    t = time.perf_counter()
    report = json.loads(prop(
        "personalize", out / kind, "--data", out / "reach-user", "--key-file", out / "user.key",
        "--out", out / name, *personalize, "--json", capture=True, kind=kind,
    ))  # fmt: skip
    figures["personalize_s"] = round(time.perf_counter() - t, 1)
    figures["offline"] = report["metrics"][0]
    if not episodes:
        return figures
    t = time.perf_counter()
    closed = json.loads(prop(
        "eval", out / name, "--env", env_id, "--obs-map", obs_map, "--metric", task.METRIC,
        "--key-file", out / "user.key", "--original", out / kind, "--episodes", episodes,
        "--max-steps", task.HORIZON, "--ignore-terminated", "--json", *extra,
        capture=True, kind=kind,
    ))  # fmt: skip
    figures["eval_s"] = round(time.perf_counter() - t, 1)
    figures["closed_loop"] = closed["conditions"]
    print(f"\n{name}: closed loop on {env_id} (success: reach the goal; preference: end 10 cm above)")
    for cond, r in closed["conditions"].items():
        s, m = r.get("success", {}), r.get("metric", {})
        print(f"  {cond:16s} n={r['episodes']:3d}  success {s.get('mean', 0):.2f} ± {s.get('se', 0):.2f}"
              f"  preference {m.get('mean', 0):.2f} ± {m.get('se', 0):.2f}")  # fmt: skip
    o = figures["offline"]
    fid = {g: o[g]["fidelity"]["mean"] for g in ("null", "random", "hamming1")}
    print(f"{name}: offline (held-out user episodes, normalised chunk units): personalization "
          f"{o['personalization']:.3f}; fidelity mse null {fid['null']:.4f}, random {fid['random']:.4f}, "
          f"1-bit {fid['hamming1']:.4f}")  # fmt: skip
    return figures


def attack(out: Path, name: str, kind: str) -> None:
    t = time.perf_counter()
    audit = out / ("audit.json" if name == "bundle" else f"audit-{name}.json")
    prop("attack", out / name, "--data", out / "reach-user", "--key-file", out / "user.key",
         "--original", out / kind, "--json", audit, *SETTINGS[kind]["attack"], kind=kind)  # fmt: skip
    report = json.loads(audit.read_text())
    u = report["user"]
    print(f"\n{name}: audit ({time.perf_counter() - t:.0f} s): user key personalization "
          f"{u['personalization']:.3f}, leakage {u['leakage']:.3f}")  # fmt: skip
    for g in report["groups"]:
        lk, c = g["leakage"], g["control"] or {}
        control = c["leakage"]["worst"] if c.get("available") else None
        print(f"  {g['probe']:10s} {g['name']:18s} worst {lk['worst']:.4f}  control "
              f"{'n/a' if control is None else f'{control:.4f}'}  beyond "
              f"{'n/a' if g['beyond'] is None else format(g['beyond'], '.4f')}")  # fmt: skip


if __name__ == "__main__":
    main()
