"""Cross-user: other keys (second and later ``--key-file``) on the audited user's behaviour.

Only a key that is a user of the bundle (``ProbeContext.enrolment``: a sealed bundle's key opens one of
its records; an unsealed bundle's moves the outputs like no random key does, with more than one user in
the manifest) gets a cross-user row, ``user j``. It measures how much of your behaviour that user's key
shows beyond what that user's own behaviour explains:

- sealed: each record is trained on its own user's data alone, so what user j's key shows is user j's
  enrolled behaviour, and that is the control (beyond it: 0), unless the key opens *your* record (then
  the control is the reference, and the row is your behaviour);
- unsealed: users share one encoder trained on every user's data, so their enrolled behaviour is not
  theirs alone: the control is unavailable, and the row is gated on its own figure.

Any other key is audited as a plain key (row ``key j``, threat T0, the key rows' control), with one
warning line.
"""

from __future__ import annotations

from .base import Group, Probe, ProbeContext

UNSEALED_NO_CONTROL = (
    "unsealed users share one encoder trained on every user's data: what this user's own behaviour "
    "explains cannot be told apart from yours (a sealed bundle trains each user alone)"
)


def run(ctx: ProbeContext) -> list[Group]:
    groups = []
    for j, k in enumerate(ctx.keys[1:], start=2):
        who = ctx.enrolment(k)
        if who.user:
            g = Group(f"user {j}", ctx.probe_keys(k, f"user {j}"), is_key=True, bits=k[None])
            g.extra = {"enrolment": {"how": who.how, "yours": who.yours, "independent": who.independent}}
            if not (who.yours or who.independent):
                g.extra["control_unavailable"] = UNSEALED_NO_CONTROL
        else:
            g = Group(f"key {j}", ctx.probe_keys(k, f"key {j}"), is_key=True, bits=k[None], threat="T0",
                      note=f"--key-file {j} is not a user of this bundle ({who.how}): audited as a plain "
                      f"key, row 'key {j}'")  # fmt: skip
            g.extra = {"enrolment": {"how": who.how, "yours": False, "independent": False}}
        groups.append(g)
    return groups


def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
    out = []
    for g in found:
        who = g.extra["enrolment"]
        if g.name.startswith("key ") or who["yours"]:  # the reference: where no user was enrolled
            out.append(Group(g.name, ctx.on(ctx.unenrolled).probe_keys(g.bits, f"{g.name} control"), True))
        elif who["independent"]:  # user j's own record, trained without your data: their behaviour
            own = f"{g.name}'s own record, trained on their data alone"
            out.append(Group(g.name, g.values, True, model=own))
    return out  # unsealed users: no control (UNSEALED_NO_CONTROL)


PROBE = Probe(
    "cross-user", "cross-user", "key",
    "another user's key (a second --key-file) on your behaviour, beyond that user's own", run,
    control=control, needs="other-keys",
)  # fmt: skip
