"""Settings of personalize, the audit and the export: dataclasses, validated here and nowhere else.

Their field defaults are the only place a default is written, and each CLI setting's help text is
stored in its field (``metadata["help"]``): the CLI builds its options from them and docs/cli.md's
settings table is checked against them (tests/test_docs.py). No torch here, so `prop --help` stays fast.

personalize's settings are one value per mode (docs/design.md, "Settings"): a ``TrainConfig`` every
recipe reads, and either an ``UnsealedConfig`` (the key encoder, its fallback terms and its
``Hardening``, a preset value) or a ``SealedConfig`` (the payload). A recipe receives only its own mode's
part, so a setting of the other mode cannot leak into it; ``PersonalizeConfig.of`` turns the CLI's flat
flags into them and is the one place that refuses a flag of the other mode.
"""

from __future__ import annotations

from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from typing import Any, ClassVar

from .constants import FALLBACK_TIMES, KEY_ENCODINGS, PASSPHRASE_MIN_YEARS
from .errors import PropError

TASKS = ("classification", "regression")
# What a sealed bundle stores per user: the names of core.payload.KINDS (one class each, which checks these).
PAYLOAD_KINDS = ("lora", "delta", "full", "peft-lora")
ENCODER_INITS = ("seed", "os")
PRECISIONS = ("fp32", "bf16")  # --precision: bf16 = autocast mixed precision (prop_cli.train.loop)


def _need(ok: bool, flag: str, value: Any, rule: str) -> None:
    if not ok:
        raise PropError(f"{flag} {value!r} is invalid", f"{flag} must be {rule}")


def _require(ok: bool, what: str, fix: str) -> None:
    if not ok:
        raise PropError(what, fix)


def flag(name: str) -> str:
    """A setting's CLI flag: its field name with dashes."""
    return "--" + name.replace("_", "-")


def setting(default: Any, help: str, *, cli: bool = True) -> Any:
    """A settings field whose help text lives with it (``cli``: the CLI has a flag for it)."""
    meta = {"help": help, "cli": cli}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


def default_of(f) -> Any:
    """A dataclass field's default (its factory's value for a list)."""
    return f.default_factory() if f.default is MISSING else f.default


class _Settings:
    """What the settings dataclasses share: checkers naming the CLI flag, and dict round trips."""

    def need(self, ok: bool, name: str, rule: str, flag_: str | None = None) -> None:
        _need(ok, flag_ or flag(name), getattr(self, name), rule)

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


# ---- personalize: what every mode trains with, then each mode's own part ---------------------------


@dataclass(frozen=True)
class TrainConfig(_Settings):
    """What every recipe reads, unsealed or sealed, array model or policy."""

    steps: int = setting(2000, "Training steps.")
    # The cosine decay of every learning rate (the encoder's, the base's, a sealed payload's).
    lr_floor: float = setting(0.05, "The cosine decay ends at lr times this (1: a constant learning rate).")
    # Rows of one step: each row is one (sample, key) pair; these are the user's key on the user's data.
    user_rows: int = setting(64, "Rows of the users' data per step.")
    val_fraction: float = setting(0.2, "Share of each user's data held out for the final report.")
    seed: int = setting(0, "Seed: the same seed and inputs give byte-identical weights (not with --harden).")
    layers: list[str] | None = setting(
        None, "Layers to key: exact name, dotted suffix, regex or all-linear; repeat."
    )  # None = default choice (see layers.default_layers)
    exclude: list[str] | None = setting(None, "Layers not to key (same forms); repeat.")
    eval_random_keys: int = setting(64, "Random keys of the final report.", cli=False)
    # The report's budget, in (key condition x held-out frame) runs of a policy's sampler (None: by the
    # policy's size, prop_cli.train.policy.report_budget; 0: every key on every held-out frame).
    report_budget: int | None = setting(
        None,
        "Policies: the final report's (key, held-out frame) sampler runs (default: by the policy's size; "
        "0 = every key on every frame).",
    )
    task: str | None = setting(
        None, " or ".join(TASKS) + " (default: decided against the model)."
    )  # None: decided against the model (prop_cli.fit.resolve_task)
    # The step's forward and loss: fp32, or bf16 autocast with fp32 parameters and optimiser state
    # (prop_cli.train.loop.mixed_precision). Recorded so a run can be repeated as it was trained.
    precision: str = setting(
        PRECISIONS[0], "fp32, or bf16: mixed precision (bf16 autocast; weights and Adam stay fp32)."
    )

    def __post_init__(self) -> None:
        # The CLI gives an empty list for a list flag not given: the same as None (the default choice).
        object.__setattr__(self, "layers", self.layers or None)
        object.__setattr__(self, "exclude", self.exclude or None)
        self.at_least(steps=1, user_rows=1, eval_random_keys=1)
        self.need(0 < self.lr_floor <= 1, "lr_floor", "in (0, 1]")
        self.need(0 < self.val_fraction < 1, "val_fraction", "in (0, 1)")
        self.need(self.task is None or self.task in TASKS, "task", "classification, regression or auto")
        if self.report_budget is not None:
            self.at_least(report_budget=0)
        self.need(self.precision in PRECISIONS, "precision", " or ".join(PRECISIONS))


