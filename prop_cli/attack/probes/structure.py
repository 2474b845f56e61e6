"""Encoder structure: candidate codes read off the encoder's weights and derivatives, then probed.

No data, no search over the model. The user's code is the one encoder input present in every
training step, and training imprints it on the encoder:

- head imprint: the encoder's last layer starts at zero, so all it holds was written by training;
  its top right singular vectors are the hidden directions the trained codes light up, and
  ``sign(W1^T v)`` (also through tanh's slope at the zero code) maps one back to a code;
- Jacobian: top right singular vectors of d(head pre-activation)/d(code) at the zero code and at a
  few random codes;
- latent norm: a data-free relaxed search for codes whose delta is far from 1 (a large head output);
  only trained codes have one;
- W1 SVD: top singular vectors of the first layer alone (weak; kept as a floor);
- init difference: W1 minus its initialisation recreated from the manifest's seed, where it has one;
- antipode vote: the random codes whose delta is farthest from 1, their bitwise majority. Trained to
  pull every wrong key's delta to 1 (``--delta-pull``), a near-odd encoder leaves the largest deltas
  around the user's antipode, so the vote's negation lands a few bits from the user's code (found
  attacking issue 32's fix: 2 of 128 bits off, leakage 0.94, where the same vote was 35 bits off
  before the pull); both signs are probed;
- delta PCA: the same scan's heads, their top principal directions regressed on the codes (a near-odd
  encoder's delta - 1 follows the code's projection on the user's): 0-1 bits off on IL bundles;
- and a greedy bit-flip refinement of the attacker's pick on the same data-free objective.

Every candidate is rounded to ±1 (both signs: a singular vector's sign is arbitrary) and probed as a
code. Kind "key": the candidates are concrete codes, each a fixed behaviour anyone holding the files
can run, so they are scored like keys (leakage, not bounded leakage), not against a search on the
original. Control: the same analysis of a freshly initialised encoder of the same shape on the
reference model: ``ProbeContext.unenrolled``, whose encoder is built from the audit's ``--seed``
(what the structure gives when training wrote nothing into it; the same figures on every run).
"""

from __future__ import annotations

import torch
from torch import nn

from prop_cli.core.keyed_model import KeyEncoder

from .base import Group, Probe, ProbeContext, on_unenrolled

TOP = 3  # singular vectors per matrix
JACOBIAN_POINTS = 4  # random codes besides the zero code
NORM_RESTARTS, NORM_STEPS, NORM_LR = 16, 100, 0.1
FLIP_PASSES = 2
VOTE_CODES, VOTE_TOP, VOTE_CHUNK = 16384, 64, 1024  # code scan: codes, antipode voters, rows per forward
SCAN_DIMS, SCAN_PCS = 256, 4  # code scan's delta PCA: projected width, principal directions regressed


def _linears(enc: KeyEncoder) -> list[nn.Linear]:
    return [m for m in enc.net if isinstance(m, nn.Linear)]


def _both(dirs: torch.Tensor) -> torch.Tensor:
    s = torch.where(dirs >= 0, 1.0, -1.0)
    return torch.cat([s, -s])


def _head_norm(enc: KeyEncoder, codes: torch.Tensor) -> torch.Tensor:
    """How far each code's delta is from 1, before the scale: ||tanh(head(c))||^2."""
    return (torch.tanh(enc.net(codes)) ** 2).sum(-1)


@torch.no_grad()
def head_imprint(enc: KeyEncoder) -> torch.Tensor:
    lins = _linears(enc)
    if len(lins) != 2:  # the read-back goes through exactly one hidden layer
        return torch.zeros(0, enc.code_bits)
    first, last = lins
    vh = torch.linalg.svd(last.weight, full_matrices=False).Vh[:TOP]  # (TOP, hidden)
    slope = 1 - torch.tanh(first.bias) ** 2  # tanh's slope at the zero code
    return _both(torch.cat([vh @ first.weight, (vh * slope) @ first.weight]))


def jacobian(enc: KeyEncoder, gen: torch.Generator) -> torch.Tensor:
    rand = torch.rand(JACOBIAN_POINTS, enc.code_bits, generator=gen) * 2 - 1
    points = torch.cat([torch.zeros(1, enc.code_bits), rand])
    dirs = []
    blank = enc.blank()
    for c in points.to(enc.net[0].weight.device):
        if blank:  # a zero head: the Jacobian is 0 exactly (jacrev would give the same zeros, slowly)
            jac = torch.zeros(sum(enc.features), enc.code_bits, device=c.device)
        else:
            jac = torch.func.jacrev(lambda z: enc.net(z[None])[0])(c)  # (F, n)
        dirs.append(torch.linalg.svd(jac, full_matrices=False).Vh[:2])
    return _both(torch.cat(dirs))


def latent_norm(enc: KeyEncoder, gen: torch.Generator) -> torch.Tensor:
    u = torch.rand(NORM_RESTARTS, enc.code_bits, generator=gen).clamp(0.02, 0.98)
    theta = torch.logit(u).to(enc.net[0].weight.device).requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=NORM_LR)
    # A zero head: every gradient is 0 and Adam leaves theta as it is, so the steps are not taken.
    for _ in range(0 if enc.blank() else NORM_STEPS):
        loss = -_head_norm(enc, torch.tanh(theta / 2)).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        return torch.where(theta >= 0, 1.0, -1.0)  # rounded; the search's own sign is meaningful


