"""The paper's baselines, trained with the same Eq. 8 key sampling as prop.

- ``KeyInputMLP``: the key (as ±1 bits) concatenated to the input of an MLP.
- ``StateCVAE``: a conditional VAE (Sohn et al. 2015) conditioned on the state x, the variant the paper
  found better: the recognition net encodes (key, x) to a latent z ~ N(mu, sigma), prior N(0, I), and the
  decoder maps (z, x) to the output. At evaluation z = mu, so a key gives one deterministic behaviour.

Both are sized by one width to within +-10% of PRoP's total (base + encoder) parameter count
(``fit_width``). Training rows per step are the trainer's: user keys on user data (personal targets),
K1 Hamming neighbours and K2 random keys on fallback inputs, and the "no key" rows (an all-zero key
input here), with the original model's outputs as fallback targets (distillation, as prop does).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from examples import mlp
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_sampling import KeySampler
from prop_cli.core.keyed_model import key_codes
from prop_cli.train.objective import row_loss

CVAE_LATENT = 16
CVAE_BETA = 1e-3  # small: the decoder must read the key from z, a strong KL pull would erase it


def n_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


class KeyInputMLP(nn.Module):
    def __init__(self, in_dim: int, key_bits: int, out_dim: int, hidden: int) -> None:
        super().__init__()
        self.net = mlp([in_dim + key_bits, hidden, hidden, out_dim])

    def forward(self, x: torch.Tensor, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.net(torch.cat([x.flatten(1), codes], 1)), x.new_zeros(())


class StateCVAE(nn.Module):
    def __init__(self, in_dim: int, key_bits: int, out_dim: int, hidden: int, latent: int = CVAE_LATENT):
        super().__init__()
        self.latent = latent
        self.enc = nn.Sequential(
            nn.Linear(key_bits + in_dim, hidden), nn.ReLU(), nn.Linear(hidden, 2 * latent)
        )
        self.dec = mlp([latent + in_dim, hidden, hidden, out_dim])

    def forward(self, x: torch.Tensor, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(output, mean KL to the prior); samples z while training, z = mu in eval mode."""
        x = x.flatten(1)
        mu, logvar = self.enc(torch.cat([codes, x], 1)).chunk(2, dim=1)
        logvar = logvar.clamp(-8, 8)
        z = mu + torch.randn_like(mu) * (0.5 * logvar).exp() if self.training else mu
        kl = 0.5 * (mu**2 + logvar.exp() - 1 - logvar).sum(1).mean()
        return self.dec(torch.cat([z, x], 1)), kl


BUILDERS: dict[str, Callable[..., nn.Module]] = {"MLP": KeyInputMLP, "CVAE": StateCVAE}


def split_name(method: str) -> tuple[str, str]:
    """ "MLP" -> ("MLP", "raw"); "MLP-hashed" -> ("MLP", "hashed")."""
    arch, _, enc = method.partition("-")
    return arch, enc or "raw"


def fit_width(name: str, in_dim: int, key_bits: int, out_dim: int, budget: int) -> int:
    """The hidden width whose parameter count is closest to ``budget``."""
    best, best_gap = 1, math.inf
    lo, hi = 1, 4096
    while lo <= hi:  # counts grow with width: bisect, then check the neighbours
        mid = (lo + hi) // 2
        if n_params(BUILDERS[name](in_dim, key_bits, out_dim, mid)) < budget:
            lo = mid + 1
        else:
            hi = mid - 1
    for w in (lo - 1, lo, lo + 1):
        if w >= 1:
            gap = abs(n_params(BUILDERS[name](in_dim, key_bits, out_dim, w)) - budget)
            if gap < best_gap:
                best, best_gap = w, gap
    return best


def build(name: str, in_dim: int, key_bits: int, out_dim: int, budget: int, seed: int) -> nn.Module:
    torch.manual_seed(seed)
    return BUILDERS[name](in_dim, key_bits, out_dim, fit_width(name, in_dim, key_bits, out_dim, budget))