@dataclass(frozen=True)
class Hardening(_Settings):
    """Hardened unsealed mode's measures (prop_cli.train.hardening, docs/hardening.md). ``Hardening()`` is
    the plain mode (none of them), ``HARDENED`` the preset `--harden` names; a flag of its own replaces one
    value of the preset."""

    # "seed": the encoder's initialisation follows `seed` (byte-identical reruns, but the manifest's
    # seed recreates it); "os": fresh OS randomness that nothing in the bundle records.
    encoder_init: str = setting(
        "seed", "seed (follows --seed) or os (fresh randomness; default with --harden)."
    )
    # Code-space fallback rows per step (each on samples_per_key samples), near the users' codes:
    # up to code_flip_max bits flipped, or relaxed/noised towards the rest of the cube by >= code_relax_min.
    code_negatives: int = setting(
        0, "Code-space fallback codes per step near your code (64 with --harden, else 0)."
    )
    code_flip_max: int = setting(48, "Code-space negatives: at most this many bits flipped.")
    code_relax_min: float = setting(
        0.1, "Code-space negatives: relaxed at least this far from your code, in (0, 1]."
    )
    # ±1 codes 40-56 bits (of 128) from the antipode of the users' codes per step (72-88 from them), with
    # the far codes: a fallback term, and unlike them pulled (train.hardening.antipode_codes). The
    # encoder is nearly odd in the code, so codes past 64 bits get a share of minus the user's delta;
    # --harden's larger user delta made that a wrong key's failure (docs/privacy.md, "Wrong keys in
    # closed loop").
    antipode_codes: int = setting(
        0, "Codes 72-88 of 128 bits from yours per step, trained to fall back (16 with --harden, else 0)."
    )

    PRESET: ClassVar[tuple[str, ...]] = ("encoder_init", "code_negatives", "antipode_codes")

    def __post_init__(self) -> None:
        self.need(self.encoder_init in ENCODER_INITS, "encoder_init", " or ".join(ENCODER_INITS))
        self.at_least(code_negatives=0, code_flip_max=1, antipode_codes=0)
        self.need(0 < self.code_relax_min <= 1, "code_relax_min", "in (0, 1]")

    @classmethod
    def preset(cls, harden: bool, **given: Any) -> Hardening:
        """`--harden`'s preset (or the plain one), with the values ``given`` (None: the preset's)."""
        return replace(HARDENED if harden else PLAIN, **{k: v for k, v in given.items() if v is not None})

    @property
    def is_hardened(self) -> bool:
        """Every measure of the --harden preset, as it sets them (what the manifest records as ``harden``)."""
        return all(getattr(self, k) == getattr(HARDENED, k) for k in self.PRESET)

    def flags(self) -> list[str]:
        """--harden, or each of its measures set away from the plain mode, as flags ([]: plain)."""
        if self.is_hardened:
            return ["--harden"]
        return [f"{flag(k)} {getattr(self, k)}" for k in self.PRESET if getattr(self, k) != getattr(PLAIN, k)]


