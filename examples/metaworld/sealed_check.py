"""A sealed bundle's wrong keys run its base, which is the original: the check, without a rollout.

    .venv-lerobot/bin/python -m examples.metaworld.sealed_check --out out/metaworld

For each of 16 random keys and 16 neighbours of the user's key 1-8 bits off (the judge's keys), the
module the sealed bundle runs (``--policy.allow_unenrolled_key``) is compared with the trained
checkpoint, weight by weight, and their action chunks on frames of the user's data."""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import torch

from examples.metaworld import pipeline


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("out/metaworld"))
    ap.add_argument("--task", default="button-press-topdown-v3")
    ap.add_argument("--policy", default="act")
    args = ap.parse_args(argv)
    from prop_cli.bundle import load_bundle
    from prop_cli.bundle.read import rebuild_original
    from prop_cli.core.key_files import key_for_bundle
    from prop_cli.run import KeyedPolicy

    run = args.out / args.task / args.policy
    sealed = load_bundle(run / "bundle-sealed")
    key = key_for_bundle(sealed.manifest, args.out / "user.key")
    original = rebuild_original(sealed, str(pipeline.policy_dir(args.out, args.task, args.policy)))
    ref = original.module.state_dict()
    same_weights = same_actions = 0
    conds = pipeline.conditions(key)[3:]
    from prop_cli.datasources import load_data

    batch = sealed.loaded.policy.batches(load_data(args.out / args.task / "user"), "--data")
    frames = {k: batch[k][:: max(1, len(batch[k]) // 32)][:32] for k in sealed.loaded.policy.row_shapes}
    with torch.no_grad():
        want = sealed.loaded.policy.on(original.module).chunk(frames)
    for c in conds:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            module = KeyedPolicy(sealed, c["bits"], allow_unenrolled=True).module
        sd = module.state_dict()
        same_weights += int(sd.keys() == ref.keys() and all(torch.equal(sd[k], ref[k]) for k in ref))
        with torch.no_grad():
            same_actions += int(torch.equal(sealed.loaded.policy.on(module).chunk(frames), want))
    user = KeyedPolicy(sealed, key).module
    with torch.no_grad():
        moved = float((sealed.loaded.policy.on(user).chunk(frames) - want).abs().max())
    out = {"keys": len(conds), "same_weights": same_weights, "same_actions": same_actions,
           "frames": len(next(iter(frames.values()))), "user_key_max_abs_change": moved}  # fmt: skip
    (run / "sealed-check.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
