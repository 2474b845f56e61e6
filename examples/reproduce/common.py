"""What the supervised experiments (IL, digits, capacity) share: methods, key columns, T2 leakage.

A seed's task (``TaskData``) holds a pretrained base checkpoint, the user data, the fallback inputs and
a held-out test set. PRoP personalizes the base through the library (``api.personalize_checkpoint``:
a real bundle, loaded back with ``load_bundle``); the baselines are trained from scratch on the same
data with the same Eq. 8 key sampling (``baselines.train``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from examples import save_npz
from examples.reproduce import baselines
from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.bundle import Bundle, load_bundle
from prop_cli.config import PersonalizeConfig
from prop_cli.core import metrics
from prop_cli.core.key_sampling import one_bit_neighbours, random_keys
from prop_cli.core.keyed_model import key_codes, outputs_for_codes
from prop_cli.datasources import Dataset

KEY_BITS = 128
# PRoP as in the paper (raw key bits into the encoder) and with prop's default hashed encoding.
PROP = "PRoP"
PROP_HASHED = "PRoP-hashed"
ALL_METHODS = (PROP, PROP_HASHED, "MLP", "MLP-hashed", "CVAE")


@dataclass
class TaskData:
    task: str  # "regression" | "classification"
    base: torch.nn.Module  # the pretrained original (eval mode)
    base_path: Path  # its safetensors checkpoint
    user_x: np.ndarray
    user_y: np.ndarray  # the personalized targets
    general_x: np.ndarray  # fallback inputs (no targets needed: the base labels them)
    test_x: np.ndarray
    test_y: np.ndarray  # general objective targets
    test_y_personal: np.ndarray


@dataclass
class Budget:
    """Training and evaluation sizes of one run (the --quick versions shrink these)."""

    prop_steps: int = 2000
    baseline_steps: int = 4000
    random_keys: int = 64  # random keys evaluated per seed
    hamming_keys: int = 128  # one-bit neighbours evaluated (all 128 at full size)
    t2_restarts: int = 8
    t2_steps: int = 200
    t2_samples: int = 256
    extra: dict = field(default_factory=dict)


def user_key(seed: int, salt: int = 0) -> np.ndarray:
    """A seeded 128-bit key (stands in for `prop keygen`, so reruns match)."""
    return np.random.default_rng(50_000 + 97 * seed + salt).integers(0, 2, KEY_BITS, dtype=np.uint8)


def t2_leakage(
    bundle: Bundle, x: np.ndarray, y: np.ndarray, key: np.ndarray, base_path: Path, budget: Budget
) -> dict:
    """The audit's T2 (direct delta search) on (x, y), via prop_cli.attack.audit.audit: the attacker's pick,
    with the original checkpoint (``base_path``) as the reference and as the search's control."""
    from prop_cli.attack.audit import audit
    from prop_cli.attack.target import load_original
    from prop_cli.config import AuditSettings

    settings = AuditSettings(
        hamming=[1],
        per_distance=1,
        random=0,
        probes=["latent"],
        restarts=budget.t2_restarts,
        search_steps=budget.t2_steps,
        search_batch=0,  # every sample each step, as the T2 budget was set with
        samples=budget.t2_samples,
        seed=0,
    )
    original = load_original(bundle, str(base_path))  # rebuilt as the bundle's base: the T2 control runs
    report = audit(bundle, Dataset(x=x, y=y, path="<test split>"), [key], settings, original=original)
    latent = next(g for g in report["groups"] if g["name"] == "latent")
    return {"leakage": latent["search"]["best_leakage"], "fidelity": latent["search"]["best_fidelity"]}