PLAIN = Hardening()
HARDENED = Hardening(encoder_init="os", code_negatives=64, antipode_codes=16)


# --delta-pull's default by the model's kind (train.choose.settled applies it). Array models: 10 (SB3 SAC
# Pendulum, issue 32: keys below 0.9x the original's return 6.3% -> 0). LeRobot policies: 100 (issue 43:
# a denoising policy's wrong keys drifted systematically away from the goal at 10, in closed loop through
# the encoder on two tasks of three; examples/RESULTS.md, "Point mass", round 3). Per kind, not one value:
# the array tables (the paper's, SB3) were measured at 10 and are kept.
DELTA_PULL = {"array": 10.0, "policy": 100.0}


@dataclass(frozen=True)
class UnsealedConfig(_Settings):
    """The paper's PRoP (and --harden): base weights and a key encoder in the clear, trained with the
    fallback terms of Eq. 8 and their additions."""

    lr: float = setting(1e-3, "Adam learning rate of the key encoder (cosine decay).")
    # The base weights learn at lr * base_lr_scale: the encoder carries the personalization, and a base
    # that moves less keeps the no-key model closer to the original (docs/design.md, "No-key drift").
    base_lr_scale: float = setting(1.0, "The base weights learn at lr times this.")
    # Distinct fallback samples per step, each also run with the null key. 128 rather than 32 (and 2
    # samples per sampled key rather than 4, so a step stays ~the same size): docs/design.md, "No-key drift".
    null_rows: int = setting(128, "Fallback samples per step, each run with no key.")
    random_keys: int = setting(8, "K2: random keys per step.")
    neighbour_keys: int = setting(32, "K1: Hamming neighbours per step (0 = none: leaky, for audits).")
    samples_per_key: int = setting(2, "Fallback samples each sampled key runs on.")
    hamming_radius: int = setting(
        8, "Keys up to this many bits off fall back (at most the key size)."
    )  # epsilon of Eq. 8: neighbours at distance 1..radius
    null_weight: float = setting(
        10.0, "Weight of the no-key fallback loss."
    )  # the no-key behaviour is what everyone else gets: weigh it up
    # Weight of the sampled keys' fallback term (K1, K2; the mean over their rows). Eq. 8 sums over the
    # keys; 1 weighs all of them together as much as the user's term (bundles before issue 32).
    key_weight: float = setting(1.0, "Weight of the random and neighbour keys' fallback loss.")
    # Weight of the sampled keys' delta pulled towards 1, the null key's (objective.delta_pull): a wrong
    # key's model is then nearly the no-key model, not only close to the original on the training
    # inputs; the no-key model is what holds in closed loop (docs/privacy.md, "Wrong keys in closed
    # loop"). 0: bundles before issue 32. None: by the model's kind (DELTA_PULL, train.choose.settled),
    # and the manifest records the value used.
    delta_pull: float | None = setting(
        None,
        "Weight pulling wrong keys' layer scales to the no-key model's (default: 10 for array models, "
        "100 for LeRobot policies; 0 = off).",
    )
    # ±1 codes 40-56 bits (of 128) from the user's code per step, a fallback term of their own, not pulled
    # (train.hardening.far_codes, objective.delta_pull): the nearest codes real keys reach. 0: none.
    far_codes: int = setting(
        16, "Codes 40-56 of 128 bits from yours per step, trained to fall back (0 = none)."
    )
    # Hard-negative random keys (core.key_sampling.KeySampler; docs/privacy.md, "Wrong keys in closed
    # loop"): every hard_every steps hard_pool fresh random keys and the kept ones are scored by their
    # fallback divergence, the hard_negatives worst kept, and half of each step's random keys drawn from
    # them. Off by default: on SB3 SAC Pendulum it did not lower the closed-loop failures (0, uniform K2).
    hard_negatives: int = setting(
        0, "Worst-scoring random keys kept to train on (half of K2 each step; 0 = off)."
    )
    hard_pool: int = setting(256, "Fresh random keys scored for --hard-negatives at each rescoring.")
    hard_every: int = setting(200, "Steps between the rescorings of --hard-negatives.")
    # Fallback inputs beyond the given ones (users' data and --general-data): this share of each step's
    # fallback samples is a given input plus Gaussian noise of `fallback_sigma` per-feature standard
    # deviations, labelled by the original on the fly. Keeps the no-key model the original around and
    # between the data points too, not only on them (docs/design.md, "No-key drift"). All of them (1.0,
    # not 0.5): the reach3 no-key mse 1.4e-4 -> 0.8e-4, digits-perm groups >= 0.991 on 5/5 seeds.
    fallback_noise: float = setting(1.0, "Share of fallback inputs perturbed with noise (0 = the data only).")
    # A denoising policy's (LeRobot Diffusion, SmolVLA, pi0) fallback rows at the timesteps its deployed
    # sampler visits (its num_inference_steps of them) instead of uniform over its training range: the
    # closed loop only ever runs the denoiser there (examples/RESULTS.md, "Point mass, Diffusion").
    # "trajectory": at those timesteps, on the original's own sampler state there (its sampler run on
    # the fallback frame from the row's noise), where the closed loop runs the wrong keys (LeRobot
    # Diffusion; other policies refuse it).
    fallback_times: str = setting(
        FALLBACK_TIMES[0],
        "Denoising policies' fallback timesteps: uniform, sampler (the sampler's timesteps) or trajectory "
        "(those, on the original's own sampler states; LeRobot Diffusion).",
    )
    # Issue 40: a policy's step runs the keyed model forward and backward on every fallback row (a real-size
    # SmolVLA step with 2 user rows: 2.10x LeRobot's). Every k-th step runs them, weighted k so the
    # objective's expectation stays Eq. 8's; the other steps run the user's rows and the delta pull
    # (the encoder alone). 1: every step (bundles before it).
    fallback_every: int = setting(
        1, "LeRobot policies: the fallback rows run every this many steps, weighted by it (1 = every step)."
    )
    fallback_sigma: float = setting(
        0.5, "Noise of the perturbed fallback inputs, in per-feature standard deviations.", cli=False
    )
    encoder_hidden: list[int] = setting([256], "Hidden sizes of the key encoder.", cli=False)
    delta_scale: float = setting(
        2.0, "The encoder's layer scales lie in (1 - this, 1 + this).", cli=False
    )  # delta in (1 - scale, 1 + scale)
    key_encoding: str = setting(KEY_ENCODINGS[0], f"{KEY_ENCODINGS[0]} or {KEY_ENCODINGS[1]} (the paper's).")
    freeze_base: bool = setting(False, "Train the encoder only: the base weights stay the original's.")
    hardening: Hardening = field(default_factory=Hardening)  # Hardening(): none; HARDENED: --harden's

    def __post_init__(self) -> None:
        self.at_least(null_rows=1, random_keys=0, neighbour_keys=0, samples_per_key=1, hamming_radius=1,
                      null_weight=0, key_weight=0, far_codes=0, hard_negatives=0,
                      fallback_every=1)  # fmt: skip
        if self.delta_pull is not None:
            self.at_least(delta_pull=0)
        self.positive("lr", "base_lr_scale", "fallback_sigma", "delta_scale")
        self.need(0 <= self.fallback_noise <= 1, "fallback_noise", "in [0, 1]")
        self.need(self.key_encoding in KEY_ENCODINGS, "key_encoding", " or ".join(KEY_ENCODINGS))
        self.need(self.fallback_times in FALLBACK_TIMES, "fallback_times", " or ".join(FALLBACK_TIMES))
        self.need(all(h >= 1 for h in self.encoder_hidden), "encoder_hidden", "positive sizes")
        if self.hard_negatives:
            self.at_least(hard_pool=1, hard_every=1)

    def for_kind(self, kind: str) -> UnsealedConfig:
        """These settings with the defaults that depend on the model's kind ("array" or "policy") filled
        in (--delta-pull: DELTA_PULL); what is set stays. Each trainer settles its own."""
        return self if self.delta_pull is not None else replace(self, delta_pull=DELTA_PULL[kind])

    def check_key_bits(self, key_bits: int) -> None:
        """What depends on the key size (known once the keys are)."""
        self.need(
            self.hamming_radius <= key_bits, "hamming_radius", f"at most the key size ({key_bits} bits)"
        )

    def batch_rows(self, user_rows: int) -> int:
        """Rows of one step: the users', the no-key ones, and each sampled or placed code's samples."""
        h = self.hardening
        sampled = (
            self.random_keys + self.neighbour_keys + self.far_codes + h.code_negatives + h.antipode_codes
        )
        return user_rows + self.null_rows + sampled * self.samples_per_key


