"""Requests from any connection that arrive within a short window run as one forward (``rows.run_requests``).

The first request opens a window of ``window_s``; the batch goes when the window closes or ``max_rows``
observations are waiting, whichever is first. One batch runs at a time on the server's worker thread;
what arrives meanwhile waits for the next (so a busy server batches more, as continuous batching does).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from concurrent.futures import Executor

from .rows import Request


class Batcher:
    """``await submit(request)`` -> that request's raw output; ``run(requests) -> outputs`` runs a batch."""

    def __init__(self, run: Callable[[Sequence[Request]], list], pool: Executor, window_s: float,
                 max_rows: int) -> None:  # fmt: skip
        self.run, self.pool, self.window_s, self.max_rows = run, pool, window_s, max_rows
        self._waiting: list[tuple[Request, asyncio.Future]] = []
        self._timer: asyncio.TimerHandle | None = None
        self._busy = False
        self.batches = 0  # forwards run (a figure for tests and benchmarks)
        self.rows = 0

    def _rows_waiting(self) -> int:
        return sum(r.rows for r, _ in self._waiting)

    async def submit(self, request: Request):
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        self._waiting.append((request, future))
        if self._rows_waiting() >= self.max_rows:
            self._go()
        elif self._timer is None and not self._busy:
            self._timer = loop.call_later(self.window_s, self._go)
        return await future

    def _go(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._busy or not self._waiting:
            return
        batch, rows = [], 0
        while self._waiting and (not batch or rows + self._waiting[0][0].rows <= self.max_rows):
            item = self._waiting.pop(0)
            batch.append(item)
            rows += item[0].rows
        self._busy = True
        self.batches += 1
        self.rows += rows
        loop = asyncio.get_running_loop()
        done = loop.run_in_executor(self.pool, self.run, [r for r, _ in batch])
        done.add_done_callback(lambda f: self._finished(f, batch))

    def _finished(self, done: asyncio.Future, batch: list) -> None:
        self._busy = False
        error = done.exception()
        outputs = None if error is not None else done.result()
        for i, (_, future) in enumerate(batch):
            if future.done():  # its connection went away
                continue
            if error is not None:
                future.set_exception(error)
            else:
                future.set_result(outputs[i])
        if self._waiting:  # what came while this batch ran has waited long enough: it goes now
            self._go()
