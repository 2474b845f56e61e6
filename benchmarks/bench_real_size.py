"""SmolVLA at its published size: `prop personalize` (unsealed and --seal) beside LeRobot's own training of
the same policy on the same data, each in its own process under ``/usr/bin/time -v``.

    bash scripts/setup-lerobot.sh
    .venv-lerobot/bin/python -m benchmarks.bench_real_size [--steps 3] [--image 512] [--runs ...]

What is built here (nothing is downloaded):
- **The VLM**: SmolVLM2-500M-Video-Instruct's text and vision configs, written out below as the
  published numbers (``SMOLVLM2_500M``), random weights, with examples/smolvla_tiny.py's tiny word-level
  tokenizer (the embedding keeps the published vocabulary size).
- **The policy**: LeRobot's ``SmolVLAConfig`` defaults (16 VLM layers, expert width 0.75, chunk 50, 10
  flow steps, ``train_expert_only``, frozen vision encoder, images resized to 512x512), one camera, a
  6-value state and 6-value actions: 450 M parameters, 99.9 M of them trainable.
- **The data**: a LeRobotDataset of ``--episodes`` episodes x ``--frames`` frames, camera frames of
  ``--image`` pixels square (smooth random images; the policy resizes them to 512 x 512 whatever their
  size), one task text.

The runs (``--runs``, each a fresh process):
- ``lerobot``: LeRobot's own fine-tuning: ``SmolVLAPolicy.from_pretrained``, its preprocessor, its
  ``LeRobotDataset`` with the policy's delta timestamps, batch ``--batch``, its AdamW preset with the
  grad clip, as ``lerobot_train.update_policy`` steps (no DataLoader workers: one process to measure).
- ``prop``: ``prop personalize`` unsealed, 128-bit key (``--key-bits``); a step is ``--batch`` user rows,
  ``--batch`` null rows, one Hamming-neighbour and one random-key row (``PROP_STEP``).
- ``peft``: the same LeRobot loop after ``policy.wrap_with_peft`` (LoRA, rank ``--rank``, LeRobot's
  default SmolVLA targets), as ``lerobot-train --peft.method_type=LORA --peft.r=RANK``.
- ``sealed``: ``prop personalize --seal``, a LoRA payload of the same rank on the same layers, ``--batch``
  user rows per step.

Printed: peak resident memory (``Maximum resident set size``), the median step, and the fixed costs:
set-up (process start to the first step, less the precompute), precompute (the original's fallback
targets and chunks, drawn before the steps), report (the key sweep after the steps), wall; then prop's
ratios to LeRobot's runs (prop / lerobot, sealed / peft). The command line comes first.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# SmolVLM2-500M-Video-Instruct's config.json (HuggingFaceTB), the numbers that size the model: a
# SmolLM2-360M text model (32 layers; SmolVLA keeps the first 16) and a SigLIP base/16 vision encoder at
# 512 px, pixel-shuffled by 4 (64 image tokens).
SMOLVLM2_500M = dict(
    text_config=dict(
        model_type="llama", vocab_size=49280, hidden_size=960, intermediate_size=2560, num_hidden_layers=32,
        num_attention_heads=15, num_key_value_heads=5, head_dim=64, max_position_embeddings=8192,
        rms_norm_eps=1e-5, rope_theta=100000.0, tie_word_embeddings=False, hidden_act="silu",
        attention_bias=False, mlp_bias=False, pad_token_id=2,
    ),
    vision_config=dict(
        hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
        image_size=512, patch_size=16, num_channels=3, layer_norm_eps=1e-6, hidden_act="gelu_pytorch_tanh",
    ),
    scale_factor=4, image_token_id=49190, vocab_size=49280, tie_word_embeddings=False, pad_token_id=2,
)  # fmt: skip
STATE, CAMERA, ACTION = "observation.state", "observation.images.front", "action"
DIMS = 6  # state and action values
TASK_TEXT = "pick up the red block"
RUNS = ("lerobot", "prop", "peft", "sealed")
PHASES = ("setup", "precompute", "steps", "targets", "report")
MARK = "BENCH-REAL-SIZE "  # the line a worker prints its figures on (stderr)


# ---------------------------------------------------------------------------------------------- build
def build(work: Path, image: int, episodes: int, frames: int, seed: int = 0) -> tuple[Path, Path]:
    """The VLM folder, the policy folder and the dataset under ``work`` (kept if already there)."""
    import numpy as np
    import torch

    from examples.smolvla_tiny import build_vlm

    policy_dir, data_dir = work / "smolvla", work / "data"
    if (policy_dir / "model.safetensors").is_file() and (data_dir / "meta" / "info.json").is_file():
        return policy_dir, data_dir
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    rng = np.random.default_rng(seed)
    if not (data_dir / "meta" / "info.json").is_file():
        ds = LeRobotDataset.create(
            repo_id="local/real-size", fps=10, root=data_dir, robot_type="arm", use_videos=False,
            video_backend="pyav",
            features={
                STATE: {"dtype": "float32", "shape": (DIMS,), "names": [f"s{i}" for i in range(DIMS)]},
                ACTION: {"dtype": "float32", "shape": (DIMS,), "names": [f"a{i}" for i in range(DIMS)]},
                CAMERA: {"dtype": "image", "shape": (image, image, 3), "names": ["height", "width", "rgb"]},
            },
        )  # fmt: skip
        for _ in range(episodes):
            state = rng.standard_normal(DIMS).astype(np.float32)
            for _ in range(frames):
                coarse = rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)  # smooth: an 8x8 image upscaled
                block = np.ones((image // 8 + 1, image // 8 + 1, 1), np.uint8)
                frame = np.kron(coarse, block)[:image, :image]
                action = np.tanh(state + 0.1 * rng.standard_normal(DIMS)).astype(np.float32)
                ds.add_frame({STATE: state, ACTION: action, CAMERA: frame, "task": TASK_TEXT})
                state = (state + 0.1 * action).astype(np.float32)
            ds.save_episode()
        ds.finalize()
    meta = LeRobotDatasetMetadata("local/real-size", root=data_dir)
    stats = {
        k: {s: torch.as_tensor(np.asarray(v), dtype=torch.float32) for s, v in meta.stats[k].items()
            if s in ("mean", "std", "min", "max")}
        for k in (STATE, ACTION, CAMERA)
    }  # fmt: skip
    vlm = build_vlm(work / "vlm", config=SMOLVLM2_500M)
    cfg = SmolVLAConfig(
        input_features={STATE: PolicyFeature(FeatureType.STATE, (DIMS,)),
                        CAMERA: PolicyFeature(FeatureType.VISUAL, (3, image, image))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (DIMS,))},
        device="cpu", vlm_model_name=str(vlm), load_vlm_weights=False,
    )  # fmt: skip
    torch.manual_seed(seed)
    policy = SmolVLAPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(policy_dir)
    return policy_dir, data_dir


def counts(module) -> tuple[int, int]:
    """(parameters, trainable parameters) of a module."""
    params = list(module.parameters())
    return sum(p.numel() for p in params), sum(p.numel() for p in params if p.requires_grad)


# -------------------------------------------------------------------------------------------- workers
class Clock:
    """Phase timings and the peak resident memory reached by the end of each phase, printed on exit."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.phase_start = self.t0
        self.figures: dict = {"phases": {p: 0.0 for p in PHASES}, "peak_gib": {}, "steps_s": []}
        atexit.register(self.emit)

    def add(self, phase: str, seconds: float) -> None:
        self.figures["phases"][phase] += seconds

    def peak(self, label: str) -> None:
        self.figures["peak_gib"][label] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20

    def emit(self) -> None:
        self.peak("end")
        self.figures["wall_s"] = time.perf_counter() - self.t0
        print(MARK + json.dumps(self.figures), file=sys.stderr, flush=True)


