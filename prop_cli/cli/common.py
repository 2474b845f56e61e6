"""What the commands share: output streams, progress, key input, JSON output. No torch here (fast --help)."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import typer
from rich.console import Console, ConsoleDimensions

# Where output is not a terminal (a pipe, a log file), rich would wrap at 80 columns and split table
# cells; there the console is as wide as any line and never wraps, unless COLUMNS asks for a width
# (then tables wrap their cells to it, as on a terminal).
_WIDE = 100_000


class _Stream(Console):
    """A console on stdout or stderr that, when it is not a terminal and COLUMNS is not set, never wraps
    or splits a line. Decided at each print (the stream or COLUMNS may change after import)."""

    def _unbounded(self) -> bool:
        return not self.is_terminal and not self._environ.get("COLUMNS", "").isdigit()

    @property
    def size(self) -> ConsoleDimensions:
        dims = Console.size.fget(self)
        return ConsoleDimensions(_WIDE, dims.height) if self._unbounded() else dims

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        Console.size.fset(self, new_size)

    @property
    def soft_wrap(self) -> bool:
        return self._soft_wrap or self._unbounded()

    @soft_wrap.setter
    def soft_wrap(self, value: bool) -> None:
        self._soft_wrap = value


out = _Stream()  # results
err = _Stream(stderr=True)  # progress and diagnostics


def fail(what: str, fix: str | None = None):
    """Raise the one expected-failure type from CLI code."""
    from prop_cli.errors import PropError

    raise PropError(what, fix)


def parse_json_option(value: str | None, flag: str) -> dict | None:
    if value is None:
        return None
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError as e:
        fail(f"{flag} is not valid JSON ({e.msg})", f"e.g. {flag} '{{\"hidden\": 256}}'")
    if not isinstance(parsed, dict):
        fail(f"{flag} must be a JSON object", f"e.g. {flag} '{{\"hidden\": 256}}'")
    return parsed


def checkpoint_options(
    arch: str | None, arch_kwargs: str | None, activation: str | None, trust_remote_code: bool = False
):
    from prop_cli.api import CheckpointOptions

    kwargs = parse_json_option(arch_kwargs, "--arch-kwargs")
    return CheckpointOptions(arch, kwargs, activation, trust_remote_code)


def read_passphrase(prompt: str = "Passphrase") -> str:
    from prop_cli.constants import ENV_PASSPHRASE

    value = os.environ.get(ENV_PASSPHRASE)
    if value is None:
        if not sys.stdin.isatty():
            fail(
                "--passphrase needs a terminal to prompt on",
                f"set {ENV_PASSPHRASE} for scripts, or use --key-file",
            )
        value = typer.prompt(prompt, hide_input=True)
    return value


def print_json(obj: dict) -> None:
    from prop_cli.files import dump_json

    sys.stdout.write(dump_json(obj))


def warn(message: str) -> None:
    print(f"prop: warning: {message}", file=sys.stderr)


# What to try when the wrong keys drift systematically (personalize's lean, eval's drift): --delta-pull is
# already 100 for policies, and what was left on the point-mass tasks was the keys farthest from yours.
DRIFT_FIX = ("personalize again with more --steps, a stronger --delta-pull, --antipode-codes 16 (the codes "
             "farthest from yours; examples/RESULTS.md, point mass), or --seal")  # fmt: skip

PLAIN_EVERY_S = 60.0  # the longest a plain progress display stays silent


def duration(seconds: float) -> str:
    """A rough duration for people: 40 s, 3 min 20 s, 2 h 05 min."""
    s = round(seconds)
    if s < 1:
        return "under 1 s"
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def step_progress(fn: Callable, total: int, label: str, fields: Callable[[dict], str]):
    """Run ``fn(callback)`` with a progress display on stderr: a bar on a terminal, else a plain line
    every tenth of the way (logs, nohup)."""
    if not err.is_terminal:
        every = max(1, total // 10)
        t0 = time.perf_counter()
        first: list[tuple[int, float]] = []  # the first step reported: set-up ends there, steps are timed
        shown = [t0]

        def plain(step: int, info: dict) -> None:
            now = time.perf_counter()
            if not first:
                first.append((step, now))
            # A line every tenth of the way, and at least once a minute (a long policy run's tenth is long).
            if step % every == 0 or step == total or now - shown[0] >= PLAIN_EVERY_S:
                shown[0] = now
                (s0, t1), eta = first[0], ""
                if s0 < step < total:  # steps left x the mean step time so far
                    eta = f", about {duration((total - step) * (now - t1) / (step - s0))} left"
                print(f"{label}: step {step}/{total} ({now - t0:.1f} s{eta}) {fields(info)}", file=sys.stderr,
                      flush=True)  # fmt: skip

        return fn(plain)

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(
        TextColumn(label), BarColumn(), TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(),
        TimeRemainingColumn(), TextColumn("{task.fields[info]}"), console=err, transient=True,
    ) as bar:  # fmt: skip
        task = bar.add_task(label, total=total, info="")

        def rich_cb(step: int, info: dict) -> None:
            if step % 10 == 0 or step == total:
                bar.update(task, completed=step, info=fields(info))

        return fn(rich_cb)


def stage_progress(fn: Callable):
    """Run ``fn(callback(stage, done, total))``: a bar per stage on a terminal, else a line per finished
    stage."""
    if not err.is_terminal:
        t0 = time.perf_counter()

        def plain(stage: str, done: int, total: int) -> None:
            if done == total:
                print(f"attack: {stage} {done}/{total} ({time.perf_counter() - t0:.1f} s)", file=sys.stderr)

        return fn(plain)

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description:<12}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(), console=err, transient=True,
    ) as bar:  # fmt: skip
        tasks: dict[str, int] = {}

        def rich_cb(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        return fn(rich_cb)


def output_path(value: Path | None) -> Path | None:
    """``-`` means stdout: no file."""
    return None if value is None or str(value) == "-" else value


# A status line shows once its stage has lasted this long: a real-size policy's set-up or report (minutes)
# is said while it runs, and a small model's (milliseconds) or one that ends in an error (one line: the
# error) says nothing. 0: every status at once (tests).
STATUS_AFTER_S = 1.0


class StatusLines:
    """A ``status`` callback: one stderr line for a stage a run spends time in outside its steps, with the
    time since the run started (above the progress bar on a terminal: the bar's console prints it). Use it
    as a context manager: a stage still pending when the run ends is never shown."""

    def __init__(self, label: str) -> None:
        self.label, self.t0 = label, time.perf_counter()
        self.pending: threading.Timer | None = None

    def __call__(self, what: str) -> None:
        self.close()
        if STATUS_AFTER_S <= 0:
            self._show(what)
            return
        self.pending = threading.Timer(STATUS_AFTER_S, self._show, (what,))
        self.pending.daemon = True
        self.pending.start()

    def _show(self, what: str) -> None:
        line = f"{self.label}: {what} ({time.perf_counter() - self.t0:.1f} s)"
        if err.is_terminal:
            err.print(line, markup=False, highlight=False)
        else:
            print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.pending is not None:
            self.pending.cancel()
            self.pending = None

    def __enter__(self) -> StatusLines:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def training_progress(fn: Callable, steps: int, label: str):
    """``step_progress`` for a training run: the step's latest losses beside the bar."""
    return step_progress(fn, steps, label, lambda losses: " ".join(f"{k} {v:.4f}" for k, v in losses.items()))
