"""Finding a key's own record or enrolment by name (format 6), without trying every user's.

Since format 6 each sealed record and each enrolment is filed under a **lookup name**: 16 bytes of
HKDF-SHA256 of the user's key bytes, salted with the bundle id, under the label ``prop/lookup/v1``
(``cipher.LOOKUP_INFO``). Opening a key computes its name once and looks it up, so the cost is the same
for one user or 10,000 and says nothing of which user the key is, or of how many there are:

- the name is found: that one record (enrolment) is opened, as it was by trial decryption before;
- it is not found (a key enrolled in nothing): a **stand-in** of the same kind, picked by the name, is
  tried with the key all the same (read, hashed, decrypted: it cannot open) and the key is refused
  after the same work.

Entries without a name (written in format 1-5, or kept through ``prop enrol`` when it made an unsealed
bundle format 6) are all tried as before, on every key: an older bundle costs one trial per user.

What a name gives away without the key: nothing. It is a pseudo-random function of the key (HKDF's
extract and expand, keyed with the key bytes), never the key or a plain hash of it; under another
bundle id the same key has an unrelated name, so names do not link a user across bundles. Testing a
guessed key against a name costs one HKDF, what a record's ciphertext already offered (HKDF and one AES
block of the padded plaintext's known framing). One computation tests a guess against every user's name
at once, where trial decryption takes one HKDF per record (each has its own salt): a search for any
user's key is up to n times cheaper with n users, 2^-13.3 of the work at 10,000 users of 128-bit keys
(2^114.7 guesses left); a passphrase's guesses cost one scrypt each either way (the bundle has one salt).
"""

from __future__ import annotations

import numpy as np

from prop_cli import constants as C

from .cipher import lookup_name

LOOKUP = C.M_LOOKUP  # the field of a record's or enrolment's entry holding its name (format 6 on)


def salt_of(manifest: dict) -> str | None:
    """The bundle id names are derived under where its format files users by name (6 on), else None."""
    if manifest.get(C.M_FORMAT, 0) >= C.LOOKUP_SINCE:
        return manifest.get(C.M_BUNDLE_ID)
    return None


class Index:
    """Where each entry of a list of records or enrolments is filed: by name, or nowhere (tried always)."""

    def __init__(self, names: list[str | None], bundle_id: str | None) -> None:
        self.bundle_id = bundle_id
        named = {} if bundle_id is None else {n: i for i, n in enumerate(names) if n is not None}
        self.by_name = named
        self.named = sorted(named.values())  # the stand-ins' choice, in list order
        self.unnamed = [i for i, n in enumerate(names) if n is None or bundle_id is None]

    @classmethod
    def of(cls, entries: list[dict], manifest: dict) -> Index:
        return cls([e.get(LOOKUP) for e in entries], salt_of(manifest))

    def name(self, bits: np.ndarray) -> str | None:
        """The name ``bits`` would be filed under here (None: this bundle files nothing by name)."""
        return None if self.bundle_id is None else lookup_name(bits, self.bundle_id)

    def tries(self, bits: np.ndarray) -> tuple[int | None, bool, list[int]]:
        """What opening ``bits`` tries: (the entry filed under its name, or a stand-in when none is, or
        None when nothing is named; whether what it opens counts: False for a stand-in; every unnamed
        entry). The same work for every key: one name, one named entry, every unnamed one."""
        if not self.by_name:
            return None, False, self.unnamed
        name = lookup_name(bits, self.bundle_id)
        found = self.by_name.get(name)
        if found is not None:
            return found, True, self.unnamed
        return self.named[int(name, 16) % len(self.named)], False, self.unnamed

    def holds(self, bits: np.ndarray) -> bool:
        """Whether an entry is filed under the name of ``bits`` (a new user's key must not be)."""
        return bool(self.by_name) and lookup_name(bits, self.bundle_id) in self.by_name