def train(
    model: nn.Module,
    users: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    pool: np.ndarray,
    pool_targets: torch.Tensor,
    task: str,
    cfg: PersonalizeConfig,
    steps: int,
    encoding: str = "raw",
) -> nn.Module:
    """Eq. 8 with the trainer's row counts: ``users`` = [(x, y, key bits)], fallback inputs ``pool``.

    ``encoding`` is how key bits become the model's key input (prop_cli.core.keyed_model.key_codes):
    "raw" = the paper's ±1 bits; "hashed" = prop's SHAKE-256 code, to separate the encoding's effect from
    PRoP's.
    """
    rng = np.random.default_rng(cfg.train.seed)
    torch.manual_seed(cfg.train.seed)
    sampler = KeySampler([k for _, _, k in users], cfg.mode.hamming_radius, rng)
    ux = [torch.from_numpy(x) for x, _, _ in users]
    uy = [torch.from_numpy(y if task == "classification" or y.ndim > 1 else y[:, None]) for _, y, _ in users]
    ucodes = key_codes(np.stack([k for _, _, k in users]), encoding)
    px = torch.from_numpy(pool)
    per_user = max(1, cfg.train.user_rows // len(users))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.mode.lr)
    floor = cfg.train.lr_floor
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda t: floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t / steps))
    )
    model.train()
    # As in prop's trainer: denormal Adam moments slow CPU steps ~10x; flushing them costs nothing.
    flush = torch.set_flush_denormal(True)
    try:
        _loop(
            model,
            opt,
            sched,
            rng,
            sampler,
            ux,
            uy,
            ucodes,
            px,
            pool_targets,
            task,
            cfg,
            steps,
            per_user,
            encoding,
        )
    finally:
        if flush:
            torch.set_flush_denormal(False)
    return model.eval()


def _loop(
    model, opt, sched, rng, sampler, ux, uy, ucodes, px, pool_targets, task, cfg, steps, per_user, encoding
):
    for _ in range(steps):
        xs, ys, cs = [], [], []
        for i in range(len(ux)):
            idx = torch.from_numpy(rng.integers(0, len(ux[i]), per_user))
            xs.append(ux[i][idx])
            ys.append(uy[i][idx])
            cs.append(ucodes[i].expand(per_user, -1))
        m = cfg.mode
        sampled = np.concatenate([sampler.neighbours(m.neighbour_keys), sampler.random(m.random_keys)])
        s = cfg.mode.samples_per_key
        fb = torch.from_numpy(rng.integers(0, len(px), len(sampled) * s))
        null = torch.from_numpy(rng.integers(0, len(px), cfg.mode.null_rows))
        sampled_codes = key_codes(sampled, encoding).repeat_interleave(s, 0)
        x = torch.cat([*xs, px[fb], px[null]])
        codes = torch.cat([*cs, sampled_codes, torch.zeros(cfg.mode.null_rows, ucodes.shape[1])])
        out, kl = model(x, codes)
        nu, nk = sum(len(v) for v in xs), len(fb)
        personal = row_loss(out[:nu], torch.cat(ys), task, distill=False).mean()
        keyed = row_loss(out[nu : nu + nk], pool_targets[fb], task, distill=True).mean()
        nul = row_loss(out[nu + nk :], pool_targets[null], task, distill=True).mean()
        loss = personal + keyed + cfg.mode.null_weight * nul + CVAE_BETA * kl
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()


@torch.no_grad()
def outputs(
    model: nn.Module, x: torch.Tensor, bits: np.ndarray, encoding: str = "raw", chunk_rows: int = 1 << 16
) -> torch.Tensor:
    """Every key (K, n bits) on every sample: (K, B, ...)."""
    codes = key_codes(bits, encoding)
    b = x.shape[0]
    per = max(1, chunk_rows // b)
    outs = []
    for i in range(0, len(codes), per):
        c = codes[i : i + per]
        xx = x.repeat(len(c), *([1] * (x.dim() - 1)))
        o, _ = model(xx, c.repeat_interleave(b, 0))
        outs.append(o.view(len(c), b, *o.shape[1:]))
    return torch.cat(outs)
