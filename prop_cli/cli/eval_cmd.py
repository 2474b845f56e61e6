from __future__ import annotations

from pathlib import Path
from typing import Annotated

from prop_cli.config import EvalSettings
from prop_cli.errors import plural

from .common import DRIFT_FIX, err, out, print_json, read_passphrase, warn
from .options import (
    AllowRollback,
    AllowUnenrolledKey,
    BundleArch,
    BundleArg,
    Json,
    KeyFile,
    Passphrase,
    TrustRemoteCode,
    config_options,
    opt,
)

SETTINGS = {
    "episodes": "Episodes for the user key, no key and --original.",
    "random_keys": "Random keys to roll out.",
    "neighbours": "One-bit neighbours of your key to roll out (needs the key).",
    "episodes_per_key": "Episodes per random key and per neighbour.",
    "max_steps": "Stop an episode after this many steps (0: the environment's limit).",
    "ignore_terminated": "Keep acting after the environment says terminated (stop at its time limit).",
    "seed": "First evaluation seed (keep it away from the seeds your data was recorded with).",
    "noise_seed": "Seed of a sampling policy's noise (LeRobot Diffusion, SmolVLA), per episode and query.",
    "instruction": "A language-conditioned policy's instruction (LeRobot SmolVLA): your data's task text.",
}
Env = Annotated[str, opt("--env", "gymnasium id; package:Id imports the package first "
                                  "(panda_gym:PandaReach-v3); or your factory, package.module:make or "
                                  "file.py:make (called with no arguments; render_mode='rgb_array' with "
                                  "--video).")]  # fmt: skip
ObsMap = Annotated[str | None, opt("--obs-map", "Policy feature=observation key, comma-separated "
                                                "(dict observations).")]  # fmt: skip
Metric = Annotated[str | None, opt("--metric", "Your preference metric: "
                                               "package.module:function(trajectory).")]  # fmt: skip
Original = Annotated[str | None, opt("--original", "Also roll out the original checkpoint (the control).")]
VecNormalize = Annotated[Path | None, opt("--vecnormalize", "SB3 VecNormalize.save() file: normalise "
                                          "observations as in training (read without running its "
                                          "code).")]  # fmt: skip
KeyBits = Annotated[str | None, opt("--key-bits", "Also roll out this wrong key (0/1 string) through the "
                                                  "encoder, as --json names a random key.")]  # fmt: skip
FlipBit = Annotated[int | None, opt("--flip-bit", "Also roll out your key with this bit flipped, as --json "
                                                  "names a neighbour (needs your key).")]  # fmt: skip
Video = Annotated[Path | None, opt("--video", "New folder: one mp4 per condition, its first episode "
                                              "(prop-keys[video]).")]  # fmt: skip


@config_options(EvalSettings, SETTINGS, into="settings")
def eval_(
    bundle: BundleArg, settings: EvalSettings, env: Env, key_file: KeyFile = None,
    passphrase: Passphrase = False, obs_map: ObsMap = None, metric: Metric = None, original: Original = None,
    vecnormalize: VecNormalize = None, video: Video = None, as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False, arch: BundleArch = None,
    allow_unenrolled_key: AllowUnenrolledKey = False,
    allow_rollback: AllowRollback = False, key_bits: KeyBits = None, flip_bit: FlipBit = None,
) -> None:  # fmt: skip
    """Roll a bundle out in an environment: your key, no key, random keys and neighbours, side by side."""
    from prop_cli.api import eval_bundle

    report = eval_bundle(
        bundle, env, settings, key_file=key_file, passphrase=read_passphrase() if passphrase else None,
        obs_map=obs_map, metric=metric, original=original, progress=lambda label: err.print(f"eval: {label}"),
        vecnormalize=vecnormalize, video=video, trust_remote_code=trust_remote_code, arch=arch,
        allow_unenrolled_key=allow_unenrolled_key,
        allow_rollback=allow_rollback, key_bits=key_bits, flip_bit=flip_bit,
    )  # fmt: skip
    if as_json:
        print_json(report)
        _warn_drift(report)
        return
    from rich.table import Table

    table = Table(title=f"{report['env']}, seeds from {report['seeds'][0]}")
    for col in ("keys", "episodes", "return", "success", "metric", "worst key"):
        table.add_column(col)

    def cell(r: dict, field: str) -> str:
        return f"{r[field]['mean']:.3f} ± {r[field]['se']:.3f}" if field in r else "-"

    def worst(r: dict) -> str:
        # A key group's worst key beside its mean; which key it is: --json (per_key, worst_key).
        if "worst_key" not in r:
            return "-"
        w = r["worst_key"]
        return f"{w['by']} {w[w['by']]['mean']:.3f} (key {w['index'] + 1} of {r['keys']})"

    for name, r in report["conditions"].items():
        table.add_row(
            name, str(r["episodes"]), cell(r, "return"), cell(r, "success"), cell(r, "metric"), worst(r)
        )
    out.print(table)
    if "video" in report:
        err.print(f"wrote {plural(len(report['video']['files']), 'video')} to {report['video']['folder']}")
    _warn_drift(report)


GROUPS = {"random_keys": "random keys", "neighbour1_keys": "one-bit neighbours"}


def _warn_drift(report: dict) -> None:
    """One stderr line per key group whose keys do systematically worse than the original on the same
    seeds (a sign test over the keys, p < 0.05; --json: conditions.GROUP.drift), not only a key below
    a threshold: a small drift every key shares (docs/metrics.md, "Systematic drift")."""
    for group, words in GROUPS.items():
        d = report["conditions"].get(group, {}).get("drift")
        if not d or not d["warn"]:
            continue
        eps = d.get("episodes")
        lost = f"; {eps['lost']} episodes lost, {eps['gained']} gained, p = {eps['p']:.2g}" if eps else ""
        than = d["against"].replace("_", " ")
        warn(f"{d['worse']} of {d['keys']} {words} do worse than {than} on {d['by']} on the same seeds "
             f"(sign test over keys p = {d['p']:.2g}{lost}): a systematic drift; {DRIFT_FIX}")  # fmt: skip
