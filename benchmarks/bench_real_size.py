"""SmolVLA and pi0 at their published sizes: `prop personalize` (unsealed and --seal) beside LeRobot's own
training of the same policy on the same data, each in its own process under ``/usr/bin/time -v``.

    bash scripts/setup-lerobot.sh
    .venv-lerobot/bin/python -m benchmarks.bench_real_size [--policy smolvla|pi0] [--steps 3] [--runs ...]

``--policy pi0``: ``build_pi0`` (LeRobot's PI0Config defaults, held bf16 as lerobot/pi0_base; runs
``peft`` and ``sealed`` by default, its unsealed run does not fit 24 GiB: docs/speed.md), and ``--runs
gc`` measures its gradient checkpointing on one sealed payload step (``gc_worker``). ``--device cuda``
runs every run on the GPU (scripts/gpu_smoke_lerobot.py does).

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
  ``--batch`` null rows, one Hamming-neighbour, one random-key and one far-code row (``PROP_STEP``).
- ``peft``: the same LeRobot loop after ``policy.wrap_with_peft`` (LoRA, rank ``--rank``, LeRobot's
  default SmolVLA targets), as ``lerobot-train --peft.method_type=LORA --peft.r=RANK``.
- ``sealed``: ``prop personalize --seal``, a LoRA payload of the same rank on the same layers, ``--batch``
  user rows per step.

Printed: peak resident memory (``Maximum resident set size``), the largest resident memory sampled while
the steps ran ("in the steps": a load's peak can hide it), on a GPU ``--device cuda``'s
``torch.cuda.max_memory_allocated``, the median step, and the fixed costs:
set-up (process start to the first step, less the precompute), precompute (the original's fallback
targets and chunks, drawn before the steps), report (the key sweep after the steps), wall; then prop's
ratios to LeRobot's runs (prop / lerobot, sealed / peft). The command line comes first.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import json
import os
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import threading
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
RUNS = ("lerobot", "prop", "peft", "sealed", "gc")
POLICIES = ("smolvla", "pi0", "pi05")
PI = ("pi0", "pi05")  # built by build_pi0 (PaliGemma and its action expert)
TINY_ENV = "BENCH_REAL_SIZE_TINY"  # set: the tiny SmolVLA / pi0 instead (tests; pi0 under pi_tiny.tiny())
PHASES = ("setup", "precompute", "steps", "targets", "report")
MARK = "BENCH-REAL-SIZE "  # the line a worker prints its figures on (stderr)


# ---------------------------------------------------------------------------------------------- build
def build_data(data_dir: Path, image: int, episodes: int, frames: int, seed: int = 0, *,
               quantiles: bool = False) -> dict:  # fmt: skip
    """The LeRobotDataset at ``data_dir`` (kept if already there) and its statistics as the policies'
    processors take them (``quantiles``: with q01 ... q99, which pi0.5's QUANTILES normalization reads)."""
    import numpy as np
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

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
    return {
        k: {s: torch.as_tensor(np.asarray(v), dtype=torch.float32) for s, v in meta.stats[k].items()
            if s in ("mean", "std", "min", "max") or (quantiles and s.startswith("q"))}
        for k in (STATE, ACTION, CAMERA)
    }  # fmt: skip


def features(image: int) -> dict:
    """(input_features, output_features) of the policies: one camera, the state, the action."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    return dict(
        input_features={STATE: PolicyFeature(FeatureType.STATE, (DIMS,)),
                        CAMERA: PolicyFeature(FeatureType.VISUAL, (3, image, image))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (DIMS,))},
    )  # fmt: skip


def build(work: Path, image: int, episodes: int, frames: int, seed: int = 0, *, tiny: bool = False,
          data: str = "data") -> tuple[Path, Path]:  # fmt: skip
    """The SmolVLA policy folder (its VLM in ``work/vlm``) and the dataset under ``work`` (kept if
    already there). ``tiny``: examples/smolvla_tiny.py's VLM instead of the published size (tests)."""
    import torch

    from examples.smolvla_tiny import build_vlm

    policy_dir, data_dir = work / ("smolvla-tiny" if tiny else "smolvla"), work / data
    stats = build_data(data_dir, image, episodes, frames, seed)
    if (policy_dir / "model.safetensors").is_file():
        return policy_dir, data_dir
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    vlm = build_vlm(work / "vlm-tiny") if tiny else build_vlm(work / "vlm", config=SMOLVLM2_500M)
    cfg = SmolVLAConfig(**features(image), device="cpu", vlm_model_name=str(vlm), load_vlm_weights=False,
                        **(dict(resize_imgs_with_padding=(image, image)) if tiny else {}))  # fmt: skip
    torch.manual_seed(seed)
    policy = SmolVLAPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(policy_dir)
    return policy_dir, data_dir


# pi0 at its published size: LeRobot's PI0Config defaults (PaliGemma's gemma_2b with SigLIP so400m at
# 224 px, the gemma_300m action expert, chunk 50, 10 flow steps; every weight trainable), held as
# lerobot/pi0_base is (its config says "dtype": "bfloat16", its model.safetensors is 7.0 GB: LeRobot's
# to_bfloat16_for_selected_params, the vision tower, projector and norms fp32, the rest bf16).
PI0_IMAGE = 224
CHUNK = 2**25  # values generated at once when writing random weights (128 MB as fp32)


def build_pi0(work: Path, stats: dict, seed: int = 0, *, tiny: bool = False, kind: str = "pi0",
              **overrides) -> Path:  # fmt: skip
    """A pi0 (``kind`` pi05: pi0.5, its PI05Config defaults: the same PaliGemma and expert, quantile
    normalization, the state as discretized text) policy folder under ``work`` (kept if already there):
    its config, processors (the tokenizer step reading examples/pi_tiny.py's word-level tokenizer,
    written to ``work/tokenizer``; the embedding keeps PaliGemma's 257,152 rows) and random weights. The
    model is built on the meta device (shapes and dtypes only) and its weights written one tensor at a
    time (``write_random_safetensors``): 3.5 B parameters in 7 GB, never the whole model in memory.
    ``tiny``: pi_tiny's sizes (loads only under ``pi_tiny.tiny()``; tests)."""
    import contextlib
    import copy
    import importlib

    import torch

    from examples import pi_tiny

    package, config_name, policy_name = pi_tiny.KINDS[kind]
    lerobot = f"lerobot.policies.{package}"
    config_class = getattr(importlib.import_module(f"{lerobot}.configuration_{package}"), config_name)
    policy_class = getattr(importlib.import_module(f"{lerobot}.modeling_{package}"), policy_name)
    policy_dir = work / (f"{kind}-tiny" if tiny else kind)
    if (policy_dir / "model.safetensors").is_file():
        return policy_dir
    tok = pi_tiny.build_tokenizer(work / "tokenizer")
    sizes = dict(chunk_size=10, n_action_steps=5, max_state_dim=8, max_action_dim=8, tokenizer_max_length=16,
                 image_resolution=(pi_tiny.IMAGE, pi_tiny.IMAGE)) if tiny else {}  # fmt: skip
    image = pi_tiny.IMAGE if tiny else PI0_IMAGE
    cfg = config_class(**features(image), device="cpu", dtype="bfloat16", **(sizes | overrides))
    on_meta = copy.copy(cfg)
    on_meta.device = "meta"  # PI0Policy moves its model to config.device
    with pi_tiny.tiny() if tiny else contextlib.nullcontext(), torch.device("meta"):
        policy = policy_class(on_meta)
    policy_dir.mkdir(parents=True, exist_ok=True)
    write_random_safetensors(policy, policy_dir / "model.safetensors", seed)
    cfg.save_pretrained(policy_dir)
    for part in pi_tiny.local_processors(kind, cfg, tok, stats):
        part.save_pretrained(policy_dir)
    return policy_dir


def write_random_safetensors(module, path: Path, seed: int = 0) -> None:
    """``module``'s state dict (meta tensors: names, shapes, dtypes) written to ``path`` as safetensors
    with random values, one tensor at a time: matrices N(0, 1/fan_in), LayerNorm weights 1, every other
    vector 0 (biases; Gemma's RMSNorm scales by 1 + weight)."""
    import json as _json

    import torch

    codes = {torch.float32: "F32", torch.bfloat16: "BF16", torch.float16: "F16", torch.int64: "I64"}
    mods = dict(module.named_modules())
    state = module.state_dict()
    header, offset = {}, 0
    for name, t in state.items():
        size = t.numel() * t.element_size()
        header[name] = {"dtype": codes[t.dtype], "shape": list(t.shape),
                        "data_offsets": [offset, offset + size]}  # fmt: skip
        offset += size
    header["__metadata__"] = {"format": "pt"}
    head = _json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)
    gen = torch.Generator().manual_seed(seed)
    with open(path, "wb") as f:
        f.write(len(head).to_bytes(8, "little") + head)
        for name, t in state.items():
            owner = mods.get(name.rpartition(".")[0])
            rows = max(1, CHUNK // max(1, t[0].numel())) if t.dim() else 1
            for i in range(0, max(1, len(t)) if t.dim() else 1, rows):  # a block of rows at a time
                shape = (min(rows, len(t) - i), *t.shape[1:]) if t.dim() else ()
                if t.dim() >= 2:
                    value = torch.randn(shape, generator=gen).mul_(t[0].numel() ** -0.5)
                elif isinstance(owner, torch.nn.LayerNorm) and name.endswith("weight"):
                    value = torch.ones(shape)
                else:
                    value = torch.zeros(shape)
                f.write(value.to(t.dtype).reshape(-1).view(torch.uint8).numpy().data)


def counts(module) -> tuple[int, int]:
    """(parameters, trainable parameters) of a module."""
    params = list(module.parameters())
    return sum(p.numel() for p in params), sum(p.numel() for p in params if p.requires_grad)


# -------------------------------------------------------------------------------------------- workers
def sync() -> None:
    """Wait for the GPU's queued work (a step's time is its work's, not its launch's)."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


class Clock:
    """Phase timings and the peak resident memory reached by the end of each phase, printed on exit."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.phase_start = self.t0
        self.figures: dict = {"phases": {p: 0.0 for p in PHASES}, "peak_gib": {}, "steps_s": []}
        self.watching = False  # between steps_begin and steps_end: the resident memory sampled
        atexit.register(self.emit)
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        """The largest resident memory seen while the steps run (the process's peak may be its load's,
        which hides what the steps hold): /proc/self/statm every 50 ms."""
        page = os.sysconf("SC_PAGE_SIZE")
        while True:
            if self.watching:
                with open("/proc/self/statm") as f:
                    rss = int(f.read().split()[1]) * page / 2**30
                self.figures["steps_rss_gib"] = max(self.figures.get("steps_rss_gib", 0.0), rss)
            time.sleep(0.05)

    def steps_begin(self) -> None:
        self.watching = True
        torch = sys.modules.get("torch")
        if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
            self.figures["cuda_before_steps_gib"] = torch.cuda.max_memory_allocated() / 2**30
            torch.cuda.reset_peak_memory_stats()

    def steps_end(self) -> None:
        self.watching = False
        torch = sys.modules.get("torch")
        if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
            self.figures["cuda_steps_gib"] = torch.cuda.max_memory_allocated() / 2**30

    def add(self, phase: str, seconds: float) -> None:
        self.figures["phases"][phase] += seconds

    def peak(self, label: str) -> None:
        self.figures["peak_gib"][label] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20

    def emit(self) -> None:
        self.peak("end")
        torch = sys.modules.get("torch")
        if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
            f = self.figures
            now = torch.cuda.max_memory_allocated() / 2**30
            f["cuda_peak_gib"] = max(now, f.get("cuda_before_steps_gib", 0.0), f.get("cuda_steps_gib", 0.0))
        self.figures["wall_s"] = time.perf_counter() - self.t0
        print(MARK + json.dumps(self.figures), file=sys.stderr, flush=True)


def lerobot_worker(args: argparse.Namespace) -> None:
    """LeRobot's own training of the policy at ``args.folder`` (``--peft``: its LoRA run)."""
    import dataclasses

    import torch

    clock = Clock()
    torch.set_num_threads(args.threads)
    from lerobot.configs.default import PeftConfig
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    torch.manual_seed(0)
    kind = json.loads((Path(args.folder) / "config.json").read_text())["type"]
    policy = get_policy_class(kind).from_pretrained(args.folder).to(args.device)
    pre, _ = make_pre_post_processors(policy.config, pretrained_path=args.folder)
    if args.peft:  # lerobot-train's make_policy records the path the policy came from; PEFT needs it
        policy.config.pretrained_path = Path(args.folder)
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
    clock.steps_begin()
    for _ in range(args.steps):  # lerobot_train.update_policy: forward, backward, clip, step
        t = time.perf_counter()
        try:
            batch = next(batches)
        except StopIteration:
            batches = iter(loader)
            batch = next(batches)
        batch = {k: v.to(args.device) if torch.is_tensor(v) else v for k, v in pre(batch).items()}
        loss, _ = policy.forward(batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, preset.grad_clip_norm)
        optimizer.step()
        optimizer.zero_grad()
        sync()
        clock.figures["steps_s"].append(time.perf_counter() - t)
    clock.steps_end()
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
            sync()
            clock.figures["steps_s"].append(time.perf_counter() - t)
            clock.figures.setdefault("targets_s", []).append(clock.figures["phases"]["targets"] - pool)
            return out

        clock.peak("before steps")
        phases = clock.figures["phases"]
        phases["setup"] = time.perf_counter() - clock.t0 - phases["precompute"]
        t = time.perf_counter()
        clock.steps_begin()
        try:
            return run_steps(one, n, progress, *a, **k)
        finally:
            clock.steps_end()
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


def gc_worker(args: argparse.Namespace) -> None:
    """pi0's gradient checkpointing on a sealed payload step, in one process: the policy loaded as prop
    loads it, a rank-``args.rank`` payload on prop's default layers, ``args.batch`` rows of LeRobot's
    own loss forward and backward with LeRobot's checkpointing off, then on; for each, the largest
    resident memory above the step's start (sampled every 20 ms) and its time."""
    from dataclasses import replace

    import torch

    from prop_adapters import load_checkpoint
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core.payload import Payload
    from prop_cli.datasources import load_data
    from prop_cli.train.sealed import payload_spec

    torch.set_num_threads(args.threads)
    loaded = load_checkpoint(args.folder)
    policy, module = loaded.policy, loaded.module
    cfg = PersonalizeConfig.of(seal=True, payload_rank=args.rank)
    payload = Payload(payload_spec(module, replace(cfg.train, layers=policy.default_layers), cfg.mode),
                      torch.Generator().manual_seed(0))  # fmt: skip
    module.requires_grad_(False)
    batch = policy.batches(load_data(args.data), "--data")
    rows = {k: v[: args.batch] for k, v in batch.items()}
    page = os.sysconf("SC_PAGE_SIZE")

    def rss() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * page / 2**30

    out = []
    with payload.attached(module):
        for on in (False, True):
            m = policy.model  # PI0Pytorch: LeRobot's switch (its config's gradient_checkpointing)
            (m.gradient_checkpointing_enable if on else m.gradient_checkpointing_disable)()
            base, top, stop = rss(), [0.0], threading.Event()

            def sample(top=top, stop=stop) -> None:
                while not stop.is_set():
                    top[0] = max(top[0], rss())
                    time.sleep(0.02)

            watcher = threading.Thread(target=sample, daemon=True)
            watcher.start()
            t = time.perf_counter()
            torch.manual_seed(0)
            loss = policy.loss(rows)
            loss.backward()
            seconds = time.perf_counter() - t
            stop.set()
            watcher.join()
            for p in payload.parameters():
                p.grad = None
            out.append({"checkpointing": on, "step_gib": top[0] - base, "start_gib": base, "step_s": seconds,
                        "loss": loss.item()})  # fmt: skip
            print(json.dumps(out[-1]), file=sys.stderr, flush=True)
    print(MARK + json.dumps({"gc": out}), file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------------- driver
# One row of each kind of wrong key (a neighbour, a random key, a far code: issue 32's term), as LeRobot's
# batch of --batch frames: the default 16 far codes alone would be 16 rows against LeRobot's 2.
PROP_STEP = ("--user-rows {b} --null-rows {b} --neighbour-keys 1 --random-keys 1 --far-codes 1"
             " --samples-per-key 1")


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
    gpu = any("cuda_peak_gib" in r for r in results.values())
    head = "| run | peak memory | in the steps |" + (" GPU peak |" if gpu else "")
    head += " step (median) | set-up | precompute | targets in steps | steps | report | wall | CPU |"
    out = [head, "|" + "---|" * (12 if gpu else 11)]
    probes = {n: results.pop(n)["gc"] for n in [n for n, r in results.items() if "gc" in r]}
    for name, r in results.items():
        ph = r.get("phases", {})
        cells = [f"{r['rss_gb']:.2f} GiB", f"{r.get('steps_rss_gib', float('nan')):.2f} GiB"]
        cells += [f"{r.get('cuda_peak_gib', float('nan')):.2f} GiB"] if gpu else []
        cells += [f"{median(r.get('steps_s', [])):.2f} s"]
        cells += [f"{ph.get(k, 0):.0f} s" for k in ("setup", "precompute", "targets", "steps", "report")]
        out.append(f"| {name} | " + " | ".join(cells) + f" | {r['wall_s']:.0f} s | {r['cpu_s']:.0f} s |")
    for a, b in (("prop", "lerobot"), ("sealed", "peft")):
        if a in results and b in results:
            ra, rb = results[a], results[b]
            own = [s - t for s, t in zip(ra["steps_s"], ra.get("targets_s", [0.0] * len(ra["steps_s"])))]
            gpu_ratio = (f" (GPU {ra['cuda_peak_gib'] / rb['cuda_peak_gib']:.2f}x)"
                         if "cuda_peak_gib" in ra and "cuda_peak_gib" in rb else "")  # fmt: skip
            out.append(
                f"\n{a} / {b}: peak memory {ra['rss_gb'] / rb['rss_gb']:.2f}x{gpu_ratio}; step "
                f"{median(ra['steps_s']) / median(rb['steps_s']):.2f}x "
                f"({median(own) / median(rb['steps_s']):.2f}x without the original's targets)"
            )
    for rows in probes.values():  # gc_worker: a sealed payload step, LeRobot's checkpointing off / on
        out.append("\ngradient checkpointing, one sealed payload step (memory above the step's start, time):")
        out += [f"- {'on ' if r['checkpointing'] else 'off'}: {r['step_gib']:.2f} GiB, {r['step_s']:.0f} s, "
                f"loss {r['loss']:.6f}" for r in rows]  # fmt: skip
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    with tiny_pi() if os.environ.get(TINY_ENV) else contextlib.nullcontext():
        return _main(argv)


def tiny_pi() -> contextlib.AbstractContextManager:
    from examples import pi_tiny

    return pi_tiny.tiny()


def _main(argv: list[str]) -> None:
    if argv[:1] == ["worker-prop"]:
        return prop_worker(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", choices=POLICIES, default="smolvla")
    ap.add_argument("--runs", help=f"comma-separated, of {', '.join(RUNS)} (default: all for smolvla, "
                    "peft,sealed for pi0: its unsealed run does not fit 24 GiB)")  # fmt: skip
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--image", type=int, help="camera frames, pixels square (default: 512 for smolvla, 224 "
                    "for pi0: what each resizes to)")  # fmt: skip
    ap.add_argument("--gradient-checkpointing", choices=("on", "off"),
                    help="pi0: set its config.json's gradient_checkpointing (LeRobot's runs and prop's "
                    "read it); SmolVLA has none")  # fmt: skip
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=5, help="frames per episode")
    ap.add_argument("--rank", type=int, default=4, help="LoRA rank of peft and of the sealed payload")
    ap.add_argument("--key-bits", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=JSON",
                    help="set a field of the policy's config.json first (e.g. train_expert_only=true)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda: where every run trains (on cuda the "
                    "table adds torch.cuda.max_memory_allocated)")  # fmt: skip
    ap.add_argument("--work", type=Path, default=None, help="build here (reused when it holds a build)")
    ap.add_argument("--prop-args", default="", help="more `prop personalize` flags, quoted")
    ap.add_argument("--worker", choices=("lerobot", "peft", "gc"), help=argparse.SUPPRESS)
    ap.add_argument("--folder", help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker == "gc":
        return gc_worker(args)
    if args.worker:
        args.peft = args.worker == "peft"
        return lerobot_worker(args)
    print("command:", shlex.join([Path(sys.executable).name, "-m", "benchmarks.bench_real_size", *argv]))
    work = args.work or Path(tempfile.mkdtemp(prefix="prop-real-size-"))
    work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    tiny = bool(os.environ.get(TINY_ENV))
    if args.policy in PI:
        args.image = args.image or PI0_IMAGE
        data_dir = work / "data-pi0"  # the same data for both
        stats = build_data(data_dir, args.image, args.episodes, args.frames, quantiles=args.policy == "pi05")
        policy_dir = build_pi0(work, stats, tiny=tiny, kind=args.policy)
    else:
        args.image = args.image or 512
        policy_dir, data_dir = build(work, args.image, args.episodes, args.frames, tiny=tiny)
    if args.gradient_checkpointing:
        if args.policy not in PI:
            raise SystemExit("--gradient-checkpointing: SmolVLA's config offers no gradient checkpointing")
        args.set.append(f"gradient_checkpointing={json.dumps(args.gradient_checkpointing == 'on')}")
    if args.set:  # the policy's config.json, as LeRobot's runs and prop's read it
        config = json.loads((policy_dir / "config.json").read_text())
        for item in args.set:
            name, _, value = item.partition("=")
            if name not in config:
                raise SystemExit(f"--set {item}: {policy_dir / 'config.json'} has no {name!r}")
            config[name] = json.loads(value)
        (policy_dir / "config.json").write_text(json.dumps(config, indent=4))
    runs = args.runs or ",".join(RUNS[:4] if args.policy == "smolvla" else ("peft", "sealed"))
    print(f"built in {time.perf_counter() - t:.0f} s: {policy_dir}, {data_dir} ({args.episodes} episodes x "
          f"{args.frames} frames, {args.image}x{args.image} images)", file=sys.stderr)  # fmt: skip
    env = os.environ | {"HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": str(args.threads)}
    py = sys.executable
    key = work / f"key{args.key_bits}.bin"
    if not key.exists():
        subprocess.run([py, "-m", "prop_cli.cli.main", "keygen", str(key), "--bits", str(args.key_bits)],
                       check=True, env=env, stdout=subprocess.DEVNULL)  # fmt: skip
    common = [str(policy_dir), "--data", str(data_dir), "--key-file", str(key), "--steps", str(args.steps),
              "--threads", str(args.threads), "--device", args.device, "--force", "--json",
              *shlex.split(args.prop_args)]  # fmt: skip
    cmds = {
        "lerobot": [py, "-m", "benchmarks.bench_real_size", "--worker", "lerobot"],
        "peft": [py, "-m", "benchmarks.bench_real_size", "--worker", "peft"],
        "gc": [py, "-m", "benchmarks.bench_real_size", "--worker", "gc"],
        "prop": [py, "-m", "benchmarks.bench_real_size", "worker-prop", "personalize", *common,
                 "--out", str(work / "unsealed.prop"), *shlex.split(PROP_STEP.format(b=args.batch))],
        "sealed": [py, "-m", "benchmarks.bench_real_size", "worker-prop", "personalize", *common,
                   "--out", str(work / "sealed.prop"), "--seal", "--payload-rank", str(args.rank),
                   "--user-rows", str(args.batch)],
    }  # fmt: skip
    for name in ("lerobot", "peft", "gc"):
        cmds[name] += ["--folder", str(policy_dir), "--data", str(data_dir), "--steps", str(args.steps),
                       "--batch", str(args.batch), "--rank", str(args.rank),
                       "--threads", str(args.threads), "--device", args.device]  # fmt: skip
    results = {}
    for name in [r.strip() for r in runs.split(",") if r.strip()]:
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
