"""One table of prop's speed: every figure a ratio against a baseline measured in the same run, or a time.

    python -m benchmarks.table            # the sizes below marked "default" (a few minutes on 2 cores)
    python -m benchmarks.table --quick    # smoke test: the smallest of each (well under a minute)
    python -m benchmarks.table --full     # everything: 50M-parameter steps, 512 users, 2000 steps
    python -m benchmarks.table --small    # issue 40's small-model rows and their goals (about a minute)

Rows:
- step: a PRoP training step (the trainer's make_batch, keyed forward, Eq. 8 loss, prop's Adam) vs a
  plain fine-tuning step (torch.optim.Adam) of the same model and batch rows, by model size (an
  MLP 4-W-W-W-2; 38k is the IL example's 4-192-192-2). CPU time, interleaved, median.
- personalize: the library's trainer (``prop_cli.train.personalize``, evaluation included) on the IL base, by
  number of users (each with its own key and data) and by rows of data per user. Seconds.
- audit: key x sample evaluations per second of the audit's default key probes (``audit.audit``, its
  report's ``speed``), against a bare loop of the same forwards (``KeyedModel.run_keys``).
- audit wall: issue 44's `prop attack` command (--hamming 1..8 --search relaxed,latent, --json, --plot
  when matplotlib is there) run as a user runs it, on the IL and digits examples' unsealed bundles (default
  personalize settings); seconds against the issue's 60 s goal. The tiny ACT's row (``tests/plugin/tiny.py``:
  LeRobot ACT with a ResNet-18 camera, unsealed) runs in LeRobot's own environment (``--lerobot-python``;
  default: ``.venv-lerobot`` in the repository or beside the running environment), built and audited in
  subprocesses (``prop attack BUNDLE --data user --key-file user.key --json``, default probes and budget);
  without that environment the table says the row was skipped and why.
- inference: per call after loading, keyed / no key, batch 1 and 256: torch (key folded in memory),
  onnxruntime split form (encoder.onnx once, policy.onnx per call) and onnxruntime folded in memory.
- import: ``import torch, torch._dynamo`` vs ``import torch`` (what prop's own Adam avoids).
- small (``--small`` only): the step at 38k parameters and the onnxruntime split form, each with issue
  40's goal (step <= 1.5x plain, split <= 1.05x base.onnx) and whether this run met it. The audit's key
  probe row (10M evaluations/s) is another part of issue 40 and is not measured here.

Threads follow prop's policy (``prop_cli.threads``) unless OMP_NUM_THREADS is set; the table says which.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_core import interleaved, train_steps, wide_example
from examples.il_task import write_example

# Sizes per mode: (widths of the 4-W-W-W-2 MLP, users, rows per user, personalize steps).
MODES = {
    "quick": {"widths": [None, 700], "users": [1, 8], "rows": [1000, 10000], "steps": 40, "rounds": 3},
    "default": {"widths": [None, 700, 2236], "users": [1, 8, 64], "rows": [1000, 10000, 100000],
                "steps": 200, "rounds": 5},
    "full": {"widths": [None, 700, 2236, 5000], "users": [1, 8, 64, 512], "rows": [1000, 10000, 100000],
             "steps": 2000, "rounds": 5},
    "small": {"widths": [None], "rounds": 7},
}  # fmt: skip
# Issue 40's goals for the small-model rows (--small): row title's start -> the most the ratio may be.
SMALL_GOALS = {
    "step, 38k": 1.5,
    "step with far codes and pull, 38k": 1.5,
    "run batch 1: onnxruntime split": 1.05,
    "run batch 256: onnxruntime split": 1.05,
}


def machine() -> str:
    name = platform.processor() or platform.machine()
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        name = next(
            line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name")
        )
    except (OSError, subprocess.CalledProcessError, StopIteration):
        pass
    from prop_cli.threads import cores

    return f"{name}, {cores()} cores, torch {torch.__version__}"


def _params(path: Path) -> int:
    from prop_adapters import load_checkpoint

    return sum(p.numel() for p in load_checkpoint(str(path)).module.parameters())


def step_rows(tmp: Path, il: dict, mode: dict) -> list[tuple[str, str, str]]:
    from prop_cli.threads import configure

    rows = []
    for width in mode["widths"]:
        paths = il if width is None else wide_example(tmp, width)
        n = _params(paths["base"])
        threads = configure(n)
        big = n > 5_000_000
        t = train_steps(paths, il["mine"], rounds=3 if big else mode["rounds"], reps=1 if big else 20)
        plain, prop, full = t["plain fine-tuning step"], t["PRoP step"], t["PRoP step, far codes and pull"]
        what = f"{_count(n)} parameters ({threads} thread{'s' * (threads > 1)})"
        rows.append(
            (f"step, {what}", f"{prop / plain:.2f}x",
             f"PRoP {prop * 1e3:.2f} ms vs plain {plain * 1e3:.2f} ms CPU")
        )  # fmt: skip
        if mode is MODES["small"]:  # the trainer's defaults: + far codes and the delta pull (bench_core)
            rows.append(
                (f"step with far codes and pull, {what}", f"{full / plain:.2f}x",
                 f"PRoP {full * 1e3:.2f} ms vs plain {plain * 1e3:.2f} ms CPU")
            )  # fmt: skip
    return rows


def _count(n: int) -> str:
    return f"{n / 1e6:.0f}M" if n >= 1e6 else f"{n / 1e3:.0f}k"


def _users(n_users: int, rows: int, seed: int) -> list:
    from prop_cli.datasources import Dataset
    from prop_cli.train import User

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_users):
        x = rng.uniform(-1, 1, (rows, 4)).astype(np.float32)
        y = np.tanh(x[:, :2] @ rng.standard_normal((2, 2))).astype(np.float32)
        out.append(User(Dataset(x, y, "bench"), rng.integers(0, 2, 128, dtype=np.uint8)))
    return out


def personalize_rows(il: dict, mode: dict) -> list[tuple[str, str, str]]:
    from prop_adapters import load_checkpoint
    from prop_cli.config import PersonalizeConfig
    from prop_cli.threads import configure
    from prop_cli.train import personalize

    def seconds(n_users: int, rows: int) -> float:
        loaded = load_checkpoint(str(il["base"]))
        configure(_params(il["base"]))
        t = time.perf_counter()
        personalize(loaded, _users(n_users, rows, n_users), PersonalizeConfig.of(steps=mode["steps"]))
        return time.perf_counter() - t

    out = []
    base = None
    for n in mode["users"]:
        s = seconds(n, 1000)
        base = base or s
        out.append((f"personalize, {n} user{'s' * (n > 1)} x 1000 rows, {mode['steps']} steps",
                    f"{s / base:.2f}x", f"{s:.1f} s wall (1 user = 1.00x)"))  # fmt: skip
    base = None
    for r in mode["rows"]:
        s = seconds(1, r)
        base = base or s
        out.append((f"personalize, 1 user x {r} rows, {mode['steps']} steps",
                    f"{s / base:.2f}x", f"{s:.1f} s wall ({mode['rows'][0]} rows = 1.00x)"))  # fmt: skip
    return out


def bundle_for(tmp: Path, il: dict, steps: int) -> tuple[Path, np.ndarray]:
    from prop_cli.api import KeySource, personalize_checkpoint
    from prop_cli.config import PersonalizeConfig

    key = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    out = tmp / "il.prop"
    personalize_checkpoint(str(il["base"]), [(il["mine"], KeySource(key, "file"))], out,
                           PersonalizeConfig.of(steps=steps), general=il["general"])  # fmt: skip
    return out, key


def audit_rows(bundle_path: Path, il: dict, key: np.ndarray, quick: bool) -> list[tuple[str, str, str]]:
    from prop_cli.attack import probes
    from prop_cli.attack.audit import audit
    from prop_cli.bundle import load_bundle
    from prop_cli.config import AuditSettings
    from prop_cli.core.key_sampling import random_keys
    from prop_cli.core.keyed_model import KEY_ROWS, key_codes
    from prop_cli.datasources import load_data

    bundle = load_bundle(bundle_path)
    # drift needs the original, which an unsealed bundle's own base is not (the audit below has none)
    key_probes = [p.name for p in probes.PROBES if p.kind == "key" and p.default and p.needs != "original"]
    settings = AuditSettings(
        probes=key_probes, random=1024 if quick else 4096, per_distance=64 if quick else 256
    )
    report = audit(bundle, load_data(il["mine"]), [key], settings)
    rate = report["speed"]["evaluations_per_second"]

    km = bundle.keyed.eval()
    x = torch.from_numpy(load_data(il["mine"]).x[: settings.samples])
    keys = random_keys(KEY_ROWS // len(x) * 8, bundle.key_bits, np.random.default_rng(1))
    codes = key_codes(keys, bundle.key_encoding)
    per = max(1, KEY_ROWS // len(x))

    def bare() -> None:
        with torch.inference_mode():
            for i in range(0, len(codes), per):
                km.run_keys(x, km.layer_deltas(codes[i : i + per]))

    # Wall time, as the audit's own counter measures.
    secs = interleaved({"bare": bare}, rounds=3, reps=2, clock=time.perf_counter)["bare"]
    bare_rate = len(codes) * len(x) / secs
    return [
        (f"audit key probes ({', '.join(key_probes)}), key x sample evals/s", f"{rate / bare_rate:.2f}x",
         f"{rate / 1e6:.2f}M/s in the audit vs {bare_rate / 1e6:.2f}M/s bare run_keys forwards (wall)"),
    ]  # fmt: skip


# The table's row groups, in order (--rows).
GROUPS = ("step", "personalize", "audit", "audit-wall", "inference", "import")

# issue 44's goal for its command on a quiet 2-core machine.
AUDIT_GOAL_S = 60.0


def audit_wall_rows(tmp: Path, il: dict, quick: bool) -> list[tuple[str, str, str]]:
    """The issue-44 command through the installed `prop` in a fresh process, on IL and digits bundles."""
    import importlib.util

    from examples.digits_task import write_example as write_digits
    from prop_cli.api import KeySource, personalize_checkpoint, read_key_file
    from prop_cli.config import PersonalizeConfig

    prop = str(Path(sys.executable).parent / "prop")
    plot = importlib.util.find_spec("matplotlib") is not None
    out = []
    for name, paths in (("IL", il), ("digits", write_digits(tmp / "digits", seed=0))):
        key_file = tmp / f"{name}.bin"
        subprocess.run([prop, "keygen", str(key_file)], check=True, capture_output=True)
        key = read_key_file(key_file)
        bundle = tmp / f"{name}-audit.prop"
        personalize_checkpoint(str(paths["base"]), [(paths["mine"], KeySource(key, "file"))], bundle,
                               PersonalizeConfig.of(steps=200 if quick else 2000))  # fmt: skip
        cmd = [prop, "attack", str(bundle), "--data", str(paths["mine"]), "--key-file", str(key_file),
               "--hamming", "1..8", "--search", "relaxed,latent", "--json", str(tmp / f"{name}-a.json"),
               *(["--plot", str(tmp / f"{name}-a.png")] if plot else [])]  # fmt: skip
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - t0
        inner = json.loads((tmp / f"{name}-a.json").read_text()).get("speed", {}).get("wall_seconds")
        probes = f" (the probes {inner:.1f} s)" if inner is not None else ""
        out.append((f"audit wall, issue 44's command on {name}", f"{wall / AUDIT_GOAL_S:.2f}x",
                    f"{wall:.1f} s wall{probes} vs the {AUDIT_GOAL_S:.0f} s goal"))  # fmt: skip
    return out


REPO = Path(__file__).resolve().parents[1]
TINY_ACT_BUILD = (
    "import sys; from pathlib import Path; from tests.plugin.tiny import build; build(Path(sys.argv[1]))"
)


def lerobot_python(given: Path | None) -> tuple[Path | None, str]:
    """LeRobot's environment's python: ``given``, else ``.venv-lerobot`` in the repository, else beside
    the running environment; (None, why) when there is none."""
    if given is not None:
        return (given, "") if given.is_file() else (None, f"--lerobot-python {given} does not exist")
    for venv in (REPO / ".venv-lerobot", Path(sys.prefix).parent / ".venv-lerobot"):
        if (venv / "bin" / "python").is_file():
            return venv / "bin" / "python", ""
    return None, (
        f"no LeRobot environment ({REPO / '.venv-lerobot'}; scripts/setup-lerobot.sh makes it, or pass "
        "--lerobot-python)"
    )


def tiny_act_row(tmp: Path, python: Path | None, why: str) -> tuple[tuple[str, str, str] | None, str | None]:
    """The audit's wall time on a tiny ACT, as a user runs it, in LeRobot's environment: (row, None), or
    (None, the line saying why it was skipped)."""
    what = "audit wall, tiny ACT (unsealed, default probes)"
    if python is None:
        return None, f"{what}: skipped: {why}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH"))
                                                       if p)}  # fmt: skip
    work = tmp / "tiny-act"
    built = subprocess.run([str(python), "-c", TINY_ACT_BUILD, str(work)], cwd=REPO, env=env,
                           capture_output=True, text=True)  # fmt: skip
    if built.returncode != 0:
        last = (built.stderr.strip().splitlines() or ["(no output)"])[-1]
        return None, f"{what}: skipped: building the tiny ACT in {python} failed: {last}"
    report = tmp / "tiny-act.json"
    prop = python.parent / "prop"  # the environment's command, as a user runs it
    launch = [str(prop)] if prop.is_file() else [str(python), "-m", "prop_cli.cli.main"]
    cmd = [*launch, "attack", str(work / "unsealed"), "--data",
           str(work / "user"), "--key-file", str(work / "user.key"), "--json", str(report)]  # fmt: skip
    t0 = time.perf_counter()
    ran = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if ran.returncode != 0:
        last = (ran.stderr.strip().splitlines() or ["(no output)"])[-1]
        return None, f"{what}: skipped: prop attack exited {ran.returncode}: {last}"
    rep = json.loads(report.read_text())
    speed = rep.get("speed", {})
    stages = speed.get("stage_seconds", {})
    top = sorted(stages.items(), key=lambda kv: -kv[1])[:3]
    inner = speed.get("wall_seconds")
    parts = [f"the probes {inner:.1f} s" if inner is not None else None,
             ", ".join(f"{k} {v:.1f} s" for k, v in top) or None]  # fmt: skip
    cov = rep.get("coverage") or {}
    if cov.get("cut_short") or cov.get("not_tried"):
        parts.append(f"budget ran out: cut short {cov.get('cut_short')}, not tried {cov.get('not_tried')}")
    detail = "; ".join(p for p in parts if p)
    return (what, f"{wall / AUDIT_GOAL_S:.2f}x",
            f"{wall:.1f} s wall ({detail}) vs the {AUDIT_GOAL_S:.0f} s goal"), None  # fmt: skip


def inference_rows(bundle_path: Path, key: np.ndarray, quick: bool) -> list[tuple[str, str, str]]:
    from prop_cli.bundle import load_bundle
    from prop_cli.core.keyed_model import key_codes
    from prop_cli.run.onnx import OnnxRunner, export_onnx

    bundle = load_bundle(bundle_path)
    res = export_onnx(bundle, key=key)
    code = key_codes(key, bundle.key_encoding)
    module, folded = bundle.keyed.module, bundle.keyed.fold(code)
    ort = {
        "base": OnnxRunner(res.out, None, threads=1),
        "split": OnnxRunner(res.out, code=code.numpy(), threads=1, fold=False),
        "folded": OnnxRunner(res.out, code=code.numpy(), threads=1, fold=True),
    }
    rows = []
    for batch in (1, 256):
        x = np.random.default_rng(batch).standard_normal((batch, *bundle.manifest["io"]["input_shape"]))
        x = x.astype(np.float32)
        xt = torch.from_numpy(x)

        fns = {"torch base": _torch_call(module, xt), "torch folded": _torch_call(folded, xt)}
        fns.update({f"ort {k}": _ort_call(p, x) for k, p in ort.items()})
        reps = (300 if quick else 2000) if batch == 1 else (30 if quick else 200)
        t = interleaved(fns, rounds=3 if quick else 7, reps=reps)
        for name, (a, b) in {
            "torch, key folded / no key": ("torch folded", "torch base"),
            "onnxruntime split form / base.onnx": ("ort split", "ort base"),
            "onnxruntime folded in memory / base.onnx": ("ort folded", "ort base"),
        }.items():
            rows.append((f"run batch {batch}: {name}", f"{t[a] / t[b]:.3f}x",
                         f"{t[a] * 1e6:.1f} vs {t[b] * 1e6:.1f} us CPU"))  # fmt: skip
    return rows


def small_rows(tmp: Path, il: dict) -> list[tuple[str, str, str]]:
    """Issue 40's small-model rows: the 38k step and the split ONNX form, each with its goal."""
    rows = step_rows(tmp, il, MODES["small"])
    bundle, key = bundle_for(tmp, il, 200)
    rows += [r for r in inference_rows(bundle, key, quick=False) if "split" in r[0]]
    out = []
    for what, ratio, fig in rows:
        goal = next((g for start, g in SMALL_GOALS.items() if what.startswith(start)), None)
        if goal is not None:
            met = "met" if float(ratio.rstrip("x")) <= goal else "not met"
            fig = f"{fig}; goal <= {goal}x: {met}"
        out.append((what, ratio, fig))
    return out


