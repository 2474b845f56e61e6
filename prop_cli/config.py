"""Training settings: one dataclass, validated in one place, recorded in the manifest."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from .errors import PropError
from .keyed import KEY_ENCODINGS


@dataclass
class PersonalizeConfig:
    steps: int = 2000
    lr: float = 1e-3  # Adam, base weights and encoder; cosine-decays to lr * lr_floor
    lr_floor: float = 0.05
    # Rows of one step: each row is one (sample, key) pair.
    user_rows: int = 64  # per step, shared among users: the user's key on the user's data
    null_rows: int = 32  # distinct fallback samples per step, each also run with the null key
    random_keys: int = 8  # K2: uniform random keys per step
    neighbour_keys: int = 32  # K1: Hamming neighbours of the user keys per step
    samples_per_key: int = 4  # fallback samples each sampled key is run on
    hamming_radius: int = 8  # epsilon of Eq. 8: neighbours at distance 1..radius
    null_weight: float = 10.0  # the no-key behaviour is what everyone else gets: weigh it up
    encoder_hidden: list[int] = field(default_factory=lambda: [256])
    delta_scale: float = 2.0  # delta in (1 - scale, 1 + scale)
    key_encoding: str = "hashed"
    freeze_base: bool = False
    val_fraction: float = 0.2
    seed: int = 0
    layers: list[str] | None = None  # None = default choice (see layers.default_layers)
    exclude: list[str] | None = None
    eval_random_keys: int = 64

    @property
    def batch_rows(self) -> int:
        return (
            self.user_rows + self.null_rows + (self.random_keys + self.neighbour_keys) * self.samples_per_key
        )

    def validate(self) -> PersonalizeConfig:
        def need(ok: bool, flag: str, rule: str) -> None:
            if not ok:
                raise PropError(
                    f"{flag} {getattr(self, flag[2:].replace('-', '_'))!r} is invalid",
                    f"{flag} must be {rule}",
                )

        need(self.steps >= 1, "--steps", "at least 1")
        need(self.lr > 0, "--lr", "positive")
        need(0 < self.lr_floor <= 1, "--lr-floor", "in (0, 1]")
        need(self.user_rows >= 1, "--user-rows", "at least 1")
        need(self.null_rows >= 1, "--null-rows", "at least 1")
        need(self.random_keys >= 0, "--random-keys", ">= 0")
        need(self.neighbour_keys >= 0, "--neighbour-keys", ">= 0")
        need(self.samples_per_key >= 1, "--samples-per-key", "at least 1")
        need(self.hamming_radius >= 1, "--hamming-radius", "at least 1")
        need(self.null_weight >= 0, "--null-weight", ">= 0")
        need(self.delta_scale > 0, "--delta-scale", "positive")
        need(self.key_encoding in KEY_ENCODINGS, "--key-encoding", " or ".join(KEY_ENCODINGS))
        need(0 < self.val_fraction < 1, "--val-fraction", "in (0, 1)")
        need(self.eval_random_keys >= 1, "--eval-random-keys", "at least 1")
        need(all(h >= 1 for h in self.encoder_hidden), "--encoder-hidden", "positive sizes")
        return self

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PersonalizeConfig:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})