@dataclass(frozen=True)
class SealedConfig(_Settings):
    """Sealed bundles (docs/sealed.md): the base stays the original, and each user's payload for the keyed
    layers is encrypted under their key. No encoder and no fallback terms: a wrong key opens no record."""

    # lora at rank 4 matched unsealed PRoP's personalization on IL and digits at ~2% of its bytes
    # (docs/sealed.md, "Choosing the payload"); full is the strongest, delta the smallest.
    payload: str = setting(
        "lora",
        "With --seal: lora, delta, full or peft-lora (what is stored per user; peft-lora exports as a "
        "standard peft adapter: prop export --peft).",
    )
    payload_rank: int = setting(4, "With --seal --payload lora or peft-lora: the update's rank.")
    payload_lr: float = setting(
        0.01, "Adam learning rate of a sealed bundle's payload (cosine decay)."
    )  # cosine-decays like lr

    def __post_init__(self) -> None:
        self.need(self.payload in PAYLOAD_KINDS, "payload", " or ".join(PAYLOAD_KINDS))
        self.at_least(payload_rank=1)
        self.positive("payload_lr")


Mode = UnsealedConfig | SealedConfig

# The two flags that choose a mode's part rather than set a field of one (PersonalizeConfig.of).
SWITCHES = {
    "seal": "Sealed bundle: base = the original, each user's payload encrypted under their key.",
    "harden": "Hardened unsealed mode: code-space negatives and an unrecorded encoder init "
    "(docs/hardening.md).",
}
_PARTS = {"train": TrainConfig, "unsealed": UnsealedConfig, "hardening": Hardening, "sealed": SealedConfig}