def _torch_call(module: torch.nn.Module, x: torch.Tensor):
    def call() -> None:
        with torch.inference_mode():
            module(x)

    return call


def _ort_call(policy, x: np.ndarray):
    return lambda: policy(x)


def import_row(quick: bool) -> tuple[str, str, str]:
    py = [sys.executable, "-c"]
    runs = {"torch": [], "torch + torch._dynamo": []}
    for _ in range(2 if quick else 5):
        for name, code in (
            ("torch", "import torch"),
            ("torch + torch._dynamo", "import torch, torch._dynamo"),
        ):
            t = time.perf_counter()
            subprocess.run([*py, code], check=True)
            runs[name].append(time.perf_counter() - t)
    a, b = (statistics.median(runs[k]) for k in ("torch + torch._dynamo", "torch"))
    return ("import torch._dynamo (avoided by prop's Adam)", f"{a / b:.2f}x",
            f"{a - b:.2f} s saved per process ({a:.2f} vs {b:.2f} s wall)")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.table", description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="smallest sizes only: a smoke test")
    g.add_argument("--full", action="store_true", help="every size, up to 50M parameters and 512 users")
    g.add_argument("--small", action="store_true", help="issue 40's small-model rows with their goals")
    ap.add_argument("--rows", default=",".join(GROUPS),
                    help=f"row groups to run, comma-separated (default: {','.join(GROUPS)})")  # fmt: skip
    ap.add_argument("--lerobot-python", type=Path, default=None,
                    help="LeRobot's environment's python, for the tiny ACT's audit row "
                    "(default: .venv-lerobot)")  # fmt: skip
    args = ap.parse_args(argv)
    chosen = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in chosen if r not in GROUPS]
    if unknown or not chosen:
        ap.error(f"--rows {args.rows!r}: use a comma list of {', '.join(GROUPS)}")
    name = "quick" if args.quick else "full" if args.full else "small" if args.small else "default"
    mode = MODES[name]
    threads_env = os.environ.get("OMP_NUM_THREADS")
    from prop_cli.threads import configure

    configure(parameters=0)  # the IL example's base training: a small model (rows below set their own)
    t0 = time.perf_counter()
    torch.manual_seed(0)
    skipped: list[str] = []
    rows: list[tuple[str, str, str]] = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        il = write_example(tmp / "il", seed=0)
        if args.small:
            rows, chosen = small_rows(tmp, il), []
        if "step" in chosen:
            rows += step_rows(tmp, il, mode)
        if "personalize" in chosen:
            rows += personalize_rows(il, mode)
        if {"audit", "inference"} & set(chosen):
            bundle, key = bundle_for(tmp, il, 200 if args.quick else 2000)
        if "audit" in chosen:
            rows += audit_rows(bundle, il, key, args.quick)
        if "audit-wall" in chosen:
            rows += audit_wall_rows(tmp, il, args.quick)
            row, skip = tiny_act_row(tmp, *lerobot_python(args.lerobot_python))
            rows += [row] if row else []
            skipped += [skip] if skip else []
        if "inference" in chosen:
            rows += inference_rows(bundle, key, args.quick)
        if "import" in chosen:
            rows.append(import_row(args.quick))
    print(f"prop speed ({name} mode), {machine()}; OMP_NUM_THREADS={threads_env or 'unset'}\n")
    width = max((len(r[0]) for r in rows), default=4)
    print(f"| {'what':{width}s} | ratio | figures |")
    print(f"|{'-' * (width + 2)}|-------|---------|")
    for what, ratio, fig in rows:
        print(f"| {what:{width}s} | {ratio} | {fig} |")
    for line in skipped:
        print(f"\n{line}")
    print(f"\n({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