def objective(o: torch.Tensor, y: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: mse (regression) or classification rate (classification)."""
    return metrics.target_error(o, y, task)


def columns(outputs, x: torch.Tensor, td: TaskData, key: np.ndarray, budget: Budget, rng) -> dict:
    """{row: {col: value}} for one method and seed; ``outputs(x, bits) -> (K, B, ...)``."""
    y = torch.from_numpy(td.test_y)
    yp = torch.from_numpy(td.test_y_personal)
    if td.task == "regression" and y.dim() == 1:
        y, yp = y[:, None], yp[:, None]
    with torch.no_grad():
        b = td.base(x)
    ham = one_bit_neighbours(key)
    if budget.hamming_keys < len(ham):
        ham = ham[rng.choice(len(ham), budget.hamming_keys, replace=False)]
    keysets = {
        "random": random_keys(budget.random_keys, len(key), rng, exclude=key),
        "hamming1": ham,
        "user": key[None],
    }
    cells: dict = {"general": {}, "personal": {}, "leakage": {}}
    for col, bits in keysets.items():
        o = outputs(x, bits)
        cells["general"][col] = objective(o, y, td.task).mean().item()
        cells["personal"][col] = objective(o, yp, td.task).mean().item()
        cells["leakage"][col] = metrics.leakage(o, yp, b, td.task).mean().item()
    return cells


def write_task_files(td: TaskData, work: Path) -> tuple[Path, Path]:
    mine = save_npz(work / "mine.npz", x=td.user_x, y=td.user_y)
    general = save_npz(work / "general.npz", x=td.general_x)
    return mine, general


def prop_config(seed: int, budget: Budget, encoder_hidden: int, encoding: str) -> PersonalizeConfig:
    return PersonalizeConfig.of(
        steps=budget.prop_steps, encoder_hidden=[encoder_hidden], key_encoding=encoding, seed=seed
    )


def run_prop(
    base_path: Path,
    users: list[tuple[Path, np.ndarray]],
    general: Path,
    out: Path,
    cfg: PersonalizeConfig,
    *,
    kind: str = "file",
    salt: bytes | None = None,
) -> Bundle:
    """One bundle through the library; ``kind``/``salt``: how the keys were made (passphrase + KDF salt)."""
    personalize_checkpoint(
        str(base_path),
        [(p, KeySource(k, kind)) for p, k in users],
        out,
        cfg,
        general=general,
        salt=salt,
        device="cpu",
        force=True,
    )
    return load_bundle(out)


def prop_outputs(bundle: Bundle):
    km = bundle.keyed.eval()

    def run(x: torch.Tensor, bits: np.ndarray) -> torch.Tensor:
        return outputs_for_codes(km, x, key_codes(bits, bundle.key_encoding))

    return run


def prop_params(bundle: Bundle) -> int:
    return baselines.n_params(bundle.keyed.module) + baselines.n_params(bundle.keyed.encoder)


def run_seed(
    td: TaskData,
    seed: int,
    work: Path,
    budget: Budget,
    encoder_hidden: int,
    methods: tuple[str, ...] = ALL_METHODS,
    log=print,
) -> dict:
    """{method: cells} plus {"_params": {method: n}, "_seconds": {method: s}} for one seed."""
    key = user_key(seed)
    work.mkdir(parents=True, exist_ok=True)
    mine, general = write_task_files(td, work)
    x = torch.from_numpy(td.test_x)
    res: dict = {"_params": {}, "_seconds": {}}
    budget_params = None
    for m in methods:
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed + 7)  # same probe keys for every method
        if m in (PROP, PROP_HASHED):
            enc = "raw" if m == PROP else "hashed"
            cfg = prop_config(seed, budget, encoder_hidden, enc)
            bundle = run_prop(td.base_path, [(mine, key)], general, work / f"{m}.prop", cfg)
            cells = columns(prop_outputs(bundle), x, td, key, budget, rng)
            t2 = t2_leakage(bundle, td.test_x, td.test_y_personal, key, td.base_path, budget)
            cells["leakage"]["t2"] = t2["leakage"]
            res["_params"][m] = budget_params = prop_params(bundle)
        else:
            if budget_params is None:  # baselines are sized to PRoP's count
                budget_params = prop_budget(td, encoder_hidden)
            with torch.no_grad():
                pool_targets = td.base(torch.from_numpy(td.general_x))
            out_dim = pool_targets.shape[-1]
            arch, enc = baselines.split_name(m)
            model = baselines.build(arch, td.test_x[0].size, KEY_BITS, out_dim, budget_params, seed)
            cfg = prop_config(seed, budget, encoder_hidden, enc)
            baselines.train(
                model, [(td.user_x, td.user_y, key)], td.general_x, pool_targets, td.task, cfg,
                budget.baseline_steps, encoding=enc,
            )  # fmt: skip
            cells = columns(
                lambda xx, bits, mm=model, e=enc: baselines.outputs(mm, xx, bits, e), x, td, key, budget, rng
            )
            res["_params"][m] = baselines.n_params(model)
        res[m] = cells
        res["_seconds"][m] = time.perf_counter() - t0
        log(f"  seed {seed} {m}: {res['_seconds'][m]:.1f} s")
    return res


def prop_budget(td: TaskData, encoder_hidden: int) -> int:
    """PRoP's total parameter count (base + encoder over all linear layers but the first)."""
    linears = [m for m in td.base.modules() if isinstance(m, torch.nn.Linear)]
    feats = sum(m.in_features for m in linears[1:]) if len(linears) > 1 else linears[0].in_features
    enc = KEY_BITS * encoder_hidden + encoder_hidden + encoder_hidden * feats + feats
    return baselines.n_params(td.base) + enc


def encoder_width(td: TaskData, total: int) -> int:
    """Encoder hidden width that brings base + encoder closest to ``total`` parameters."""
    return min(range(8, 1025), key=lambda e: abs(prop_budget(td, e) - total))


def seed_fields(per_seed: list[dict], params: dict[str, int], methods: tuple[str, ...] | None = None) -> dict:
    """The fields every experiment's result shares: seeds, parameter counts, time and the aggregate."""
    methods = methods or tuple(params)
    return {
        "seeds": len(per_seed),
        "params": params,
        "seconds": {m: float(np.sum([r["_seconds"][m] for r in per_seed])) for m in params},
        "methods": aggregate([{m: r[m] for m in methods} for r in per_seed], methods),
    }


def aggregate(per_seed: list[dict], methods: tuple[str, ...]) -> dict:
    """{method: {row: {col: [per-seed values]}}}."""
    out: dict = {}
    for m in methods:
        rows: dict = {}
        for r in per_seed:
            for row, cols in r[m].items():
                for col, v in cols.items():
                    rows.setdefault(row, {}).setdefault(col, []).append(float(v))
        out[m] = rows
    return out