def lerobot_worker(args: argparse.Namespace) -> None:
    """LeRobot's own training of the policy at ``args.policy`` (``--peft``: its LoRA run)."""
    import dataclasses

    import torch

    clock = Clock()
    torch.set_num_threads(args.threads)
    from lerobot.configs.default import PeftConfig
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    torch.manual_seed(0)
    policy = SmolVLAPolicy.from_pretrained(args.policy)
    pre, _ = make_pre_post_processors(policy.config, pretrained_path=args.policy)
    if args.peft:  # lerobot-train's make_policy records the path the policy came from; PEFT needs it
        policy.config.pretrained_path = Path(args.policy)
        policy = policy.wrap_with_peft(peft_cli_overrides=dataclasses.asdict(PeftConfig(r=args.rank)))
    total, trainable = counts(policy)
    clock.figures.update(parameters=total, trainable=trainable)
    meta = LeRobotDatasetMetadata("local/real-size", root=args.data)
    ds = LeRobotDataset("local/real-size", root=args.data,
                        delta_timestamps=resolve_delta_timestamps(policy.config, meta))  # fmt: skip
    loader = torch.utils.data.DataLoader(ds, batch_size=args.batch, shuffle=True, num_workers=0,
                                         generator=torch.Generator().manual_seed(0))  # fmt: skip
    preset = policy.config.get_optimizer_preset()
    optimizer = preset.build(policy.get_optim_params() if not args.peft else
                             [p for p in policy.parameters() if p.requires_grad])  # fmt: skip
    params = [p for p in policy.parameters() if p.requires_grad]
    clock.add("setup", time.perf_counter() - clock.t0)
    clock.peak("setup")
    batches = iter(loader)
    policy.train()
    for _ in range(args.steps):  # lerobot_train.update_policy: forward, backward, clip, step
        t = time.perf_counter()
        try:
            batch = next(batches)
        except StopIteration:
            batches = iter(loader)
            batch = next(batches)
        loss, _ = policy.forward(pre(batch))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, preset.grad_clip_norm)
        optimizer.step()
        optimizer.zero_grad()
        clock.figures["steps_s"].append(time.perf_counter() - t)
    clock.add("steps", sum(clock.figures["steps_s"]))


