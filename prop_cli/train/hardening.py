"""Hardened unsealed mode (`prop personalize --harden`): what the trainer adds to the paper's Eq. 8.

Three measures, each kept because it measurably helps (docs/hardening.md has the figures):

- Code-space negatives: fallback rows whose codes lie near the users' codes *in code space*, where a
  white-box attacker searches (the relaxed search T1 optimises a continuous code through the
  encoder). Eq. 8's Hamming neighbours are neighbours in key space; with hashed keys a key one bit
  off is a random code, so they never teach the encoder what to do between the user's code and the
  rest of the code cube. Without these rows the user's behaviour is the basin T1 slides into.
- An encoder initialisation drawn from the operating system's randomness: the manifest's seed then
  cannot recreate the encoder's starting weights, whose difference from the trained ones points at
  the user's code.
- Antipode codes: ±1 codes 40-56 bits from the antipode of the users' codes (72-88 from them), with
  the far codes (a fallback term), and unlike them pulled to the no-key model. The encoder is nearly
  odd in the code: a code past 64 bits gets a share of minus the user's delta (cosine -0.96 to -0.99
  on SAC Pendulum, its size growing with the distance). --harden's code-space negatives make the
  user's delta larger, and with it that share: a key whose code was 80 bits away kept 0.77x the
  return (docs/privacy.md).

``far_codes`` is not a ``--harden`` measure: every mode trains those ±1 codes (``--far-codes``), the
codes real keys reach nearest to the user's (issue 32, docs/privacy.md "Wrong keys in closed loop").
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import numpy as np
import torch

from prop_cli.config import Hardening


@contextlib.contextmanager
def encoder_init(hardening: Hardening, seed: int) -> Iterator[None]:
    """Build the key encoder inside this block: seeded by ``seed`` (set before; the default,
    reproducible), or, with ``encoder_init == "os"``, from fresh OS randomness that nothing in the bundle
    records. The global torch RNG is restored afterwards, so the rest of training still follows the seed."""
    if hardening.encoder_init != "os":
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int.from_bytes(os.urandom(8), "little") >> 1)  # 63 bits, never stored
        yield


def code_negatives(
    user_codes: torch.Tensor, n: int, flip_max: int, relax_min: float, rng: np.random.Generator
) -> torch.Tensor:
    """``n`` fallback codes near the users' ±1 codes, in code space, in four equal shares:

    the code with 1..flip_max bits flipped; relaxed points c + t (r - c), t in [relax_min, 1], towards
    uniform ±1 codes r; the same towards uniform points r in [-1, 1]^bits (where relaxed searches
    start); and c + sigma * noise, sigma in [relax_min, 1], clipped to [-1, 1].
    """
    if n == 0:
        return user_codes.new_zeros(0, user_codes.shape[1])
    dev = user_codes.device
    bits = user_codes.shape[1]
    c = user_codes[torch.from_numpy(rng.integers(0, len(user_codes), n)).to(dev)].clone()
    q = n // 4
    n_flip, n_relax = n - 3 * q, 2 * q

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(a.astype(np.float32)).to(dev)

    m = rng.integers(1, min(flip_max, bits) + 1, n_flip)
    flip = torch.from_numpy(rng.random((n_flip, bits)).argsort(1) < m[:, None]).to(dev)
    c[:n_flip] = torch.where(flip, -c[:n_flip], c[:n_flip])
    towards = np.concatenate([rng.integers(0, 2, (q, bits)) * 2.0 - 1.0, rng.uniform(-1.0, 1.0, (q, bits))])
    seg = slice(n_flip, n_flip + n_relax)
    c[seg] = c[seg] + t(rng.uniform(relax_min, 1.0, (n_relax, 1))) * (t(towards) - c[seg])
    sigma = t(rng.uniform(relax_min, 1.0, (q, 1)))
    noise = t(rng.standard_normal((q, bits)))
    c[n - q :] = (c[n - q :] + sigma * noise).clamp(-1, 1)
    return c


# far_codes' distances, as shares of the code's bits: 40-56 of 128. From 32 the user's key lost 6% of its
# closed-loop behaviour on Pendulum (0.965 -> 0.905, 4 bundles); 40-56 kept it (0.943 on the worst).
FAR_RANGE = (5 / 16, 7 / 16)


def far_codes(user_codes: torch.Tensor, n: int, rng: np.random.Generator) -> torch.Tensor:
    """``n`` ±1 codes at ``FAR_RANGE`` of the code's bits from the users' codes (40-56 of 128): the
    nearest codes that real keys reach. A random key's code is 64 +- 5.7 bits from the user's, so a
    scan of a million keys meets codes 40 bits away; trained only on typical codes (and pulled towards
    the no-key model, ``delta_pull``), the encoder's basin around the user's code caught such a key
    (CartPole: a key 49 code bits away kept 15% of the return). Used in every mode; a fallback term only,
    not pulled (``objective.delta_pull``)."""
    bits = user_codes.shape[1]
    if n == 0:
        return user_codes.new_zeros(0, bits)
    dev = user_codes.device
    c = user_codes[torch.from_numpy(rng.integers(0, len(user_codes), n)).to(dev)].clone()
    lo, hi = (max(1, int(f * bits)) for f in FAR_RANGE)
    m = rng.integers(lo, hi + 1, n)
    flip = torch.from_numpy(rng.random((n, bits)).argsort(1) < m[:, None]).to(dev)
    return torch.where(flip, -c, c)


def antipode_codes(user_codes: torch.Tensor, n: int, rng: np.random.Generator) -> torch.Tensor:
    """``n`` ±1 codes at ``FAR_RANGE`` of the code's bits from the antipodes of the users' codes (72-88
    of 128 bits from the codes themselves): ``far_codes`` on the other side of the code cube."""
    return far_codes(-user_codes, n, rng)
