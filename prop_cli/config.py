"""Settings of personalize, the audit and the export: dataclasses, validated here and nowhere else.

Their field defaults are the only place a default is written: the CLI reads its option defaults from
them. No torch here, so `prop --help` stays fast.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

from .constants import KEY_ENCODINGS, PASSPHRASE_MIN_YEARS
from .errors import PropError

TASKS = ("classification", "regression")
# What a sealed bundle stores per user: the names of core.payload.KINDS (one class each, which checks these).
PAYLOAD_KINDS = ("lora", "delta", "full", "peft-lora")
ENCODER_INITS = ("seed", "os")
PRECISIONS = ("fp32", "bf16")  # --precision: bf16 = autocast mixed precision (prop_cli.train.loop)
# `--harden` (docs/hardening.md): the settings it implies, unless given explicitly.
HARDEN_PRESET = {"encoder_init": "os", "code_negatives": 64, "antipode_codes": 16}
PLAIN_PRESET = {"encoder_init": "seed", "code_negatives": 0, "antipode_codes": 0}


def _need(ok: bool, flag: str, value: Any, rule: str) -> None:
    if not ok:
        raise PropError(f"{flag} {value!r} is invalid", f"{flag} must be {rule}")


def _require(ok: bool, what: str, fix: str) -> None:
    if not ok:
        raise PropError(what, fix)


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


class _Settings:
    """What the settings dataclasses share: checkers naming the CLI flag, and dict round trips."""

    def need(self, ok: bool, name: str, rule: str, flag: str | None = None) -> None:
        _need(ok, flag or _flag(name), getattr(self, name), rule)

    def at_least(self, **lows: int) -> None:
        """Each named field is a number >= its low (0: ">= 0", else "at least N")."""
        for name, low in lows.items():
            self.need(getattr(self, name) >= low, name, f"at least {low}" if low else ">= 0")

    def positive(self, *names: str) -> None:
        for name in names:
            self.need(getattr(self, name) > 0, name, "positive")

    def to_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls, d: dict):
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        return cls(**{k: v for k, v in d.items() if k in known})


@dataclass
class PersonalizeConfig(_Settings):
    """Training settings; recorded in the bundle's manifest so a run can be repeated."""

    steps: int = 2000
    lr: float = 1e-3  # Adam, the encoder's; cosine-decays to lr * lr_floor
    lr_floor: float = 0.05
    # The base weights learn at lr * base_lr_scale: the encoder carries the personalization, and a base
    # that moves less keeps the no-key model closer to the original (docs/design.md, "No-key drift").
    base_lr_scale: float = 1.0
    # Rows of one step: each row is one (sample, key) pair.
    user_rows: int = 64  # per step, shared among users: the user's key on the user's data
    # Distinct fallback samples per step, each also run with the null key. 128 rather than 32 (and 2
    # samples per sampled key rather than 4, so a step stays ~the same size): docs/design.md, "No-key drift".
    null_rows: int = 128
    random_keys: int = 8  # K2: uniform random keys per step
    neighbour_keys: int = 32  # K1: Hamming neighbours of the user keys per step
    samples_per_key: int = 2  # fallback samples each sampled key is run on
    hamming_radius: int = 8  # epsilon of Eq. 8: neighbours at distance 1..radius
    null_weight: float = 10.0  # the no-key behaviour is what everyone else gets: weigh it up
    # Weight of the sampled keys' fallback term (K1, K2; the mean over their rows). Eq. 8 sums over the
    # keys; 1 weighs all of them together as much as the user's term (bundles before issue 32).
    key_weight: float = 1.0
    # Weight of the sampled keys' delta pulled towards 1, the null key's (objective.delta_pull): a wrong
    # key's model is then nearly the no-key model, not only close to the original on the training
    # inputs; the no-key model is what holds in closed loop (docs/privacy.md, "Wrong keys in closed
    # loop": SAC Pendulum, keys below 0.9x the original's return 6.3% -> 0). 0: bundles before issue 32.
    delta_pull: float = 10.0
    # ±1 codes 40-56 bits (of 128) from the user's code per step, a fallback term of their own, not pulled
    # (train.hardening.far_codes, objective.delta_pull): the nearest codes real keys reach. 0: none.
    far_codes: int = 16
    # Hard-negative random keys (core.key_sampling.KeySampler; docs/privacy.md, "Wrong keys in closed
    # loop"): every hard_every steps hard_pool fresh random keys and the kept ones are scored by their
    # fallback divergence, the hard_negatives worst kept, and half of each step's random keys drawn from
    # them. Off by default: on SB3 SAC Pendulum it did not lower the closed-loop failures (0, uniform K2).
    hard_negatives: int = 0
    hard_pool: int = 256
    hard_every: int = 200
    # Fallback inputs beyond the given ones (users' data and --general-data): this share of each step's
    # fallback samples is a given input plus Gaussian noise of `fallback_sigma` per-feature standard
    # deviations, labelled by the original on the fly. Keeps the no-key model the original around and
    # between the data points too, not only on them (docs/design.md, "No-key drift"). All of them (1.0,
    # not 0.5): the reach3 no-key mse 1.4e-4 -> 0.8e-4, digits-perm groups >= 0.991 on 5/5 seeds.
    fallback_noise: float = 1.0
    fallback_sigma: float = 0.5
    encoder_hidden: list[int] = field(default_factory=lambda: [256])
    delta_scale: float = 2.0  # delta in (1 - scale, 1 + scale)
    key_encoding: str = KEY_ENCODINGS[0]
    freeze_base: bool = False
    val_fraction: float = 0.2
    seed: int = 0
    layers: list[str] | None = None  # None = default choice (see layers.default_layers)
    exclude: list[str] | None = None
    eval_random_keys: int = 64
    # The report's budget, in (key condition x held-out frame) runs of a policy's sampler (None: by the
    # policy's size, prop_cli.train.policy.report_budget; 0: every key on every held-out frame).
    report_budget: int | None = None
    task: str | None = None  # None: decided against the model (prop_cli.fit.resolve_task)
    # Sealed bundles (docs/sealed.md): the base stays the original, and each user's payload for the keyed
    # layers is encrypted under their key. The encoder and fallback settings above do not apply there.
    seal: bool = False
    # lora at rank 4 matched unsealed PRoP's personalization on IL and digits at ~2% of its bytes
    # (docs/sealed.md, "Choosing the payload"); full is the strongest, delta the smallest.
    payload: str = "lora"
    payload_rank: int = 4
    payload_lr: float = 0.01  # Adam on the payload; cosine-decays like lr
    # Hardened unsealed mode (prop_cli.train.hardening, docs/hardening.md): a preset of the fields below.
    # Those left None take HARDEN_PRESET's value with harden, PLAIN_PRESET's without (validate fills them).
    harden: bool = False
    # "seed": the encoder's initialisation follows `seed` (byte-identical reruns, but the manifest's
    # seed recreates it); "os": fresh OS randomness that nothing in the bundle records.
    encoder_init: str | None = None
    # Code-space fallback rows per step (each on samples_per_key samples), near the users' codes:
    # up to code_flip_max bits flipped, or relaxed/noised towards the rest of the cube by >= code_relax_min.
    code_negatives: int | None = None
    code_flip_max: int = 48
    code_relax_min: float = 0.1
    # ±1 codes 40-56 bits (of 128) from the antipode of the users' codes per step (72-88 from them), with
    # the far codes: a fallback term, and unlike them pulled (train.hardening.antipode_codes). The
    # encoder is nearly odd in the code, so codes past 64 bits get a share of minus the user's delta;
    # --harden's larger user delta made that a wrong key's failure (docs/privacy.md, "Wrong keys in
    # closed loop").
    antipode_codes: int | None = None
    # The step's forward and loss: fp32, or bf16 autocast with fp32 parameters and optimiser state
    # (prop_cli.train.loop.mixed_precision). Recorded so a run can be repeated as it was trained.
    precision: str = PRECISIONS[0]

    def without_hardening(self) -> PersonalizeConfig:
        """These settings with --harden's preset cleared (filled with the plain defaults by ``validate``)."""
        self.harden = False
        for name in HARDEN_PRESET:
            setattr(self, name, None)
        return self

    def hardening(self) -> list[str]:
        """--harden, or each of its preset's settings given away from the plain default (after
        ``validate`` filled them), as flags: what only the array trainer's unsealed mode trains."""
        if self.harden:
            return ["--harden"]
        return [f"{_flag(k)} {getattr(self, k)}" for k, v in PLAIN_PRESET.items() if getattr(self, k) != v]

    @property
    def batch_rows(self) -> int:
        sampled = self.random_keys + self.neighbour_keys + self.far_codes
        sampled += (self.code_negatives or 0) + (self.antipode_codes or 0)
        return self.user_rows + self.null_rows + sampled * self.samples_per_key

    def validate(self, key_bits: int | None = None) -> PersonalizeConfig:
        """Check every field; with ``key_bits``, also what depends on the key size."""
        self.at_least(steps=1, user_rows=1, null_rows=1, random_keys=0, neighbour_keys=0, samples_per_key=1,
                      hamming_radius=1, null_weight=0, key_weight=0, delta_pull=0, eval_random_keys=1,
                      payload_rank=1)  # fmt: skip
        self.positive("lr", "base_lr_scale", "fallback_sigma", "delta_scale", "payload_lr")
        self.need(0 < self.lr_floor <= 1, "lr_floor", "in (0, 1]")
        if key_bits is not None:
            self.need(
                self.hamming_radius <= key_bits, "hamming_radius", f"at most the key size ({key_bits} bits)"
            )
        self.need(0 <= self.fallback_noise <= 1, "fallback_noise", "in [0, 1]")
        self.need(self.key_encoding in KEY_ENCODINGS, "key_encoding", " or ".join(KEY_ENCODINGS))
        self.need(0 < self.val_fraction < 1, "val_fraction", "in (0, 1)")
        self.need(all(h >= 1 for h in self.encoder_hidden), "encoder_hidden", "positive sizes")
        self.need(self.task is None or self.task in TASKS, "task", "classification, regression or auto")
        self.need(self.payload in PAYLOAD_KINDS, "payload", " or ".join(PAYLOAD_KINDS))
        for name in ("payload", "payload_rank", "payload_lr"):  # an unsealed bundle has no payload:
            value = getattr(self, name)  # a payload setting without --seal would be silently ignored
            _require(
                self.seal or value == getattr(PersonalizeConfig, name),
                f"{_flag(name)} {value} applies to sealed bundles only", f"add --seal, or drop {_flag(name)}",
            )  # fmt: skip
        for name, value in (HARDEN_PRESET if self.harden else PLAIN_PRESET).items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        hardening = self.hardening()
        _require(  # a sealed recipe trains none of --harden's measures; the manifest recorded them anyway
            not (self.seal and hardening),
            f"{', '.join(hardening)}: --harden's measures harden an unsealed bundle's encoder; a sealed "
            "bundle trains none of them",
            "drop them (a sealed bundle keeps each user's payload encrypted), or drop --seal",
        )
        self.need(self.encoder_init in ENCODER_INITS, "encoder_init", " or ".join(ENCODER_INITS))
        self.at_least(code_negatives=0, code_flip_max=1, hard_negatives=0, far_codes=0, antipode_codes=0)
        if self.hard_negatives:
            self.at_least(hard_pool=1, hard_every=1)
        if self.report_budget is not None:
            self.at_least(report_budget=0)
        self.need(0 < self.code_relax_min <= 1, "code_relax_min", "in (0, 1]")
        self.need(self.precision in PRECISIONS, "precision", " or ".join(PRECISIONS))
        return self