def prop_worker(argv: list[str]) -> None:
    """``prop personalize ARGV`` in this process, its phases timed from outside (the functions that run
    them wrapped here; prop itself is unchanged)."""
    clock = Clock()
    import prop_adapters.lerobot.policy as lp
    import prop_cli.train.loop as loop
    import prop_cli.train.policy as tp
    import prop_cli.train.sealed as ts
    import prop_cli.train.sealed_policy as tsp

    state = {"stepped": False, "depth": 0}

    def timed(fn, phase_of):
        def wrapper(*a, **k):  # the outermost timed call counts (a report's chunks are the report's)
            t = time.perf_counter()
            state["depth"] += 1
            try:
                return fn(*a, **k)
            finally:
                state["depth"] -= 1
                if not state["depth"]:
                    clock.add(phase_of(), time.perf_counter() - t)

        return wrapper

    before_after = lambda: "report" if state["stepped"] else "precompute"  # noqa: E731
    run_steps = loop.run_steps

    def steps(step, n, progress, *a, **k):
        def one():
            t, pool = time.perf_counter(), clock.figures["phases"]["targets"]
            out = step()
            clock.figures["steps_s"].append(time.perf_counter() - t)
            clock.figures.setdefault("targets_s", []).append(clock.figures["phases"]["targets"] - pool)
            return out

        clock.peak("before steps")
        phases = clock.figures["phases"]
        phases["setup"] = time.perf_counter() - clock.t0 - phases["precompute"]
        t = time.perf_counter()
        try:
            return run_steps(one, n, progress, *a, **k)
        finally:
            clock.add("steps", time.perf_counter() - t)
            state["stepped"] = True
            clock.peak("steps")

    for mod in (tp, tsp):
        if hasattr(mod, "run_steps"):
            mod.run_steps = steps
        if hasattr(mod, "chunks"):
            mod.chunks = timed(mod.chunks, before_after)
    for name in ("chunk_report",):
        if hasattr(tp, name):
            setattr(tp, name, timed(getattr(tp, name), lambda: "report"))
    ts.user_report = timed(ts.user_report, lambda: "report")
    if hasattr(tp, "FallbackPool"):  # the original's targets, computed as the steps first draw them
        tp.FallbackPool._fill = timed(tp.FallbackPool._fill, lambda: "targets")
    for cls, name in ((lp.LeRobotProtocol, "_denoiser_pool"),):
        if hasattr(cls, name):
            setattr(cls, name, timed(getattr(cls, name), before_after))
    from prop_cli.cli.main import main as prop_main

    sys.argv = ["prop", *argv]
    try:
        prop_main()
    except SystemExit as e:
        if e.code:
            raise


# --------------------------------------------------------------------------------------------- driver
PROP_STEP = "--user-rows {b} --null-rows {b} --neighbour-keys 1 --random-keys 1 --samples-per-key 1"


def measured(cmd: list[str], env: dict, log: Path) -> dict:
    """Run ``cmd`` under /usr/bin/time -v; its figures (the worker's line) and peak RSS."""
    t = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run(["/usr/bin/time", "-v", *cmd], stdout=f, stderr=subprocess.STDOUT, env=env)
    wall = time.perf_counter() - t
    text = log.read_text()
    if proc.returncode:
        tail = "\n".join(text.splitlines()[-15:])
        raise SystemExit(f"run failed (exit {proc.returncode}): {shlex.join(cmd)}\n{tail}\n(log: {log})")
    lines = [line for line in text.splitlines() if line.startswith(MARK)]
    figures = json.loads(lines[-1][len(MARK) :]) if lines else {}
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
    figures["rss_gb"] = int(rss.group(1)) / 2**20 if rss else float("nan")  # KiB -> GiB
    figures["wall_s"] = wall
    cpu = re.findall(r"(?:User|System) time \(seconds\): ([\d.]+)", text)
    figures["cpu_s"] = sum(map(float, cpu)) if cpu else float("nan")
    return figures


def median(xs: list[float]) -> float:
    import statistics

    return statistics.median(xs) if xs else float("nan")


