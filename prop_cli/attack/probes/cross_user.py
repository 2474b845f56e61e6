"""Cross-user: the other users' keys (second and later ``--key-file``) on the audited user's behaviour."""

from __future__ import annotations

from .base import Group, Probe, ProbeContext, on_original


def run(ctx: ProbeContext) -> list[Group]:
    return [
        Group(f"user {j}", ctx.probe_keys(k, f"user {j}"), is_key=True)
        for j, k in enumerate(ctx.keys[1:], start=2)
    ]


PROBE = Probe(
    "cross-user", "cross-user", "key", "another user's key (a second --key-file) on your behaviour", run,
    control=on_original(run), needs="other-keys",
)  # fmt: skip