BLACKBOX_KEYS = 1_000_000
BLACKBOX_KEYS_POLICY = 65_536
FEWSHOT_RESTARTS = 128
FEWSHOT_RESTARTS_POLICY = 16  # not calibrated on policies: 8x the old budget at a tractable cost
# A policy's audit stops its probes after this many seconds unless --budget says otherwise: a real-size
# VLA's key is a sampler run per sample (seconds each on a CPU); the examples' small policies finish first.
AUDIT_BUDGET_POLICY = 600.0


@dataclass
class AuditSettings(_Settings):
    """What `prop attack` probes and how hard (docs/threat-model.md)."""

    probes: list[str] | None = None  # None: every probe in the registry that is on by default
    hamming: list[int] | None = None  # None: 1..8 with a key, none without
    per_distance: int = 256  # keys per distance; every key when the neighbourhood is smaller
    random: int = 4096
    restarts: int = 128  # T1 finds the code in a small share of restarts: docs/metrics.md, hit rate
    search_steps: int = 100
    search_lr: float = 0.1
    search_batch: int = 32  # samples per search step (0: all); each step draws its own
    # T3's code fit: the attacker's pick (lowest fit loss) finds a hardened digits code in 0.97-1.00 of
    # draws at 128 x 200 (docs/audit.md, "Few-shot budget"); 400 steps find no more than 200. None:
    # FEWSHOT_RESTARTS, or FEWSHOT_RESTARTS_POLICY for policies (an ACT forward per restart and shot).
    fewshot_restarts: int | None = None
    fewshot_steps: int = 200
    samples: int = 256  # samples of --data the audit runs on
    seed: int = 0
    # Random keys of the streamed black-box scan; None: BLACKBOX_KEYS, or BLACKBOX_KEYS_POLICY for
    # policies (an ACT key is a transformer forward: 65,536 keys took 20 s on one core, 1M over 5 minutes).
    blackbox: int | None = None
    blackbox_screen: int = 8  # samples each scanned key is screened on
    blackbox_keep: int = 256  # keys kept per criterion and re-scored on every sample
    # The passphrase row (--passphrase): fails when guessing it would take fewer core-years than this.
    min_passphrase_years: float = PASSPHRASE_MIN_YEARS
    # Wall seconds the probes may take (None: no limit; for LeRobot policies AUDIT_BUDGET_POLICY): past
    # it the running probe stops with what it has, and the rest are not tried; the report says which.
    budget: float | None = None
    # A sampling policy's chunks (LeRobot Diffusion) start from this seed's noise, for every key and
    # the original alike: outputs compare as functions of the key alone.
    noise_seed: int = 0

    def validate(self, key_bits: int, has_key: bool, known_probes: list[str]) -> AuditSettings:
        if self.fewshot_restarts is None:
            self.fewshot_restarts = FEWSHOT_RESTARTS
        self.at_least(per_distance=1, random=0, restarts=1, search_steps=1, samples=2, fewshot_restarts=1,
                      fewshot_steps=1, noise_seed=0)  # fmt: skip
        self.need(self.min_passphrase_years >= 0, "min_passphrase_years", ">= 0")
        self.positive("search_lr")
        self.need(self.search_batch >= 0, "search_batch", ">= 0 (0: every sample)")
        if self.budget is not None:
            self.positive("budget")
        if self.blackbox is None:
            self.blackbox = BLACKBOX_KEYS
        self.at_least(blackbox=0, blackbox_screen=1, blackbox_keep=1)
        if self.probes is not None:
            unknown = [p for p in self.probes if p not in known_probes]
            _need(not unknown, "--probes", ",".join(self.probes), "a list of: " + ", ".join(known_probes))
        if self.hamming:
            if not has_key:
                raise PropError(
                    "--hamming needs the user's key (neighbours are keys a few bits from it)",
                    "pass --key-file, or drop --hamming for a no-key audit",
                )
            _need(
                max(self.hamming) <= key_bits,
                "--hamming",
                max(self.hamming),
                f"at most the key size ({key_bits} bits)",
            )
        return self