def table(results: dict[str, dict]) -> str:
    """The markdown table: peak memory, step time and fixed costs per run, then prop's ratios."""
    head = ("| run | peak memory | step (median) | set-up | precompute | targets in steps | steps | report "
            "| wall | CPU |")  # fmt: skip
    out = [head, "|" + "---|" * 10]
    for name, r in results.items():
        ph = r.get("phases", {})
        cells = [f"{r['rss_gb']:.2f} GiB", f"{median(r.get('steps_s', [])):.1f} s"]
        cells += [f"{ph.get(k, 0):.0f} s" for k in ("setup", "precompute", "targets", "steps", "report")]
        out.append(f"| {name} | " + " | ".join(cells) + f" | {r['wall_s']:.0f} s | {r['cpu_s']:.0f} s |")
    for a, b in (("prop", "lerobot"), ("sealed", "peft")):
        if a in results and b in results:
            ra, rb = results[a], results[b]
            own = [s - t for s, t in zip(ra["steps_s"], ra.get("targets_s", [0.0] * len(ra["steps_s"])))]
            out.append(
                f"\n{a} / {b}: peak memory {ra['rss_gb'] / rb['rss_gb']:.2f}x; step "
                f"{median(ra['steps_s']) / median(rb['steps_s']):.2f}x "
                f"({median(own) / median(rb['steps_s']):.2f}x without the original's targets)"
            )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["worker-prop"]:
        return prop_worker(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", default=",".join(RUNS), help=f"comma-separated, of {', '.join(RUNS)}")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--image", type=int, default=512, help="camera frames, pixels square")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=5, help="frames per episode")
    ap.add_argument("--rank", type=int, default=4, help="LoRA rank of peft and of the sealed payload")
    ap.add_argument("--key-bits", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", type=Path, default=None, help="build here (reused when it holds a build)")
    ap.add_argument("--prop-args", default="", help="more `prop personalize` flags, quoted")
    ap.add_argument("--worker", choices=("lerobot", "peft"), help=argparse.SUPPRESS)
    ap.add_argument("--policy", help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        args.peft = args.worker == "peft"
        return lerobot_worker(args)
    print("command:", shlex.join([Path(sys.executable).name, "-m", "benchmarks.bench_real_size", *argv]))
    work = args.work or Path(tempfile.mkdtemp(prefix="prop-real-size-"))
    work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    policy_dir, data_dir = build(work, args.image, args.episodes, args.frames)
    print(f"built in {time.perf_counter() - t:.0f} s: {policy_dir}, {data_dir} ({args.episodes} episodes x "
          f"{args.frames} frames, {args.image}x{args.image} images)", file=sys.stderr)  # fmt: skip
    env = os.environ | {"HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": str(args.threads)}
    py = sys.executable
    key = work / f"key{args.key_bits}.bin"
    if not key.exists():
        subprocess.run([py, "-m", "prop_cli.cli.main", "keygen", str(key), "--bits", str(args.key_bits)],
                       check=True, env=env, stdout=subprocess.DEVNULL)  # fmt: skip
    common = [str(policy_dir), "--data", str(data_dir), "--key-file", str(key), "--steps", str(args.steps),
              "--threads", str(args.threads), "--force", "--json", *shlex.split(args.prop_args)]  # fmt: skip
    cmds = {
        "lerobot": [py, "-m", "benchmarks.bench_real_size", "--worker", "lerobot"],
        "peft": [py, "-m", "benchmarks.bench_real_size", "--worker", "peft"],
        "prop": [py, "-m", "benchmarks.bench_real_size", "worker-prop", "personalize", *common,
                 "--out", str(work / "unsealed.prop"), *shlex.split(PROP_STEP.format(b=args.batch))],
        "sealed": [py, "-m", "benchmarks.bench_real_size", "worker-prop", "personalize", *common,
                   "--out", str(work / "sealed.prop"), "--seal", "--payload-rank", str(args.rank),
                   "--user-rows", str(args.batch)],
    }  # fmt: skip
    for name in ("lerobot", "peft"):
        cmds[name] += ["--policy", str(policy_dir), "--data", str(data_dir), "--steps", str(args.steps),
                       "--batch", str(args.batch), "--rank", str(args.rank),
                       "--threads", str(args.threads)]  # fmt: skip
    results = {}
    for name in [r.strip() for r in args.runs.split(",") if r.strip()]:
        if name not in cmds:
            raise SystemExit(f"--runs: {name!r} is not one of {', '.join(RUNS)}")
        print(f"{name}: {shlex.join(cmds[name])}", file=sys.stderr, flush=True)
        results[name] = measured(cmds[name], env, work / f"{name}.log")
        r = results[name]
        print(f"  peak {r['rss_gb']:.2f} GiB, wall {r['wall_s']:.0f} s, phases "
              f"{ {k: round(v, 1) for k, v in r.get('phases', {}).items()} }, peaks {r.get('peak_gib')}",
              file=sys.stderr, flush=True)  # fmt: skip
    print(table(results))
    (work / "results.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
