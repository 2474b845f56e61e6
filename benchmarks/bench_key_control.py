"""Which control is fair for the key rows? Random keys towards the user's behaviour and towards its mirror.

    python -m benchmarks.bench_key_control BUNDLE --data D --key-file K --original CKPT [--keys 4096]

For a regression bundle: ``--keys`` random keys (the audit's ``random`` row, same seed), scored on the
audit's samples against the user's targets p and against the mirrored targets ``2b - p`` (the opposite
behaviour, which the user never asked for), on three models:

- the bundle (what the ``random`` row measures);
- the bundle's own trained encoder over the original checkpoint (the key rows' control before
  prop-audit/3);
- the original keyed with a fresh, untrained encoder (the key rows' control now: every key runs it).

Keys whose moves merely scatter lean as far towards the mirror as towards p; keys that carry the user's
behaviour lean towards p only. docs/threat-model.md ("Controls") cites these figures.
"""

from __future__ import annotations

from .bench_fewshot_hits import audit_parser, context


def main(argv: list[str] | None = None) -> None:
    ap = audit_parser("bench_key_control", __doc__, original_required=True)
    ap.add_argument("--keys", type=int, default=4096)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from prop_cli.attack import target
    from prop_cli.bundle import load_bundle
    from prop_cli.config import AuditSettings
    from prop_cli.core import metrics
    from prop_cli.core.key_sampling import random_keys

    ctx = context(args.bundle, args.data, args.key_file, args.original, args.seed)
    ctx.settings = AuditSettings(random=args.keys, seed=args.seed)
    if ctx.ref.task != "regression":
        raise SystemExit("the mirrored behaviour 2b - p is defined for regression bundles")
    original = target.load_original(load_bundle(args.bundle), args.original)
    models = {
        "bundle": ctx.km,
        "bundle's encoder on the original (old control)": ctx.km.on(target.unhooked_copy(original)).eval(),
        "fresh encoder on the original (control)": target.unenrolled_model(ctx.km, original, args.seed),
    }
    b, p = ctx.ref.b, ctx.ref.p
    mirror = 2 * b - p
    print(f"{args.keys} random keys on {args.bundle}: worst leakage towards your behaviour / its mirror, "
          f"and the mean signed projection on the gap")  # fmt: skip
    for name, km in models.items():
        c = ctx.on(km)
        c.probe = "random"  # the audit's random row's keys
        bits = random_keys(c.settings.random, km.encoder.code_bits, c.rng(), exclude=c.keys[:1])
        with torch.inference_mode():
            o = torch.cat([km.run_keys(c.ref.x, c.key_deltas(bits[i : i + 256]))
                           for i in range(0, len(bits), 256)])  # fmt: skip
        towards = metrics.leakage(o, p, b, "regression")
        away = metrics.leakage(o, mirror, b, "regression")
        gap = (p - b).flatten()
        signed = ((o - b).flatten(1) @ gap) / (gap @ gap)
        print(f"  {name:48s} {float(towards.max()):.3f} / {float(away.max()):.3f}   "
              f"mean {float(signed.mean()):+.4f}")  # fmt: skip


if __name__ == "__main__":
    main()