def _fields(cls: type) -> dict[str, Any]:
    return {f.name: f for f in fields(cls) if f.name != "hardening"}


def _part(cls: type, d: dict, **extra: Any) -> Any:
    return cls(**{k: v for k, v in d.items() if k in _fields(cls)}, **extra)


@dataclass(frozen=True)
class PersonalizeConfig:
    """personalize's settings: what every recipe reads, and the mode's own part (``UnsealedConfig`` or
    ``SealedConfig``). Recorded flat in the bundle's manifest (``to_dict``) so a run can be repeated."""

    train: TrainConfig = field(default_factory=TrainConfig)
    mode: Mode = field(default_factory=UnsealedConfig)

    @property
    def sealed(self) -> bool:
        return isinstance(self.mode, SealedConfig)

    @classmethod
    def of(cls, *, seal: bool = False, harden: bool = False, **settings: Any) -> PersonalizeConfig:
        """The settings from flat flags, as the CLI gives them (any field of the parts, by name; a
        ``Hardening`` field None: the preset's). The one place that refuses a flag of the other mode:
        a payload setting without ``seal``, and --harden or its measures with it. The encoder's other
        settings are left out of a sealed config (the --seal recipe has none of them to train)."""
        unknown = sorted(set(settings) - {n for c in _PARTS.values() for n in _fields(c)})
        if unknown:
            raise TypeError(f"not a setting of personalize: {', '.join(unknown)}")
        train = _part(TrainConfig, settings)
        hardening = Hardening.preset(harden, **{k: settings.get(k) for k in _fields(Hardening)})
        if not seal:
            for name, f in _fields(SealedConfig).items():  # an unsealed bundle has no payload: a payload
                value = settings.get(name, f.default)  # setting without --seal would be silently ignored
                _require(value == f.default, f"{flag(name)} {value} applies to sealed bundles only",
                         f"add --seal, or drop {flag(name)}")  # fmt: skip
            return cls(train, _part(UnsealedConfig, settings, hardening=hardening))
        given = (["--harden"] if harden else hardening.flags()) + [
            f"{flag(k)} {settings[k]}" for k in ("code_flip_max", "code_relax_min")
            if settings.get(k) is not None and settings[k] != getattr(PLAIN, k)
        ]  # fmt: skip
        _require(  # a sealed recipe trains none of --harden's measures: the manifest would record them
            not given,
            f"{', '.join(given)}: --harden's measures harden an unsealed bundle's encoder; a sealed "
            "bundle trains none of them",
            "drop them (a sealed bundle keeps each user's payload encrypted), or drop --seal",
        )
        return cls(train, _part(SealedConfig, settings))

    def replace(self, **settings: Any) -> PersonalizeConfig:
        """These settings with some flat flags changed (checked as ``of`` checks them)."""
        return PersonalizeConfig.of(**{**self.to_dict(), **settings})

    def check_key_bits(self, key_bits: int) -> None:
        if isinstance(self.mode, UnsealedConfig):
            self.mode.check_key_bits(key_bits)

    def to_dict(self) -> dict:
        """Flat, as the manifest records it (every version: old bundles' keys are these)."""
        mode = asdict(self.mode)
        hardening = mode.pop("hardening", None)
        extra = {} if hardening is None else {**hardening, "harden": self.mode.hardening.is_hardened}
        return {**asdict(self.train), **mode, **extra, "seal": self.sealed}

    @classmethod
    def from_dict(cls, d: dict) -> PersonalizeConfig:
        """A manifest's settings, of any version (0.1 and 0.2 recorded every field flat, --harden's left
        None or filled). Lenient where ``of`` is strict: a sealed bundle's recorded encoder settings, or
        --harden's (written before --seal --harden was refused), are not part of a sealed config and
        are left out, so that bundle's own add-user reads it."""
        if d.get("seal"):
            return cls(_part(TrainConfig, d), _part(SealedConfig, d))
        hardening = Hardening.preset(bool(d.get("harden")), **{k: d.get(k) for k in _fields(Hardening)})
        return cls(_part(TrainConfig, d), _part(UnsealedConfig, d, hardening=hardening))


