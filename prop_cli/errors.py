"""The one error type for expected failures.

Everything a user can cause (bad file, bad flag, bad data) raises :class:`PropError`. The CLI catches
it once and prints one line; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class PropError(Exception):
    """An expected failure: ``what`` went wrong and ``fix`` says what to do about it."""

    def __init__(self, what: str, fix: str | None = None) -> None:
        self.what = what
        self.fix = fix
        super().__init__(self.line())

    def line(self) -> str:
        return f"{self.what}; {self.fix}" if self.fix else self.what


def plural(n: int, noun: str, nouns: str | None = None) -> str:
    """``n`` and the noun it counts, for messages: "1 user", "2 users", "0 users"."""
    return f"{n} {noun if n == 1 else nouns or noun + 's'}"


def brief(e: BaseException, width: int = 120) -> str:
    """``Type: first line of the message``, short enough for a one-line error."""
    first = (str(e).splitlines() or [""])[0][:width]
    return f"{type(e).__name__}: {first}" if first else type(e).__name__
