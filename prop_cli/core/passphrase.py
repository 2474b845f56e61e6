"""How long a passphrase holds: zxcvbn's estimate of the guesses it takes, times the scrypt time per
guess measured on this machine (one core). A sealed record, an enrolment or an unsealed encoder can
each be tested offline against a guessed passphrase, so a weak one opens the bundle to anyone with the
files (the dictionary attack of docs/sealed.md). Measured, not promised: an attacker with many cores
or GPUs divides the time by their parallelism.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from dataclasses import asdict, dataclass

from prop_cli.constants import (
    PASSPHRASE_MIN_YEARS,
    SALT_BYTES,
    SCRYPT_N,
    SCRYPT_P,
    SCRYPT_R,
)
from prop_cli.errors import PropError

YEAR = 365.25 * 24 * 3600
WEAK_FLAG = "--weak-passphrase"


@dataclass(frozen=True)
class Strength:
    guesses: float  # zxcvbn's estimate
    seconds_per_guess: float  # one scrypt derivation on one core, measured
    core_years: float  # guesses x seconds per guess
    min_core_years: float
    passed: bool

    def line(self) -> str:
        return (
            f"about 10^{math.log10(max(self.guesses, 1)):.1f} guesses x {self.seconds_per_guess * 1e3:.0f} "
            f"ms per scrypt guess = {self.core_years:.3g} core-years to open (needs >= "
            f"{self.min_core_years:g})"
        )

    def to_dict(self) -> dict:
        return asdict(self)


def guesses(passphrase: str) -> float:
    """zxcvbn's estimate of the guesses a smart attacker needs (dictionaries, patterns, l33t...)."""
    try:
        from zxcvbn import zxcvbn
    except ImportError:  # a broken install: prop-keys requires zxcvbn
        raise PropError("estimating passphrase strength needs zxcvbn", "pip install zxcvbn") from None
    return float(zxcvbn(passphrase[:256])["guesses"])  # zxcvbn slows down on very long inputs


def scrypt_seconds(rounds: int = 3) -> float:
    """One scrypt derivation with prop's parameters (``keys.passphrase_bits``), timed on this machine
    (best of ``rounds``: what an attacker's tuned loop gets, not a busy moment's)."""
    salt, best = os.urandom(SALT_BYTES), math.inf
    for _ in range(rounds):
        t0 = time.perf_counter()
        mem = 4 * 128 * SCRYPT_R * SCRYPT_N * SCRYPT_P
        hashlib.scrypt(b"timing", salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, maxmem=mem, dklen=16)
        best = min(best, time.perf_counter() - t0)
    return best


def strength(
    passphrase: str, seconds_per_guess: float | None = None, min_core_years: float = PASSPHRASE_MIN_YEARS
) -> Strength:
    sec = scrypt_seconds() if seconds_per_guess is None else seconds_per_guess
    g = guesses(passphrase)
    years = g * sec / YEAR
    return Strength(g, sec, years, min_core_years, years >= min_core_years)


def check_strength(passphrase: str, what: str, allow_weak: bool = False) -> Strength:
    """Refuse a passphrase that takes less than PASSPHRASE_MIN_YEARS to guess, unless ``allow_weak``."""
    s = strength(passphrase)
    if not s.passed and not allow_weak:
        raise PropError(
            f"{what} is weak: {s.line()}",
            f"use a longer passphrase (e.g. 5 random words) or a key file (prop keygen); {WEAK_FLAG} "
            "accepts it anyway",
        )
    return s