def parse_hamming(spec: str) -> list[int]:
    """``1..8`` (a range), ``1,2,4`` (a list) or ``3`` -> sorted distinct distances >= 1."""
    bad = PropError(
        f"--hamming {spec!r} is not a distance list",
        "use a range like 1..8, a list like 1,2,4, or one distance like 3 (all >= 1)",
    )
    out: set[int] = set()
    try:
        for part in spec.replace(" ", "").split(","):
            if ".." in part:
                lo, hi = (int(v) for v in part.split(".."))
                if lo > hi:
                    raise bad
                out.update(range(lo, hi + 1))
            else:
                out.add(int(part))
    except ValueError:
        raise bad from None
    if not out or min(out) < 1:
        raise bad
    return sorted(out)


def parse_list(spec: str, flag: str) -> list[str]:
    """``a,b,c`` -> ["a", "b", "c"] (``none`` -> []); names are checked where they are known."""
    parts = [p for p in spec.replace(" ", "").lower().split(",") if p]
    if not parts:
        raise PropError(f"{flag} {spec!r} is empty", f"give a comma-separated list, or {flag} none")
    return [] if parts == ["none"] else parts


@dataclass
class ExportSettings(_Settings):
    """`prop export --onnx`: which opset, and how close onnxruntime must be to torch."""

    opset: int = 18  # runs on every onnxruntime since 1.14; the TorchScript exporter goes up to 20
    atol: float = 1e-5
    seed: int = 0  # random verification inputs and the random verification key

    MIN_OPSET = 13
    MAX_OPSET = 20

    def validate(self) -> ExportSettings:
        self.need(
            self.MIN_OPSET <= self.opset <= self.MAX_OPSET, "opset", f"in {self.MIN_OPSET}..{self.MAX_OPSET}"
        )
        self.positive("atol")
        return self


