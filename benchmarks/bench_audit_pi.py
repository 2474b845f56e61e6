"""`prop attack` on the tiny pi0 / pi0.5 bundles (issue 40 item 3): the default audit's time per probe,
its coverage and verdict, unsealed and sealed.

    .venv-lerobot/bin/python -m benchmarks.bench_audit_pi [--kinds pi05,pi0] [--work DIR] [--max-leak 0.05]

The bundles are built as tests/adapters/test_lerobot_pi0.py builds them (examples/pi_tiny.py: 2-layer
Gemmas and SigLIP, random weights, nothing downloaded; the MuJoCo reach's camera task, 2 episodes of
general and user data; a 32-bit key; the policy trained 3 LeRobot steps first; unsealed with the tests'
small personalize settings, sealed with a PEFT-LoRA payload). The audit is `prop attack`'s default (every
default probe, a policy's 600 s budget), its user key and the original checkpoint as the control
(``--original``), run in this process under ``pi_tiny.tiny()``. Printed: per probe, its
``speed.stage_seconds``; the audit's wall seconds, coverage, and the ``--max-leak`` verdict. The command
line comes first.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BITS = 32
# tests/adapters/test_lerobot_pi0.py's personalize settings
TINY = dict(steps=4, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=2, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip


def build(kind: str, root: Path) -> dict[str, Path]:
    """The policy, its data, key and both bundles (reused when ``root`` holds them)."""
    from examples import lerobot_reach_task as task
    from examples import pi_tiny
    from prop_cli import api
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core.key_files import KeySource

    out = {"policy": root / kind, "user": root / "user", "general": root / "general", "key": root / "k.bin"}
    if not out["user"].exists():
        task.record(out["general"], 2, 0, np.zeros(3, np.float32), camera=True)
        task.record(out["user"], 2, 50_000, task.USER_OFFSET, camera=True)
    bits = np.random.default_rng(1).integers(0, 2, BITS).astype(np.uint8)
    out["key"].write_bytes(np.packbits(bits).tobytes())
    out["key"].chmod(0o600)
    if not (out["policy"] / "config.json").exists():
        built = pi_tiny.build_pi(
            kind, pi_tiny.build_tokenizer(root / "tok"), task.dataset_stats(out["general"])
        )
        task.train_base(out["general"], out["policy"], steps=3, built=built)
    users = [(out["user"], KeySource(bits, "file"))]
    for mode, cfg in (
        ("unsealed", PersonalizeConfig.of(**TINY)),
        ("sealed", PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 8, "payload": "peft-lora"}))),
    ):
        out[mode] = root / f"{kind}-{mode}.prop"
        if not (out[mode] / "manifest.json").exists():
            general = out["general"] if mode == "unsealed" else None
            api.personalize_checkpoint(str(out["policy"]), users, out[mode], cfg, general=general)
    return out


def audit(paths: dict[str, Path], mode: str, max_leak: float, samples: int | None) -> dict:
    from prop_cli import api
    from prop_cli.attack.verdict import apply_max_leak
    from prop_cli.config import AuditSettings

    t = time.perf_counter()
    settings = AuditSettings() if samples is None else AuditSettings(samples=samples)
    report = api.audit_bundle(paths[mode], paths["user"], settings, key_files=[paths["key"]],
                              original=str(paths["policy"]))  # fmt: skip
    apply_max_leak(report, max_leak)
    report["process_seconds"] = time.perf_counter() - t
    return report


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", default="pi05,pi0")
    ap.add_argument("--modes", default="unsealed,sealed")
    ap.add_argument("--work", type=Path, default=None, help="build here (reused when it holds a build)")
    ap.add_argument("--max-leak", type=float, default=0.05)
    ap.add_argument("--samples", type=int, default=None, help="the audit's --samples (default: its own)")
    args = ap.parse_args(argv)
    print("command:", shlex.join([Path(sys.executable).name, "-m", "benchmarks.bench_audit_pi", *argv]))
    from examples import pi_tiny

    work = args.work or Path(tempfile.mkdtemp(prefix="prop-audit-pi-"))
    rows = []
    with pi_tiny.tiny():
        for kind in [k.strip() for k in args.kinds.split(",") if k.strip()]:
            (work / kind).mkdir(parents=True, exist_ok=True)
            paths = build(kind, work / kind)
            for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
                r = audit(paths, mode, args.max_leak, args.samples)
                rows.append((kind, mode, r))
                (work / f"{kind}-{mode}.json").write_text(json.dumps(r, indent=1, default=str))
    probes = []
    for _, _, r in rows:
        probes += [p for p in r["speed"]["stage_seconds"] if p not in probes]
    print("| probe | " + " | ".join(f"{k} {m}" for k, m, _ in rows) + " |")
    print("|---" * (len(rows) + 1) + "|")
    for p in probes:
        cells = [f"{r['speed']['stage_seconds'][p]:.1f} s" if p in r["speed"]["stage_seconds"] else ""
                 for _, _, r in rows]  # fmt: skip
        print(f"| {p} | " + " | ".join(cells) + " |")
    print(
        "| audit (`wall_seconds`) | "
        + " | ".join(f"{r['speed']['wall_seconds']:.1f} s" for *_, r in rows)
        + " |"
    )
    for kind, mode, r in rows:
        cov = r["coverage"]
        print(f"{kind} {mode}: not tried {cov['not_tried'] or 'none'}, cut short "
              f"{cov['cut_short'] or 'none'}; {r['max_leak']['verdict']}")  # fmt: skip


if __name__ == "__main__":
    main()