@torch.no_grad()
def w1_svd(enc: KeyEncoder) -> torch.Tensor:
    w = _linears(enc)[0].weight
    return _both(torch.cat([torch.linalg.svd(m, full_matrices=False).Vh[:TOP]
                            for m in (w, w - w.mean(0, keepdim=True))]))  # fmt: skip


@torch.no_grad()
def code_scan(enc: KeyEncoder, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """Two reads of one scan of VOTE_CODES random codes' heads (``tanh(head(c))``: the delta's direction
    before the scale):

    - ``antipode_vote``: the bitwise majority of the VOTE_TOP codes whose delta is farthest from 1;
    - ``delta_pca``: the heads' top SCAN_PCS principal directions (in a fixed random projection to at most
      SCAN_DIMS dimensions, so the scan holds VOTE_CODES x SCAN_DIMS floats whatever the keyed width),
      each code's coordinate on them regressed on the codes. A near-odd encoder gives delta(c) - 1 ~
      f(c . u) v, so the regression's signs are +- the user's code u (found attacking --harden's
      antipode codes: 0 and 1 bits off on a hardened and a default IL bundle, where the vote was off
      by more)."""
    dev = enc.net[0].weight.device
    codes = (torch.randint(0, 2, (VOTE_CODES, enc.code_bits), generator=gen).float() * 2 - 1).to(dev)
    width = enc.net(codes[:1]).shape[1]
    proj = None
    if width > SCAN_DIMS:
        proj = (torch.randn(width, SCAN_DIMS, generator=gen) / SCAN_DIMS**0.5).to(dev)
    norms, heads = [], []
    blank = enc.blank()  # a zero head: every head is 0 exactly, not computed
    for i in range(0, VOTE_CODES, VOTE_CHUNK):
        c = codes[i : i + VOTE_CHUNK]
        h = c.new_zeros(len(c), width) if blank else torch.tanh(enc.net(c))
        norms.append((h**2).sum(-1))
        heads.append(h if proj is None else h @ proj)
    head = torch.cat(heads)
    head = head - head.mean(0)
    pcs = torch.linalg.svd(head, full_matrices=False).Vh[:SCAN_PCS]
    return {
        "antipode_vote": _both(codes[torch.cat(norms).topk(VOTE_TOP).indices].sum(0, keepdim=True)),
        "delta_pca": _both((head @ pcs.T).T @ codes),
    }


@torch.no_grad()
def init_difference(enc: KeyEncoder, seed: int | None) -> torch.Tensor:
    if seed is None:
        return torch.zeros(0, enc.code_bits)
    lins = _linears(enc)
    state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)  # the trainer seeds torch, then builds the encoder first
        fresh = KeyEncoder(enc.code_bits, enc.features, [m.out_features for m in lins[:-1]], enc.scale)
    finally:
        torch.random.set_rng_state(state)
    diff = lins[0].weight - _linears(fresh)[0].weight.to(lins[0].weight.device)
    return _both(torch.linalg.svd(diff, full_matrices=False).Vh[:TOP])


@torch.no_grad()
def refine(enc: KeyEncoder, code: torch.Tensor) -> torch.Tensor:
    """Greedy: flip the bit that most increases the head norm, while one does."""
    c = code.clone()
    n = len(c)
    eye = torch.arange(n, device=c.device)
    for _ in range(FLIP_PASSES * n):
        flips = c[None].repeat(n, 1)
        flips[eye, eye] *= -1
        val = _head_norm(enc, flips)
        j = int(torch.argmax(val))
        if val[j] <= _head_norm(enc, c[None])[0]:
            break
        c = flips[j]
    return c


def run(ctx: ProbeContext) -> list[Group]:
    enc = ctx.km.encoder
    if enc.blank():
        ctx.shortcut("the encoder's head is zero: its Jacobian is 0 and its heads are 0, not computed; the "
                     "data-free norm search is not stepped (Adam would not move it)")  # fmt: skip
    gen = ctx.generator()
    dev = ctx.ref.x.device
    methods = {
        "head_imprint": head_imprint(enc),
        "jacobian": jacobian(enc, gen),
        "latent_norm": latent_norm(enc, gen),
        "w1_svd": w1_svd(enc),
        **code_scan(enc, gen),
        "init_difference": init_difference(enc, ctx.seed_hint),
    }
    methods = {k: v.to(dev) for k, v in methods.items() if len(v)}
    codes = torch.cat(list(methods.values()))
    values = ctx.probe_codes(codes, "structure")
    best = int(torch.argmax(values["divergence"]))  # the attacker's pick, refined without data
    refined = refine(enc, codes[best])
    more = ctx.probe_codes(refined[None], "structure")
    codes = torch.cat([codes, refined[None]])
    values = {k: torch.cat([values[k], more[k]]) for k in values}
    info: dict = {"candidates": int(len(codes)), "methods": {}}
    user = ctx.codes(ctx.keys[0])[0] if ctx.has_key else None
    start = 0
    for name, c in [*methods.items(), ("bitflip_refine", refined[None])]:
        part = slice(start, start + len(c))
        start += len(c)
        m: dict = {"candidates": int(len(c)), "best_divergence": float(values["divergence"][part].max())}
        if "leakage" in values:
            m["worst_leakage"] = float(values["leakage"][part].max())
        if user is not None:
            m["min_code_distance"] = int((c != user).sum(1).min())
        info["methods"][name] = m
    return [Group("structure", values, is_key=ctx.encoding == "raw", search=info, codes=codes)]


PROBE = Probe(
    "structure", "structure", "key",
    "codes read off the encoder's weights and Jacobian (no data), probed as codes", run,
    control=on_unenrolled(run),
    white_box=True,
)  # fmt: skip