@dataclass
class EvalSettings(_Settings):
    """`prop eval`: closed-loop rollouts per key condition (user key, no key, random keys, neighbours)."""

    episodes: int = 30  # per condition with one key (user key, no key, the original)
    random_keys: int = 6  # R random keys ...
    neighbours: int = 6  # ... and H one-bit neighbours of the user's key (needs the key)
    episodes_per_key: int = 5  # episodes each random key and each neighbour runs
    max_steps: int = 0  # 0: the environment's own time limit
    # Keep acting after the environment reports `terminated` (e.g. panda-gym ends an episode on reaching
    # the goal): a preference judged at the episode's end needs the whole episode under every key.
    ignore_terminated: bool = False
    seed: int = 1_000_000  # first evaluation seed; keep it away from the seeds the data was recorded with
    # A sampling policy's noise (LeRobot Diffusion): each query of an episode is seeded from (noise_seed,
    # the episode's seed, the query's number), the same under every key (prop_adapters.lerobot).
    noise_seed: int = 0
    # A language-conditioned policy's instruction in closed loop (LeRobot SmolVLA): the task text its data
    # was recorded with. Data rows carry their own; an environment gives none.
    instruction: str = ""

    def validate(self, has_key: bool) -> EvalSettings:
        self.at_least(episodes=1, random_keys=0, neighbours=0, episodes_per_key=1, seed=0, noise_seed=0)
        self.need(self.max_steps >= 0, "max_steps", ">= 0 (0: the environment's limit)")
        if self.neighbours and not has_key:
            self.neighbours = 0  # neighbours are keys a few bits from the user's: none without it
        return self