def cli_settings(*names: str) -> dict[str, tuple[Any, Any, str]]:
    """personalize's settings as CLI options: name -> (type, default, help), read from the fields
    (``names``: these, in this order; none: every field the CLI has a flag for, and the switches).
    A ``Hardening`` measure's CLI default is None: the preset's (--harden's, or the plain one)."""
    import typing

    out: dict[str, tuple[Any, Any, str]] = {}
    for part, cls in _PARTS.items():
        hints = typing.get_type_hints(cls)
        if part == "sealed":
            out["seal"] = (bool, False, SWITCHES["seal"])
        for name, f in _fields(cls).items():
            if f.metadata.get("cli"):
                t, default = hints[name], default_of(f)
                if part == "hardening" and name in Hardening.PRESET:
                    t, default = t | None, None
                out[name] = (t, default, f.metadata["help"])
        if part == "unsealed":
            out["harden"] = (bool, False, SWITCHES["harden"])
    return {n: out[n] for n in names} if names else out


def settings_table() -> str:
    """docs/cli.md's table of personalize's settings: flag, default and help, from the fields."""
    rows = ["| Flag | Default | Mode | What |", "|---|---|---|---|"]
    modes = {"train": "all", "unsealed": "unsealed", "hardening": "unsealed", "sealed": "--seal"}
    for part, cls in _PARTS.items():
        for name, f in _fields(cls).items():
            if f.metadata.get("cli"):
                d = default_of(f)
                shown = "preset" if part == "hardening" and name in Hardening.PRESET else d
                rows.append(f"| `{flag(name)}` | {'' if d is None else f'`{shown}`'} | {modes[part]} | "
                            f"{f.metadata['help'].replace('|', '/')} |")  # fmt: skip
    return "\n".join(rows)


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
