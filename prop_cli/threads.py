"""How many threads torch computes with: chosen from the model's size and the machine.

torch's default (one thread per core) is the wrong choice for the models prop usually sees. A
training step of a small policy is a few hundred microseconds of work per operator, less than
waking a second thread costs, so two threads burn more CPU for no speed-up; and when another
process keeps a core busy, every parallel region waits for the descheduled thread (on a 2-core
machine: `examples.reproduce all --quick` 229 s with 2 threads against 23 s with 1).

The rule: one thread below ``PARALLEL_PARAMS`` parameters; above it, one per core that is not
already busy (cores minus the 1-minute load average, rounded), at least one. An explicit count
(``--threads``) wins, then ``OMP_NUM_THREADS`` if the user set it (torch already honours it, so it is
left alone), then the rule. No torch at import time (``prop --help`` stays fast).
"""

from __future__ import annotations

import functools
import os

from .constants import ENV_OMP_THREADS
from .errors import PropError

# Parameters from which a second thread may pay for itself. Below it, measured (issue 13): at 38k
# parameters two threads burned 66% more CPU for no speed-up on an idle machine. The value itself is
# where the PRoP step's fixed overhead fades (benchmarks/table.py), not a measured crossover.
PARALLEL_PARAMS = 1_000_000


def cores() -> int:
    """CPUs this process may run on (the affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@functools.cache
def free_cores() -> int:
    """Cores not kept busy by other processes: the count minus the 1-minute load average, at least 1.

    Read once per process, at its first entry point: later, the load would count this process's own work.
    """
    total = cores()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return total
    return max(1, min(total, round(total - load)))


def choose(parameters: int, free: int | None = None) -> int:
    """The rule of the module docstring, for a model of ``parameters`` parameters."""
    if parameters < PARALLEL_PARAMS:
        return 1
    return free if free is not None else free_cores()


def check(threads: int | None, flag: str = "--threads") -> int | None:
    """Validate a requested count: None or 0 = choose automatically."""
    if threads is None or threads == 0:
        return None
    if threads < 0:
        raise PropError(f"{flag} {threads} is invalid", f"{flag} must be >= 1, or 0 to choose automatically")
    return threads


def configure(parameters: int, threads: int | None = None) -> int:
    """Set torch's intra-op threads for work on a model of ``parameters`` parameters; returns the count.

    ``threads`` (>= 1) is used as given; else an ``OMP_NUM_THREADS`` set by the user is respected;
    else ``choose``. Called once by each library entry point that computes (``prop_cli.api``).
    """
    import torch

    threads = check(threads)
    if threads is None:
        if os.environ.get(ENV_OMP_THREADS, "").strip():
            return torch.get_num_threads()
        threads = choose(parameters)
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return threads
