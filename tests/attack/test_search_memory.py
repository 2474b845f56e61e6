"""A search step's rows bounded by memory (``probes.base.GRAPH_BYTES``): chunked and unchunked searches
give the same results, the chunks stay within the bound, and the budget still stops a search."""

from __future__ import annotations

import time

import pytest
import torch
from torch import nn

from prop_cli.attack.probes import base, fewshot, latent
from prop_cli.attack.probes.base import ProbeContext, Reference, saved_bytes
from prop_cli.config import AuditSettings
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder


def _context(task: str = "regression", **settings) -> ProbeContext:
    torch.manual_seed(0)
    module = nn.Sequential(nn.Linear(6, 16), nn.Tanh(), nn.Linear(16, 16), nn.Tanh(), nn.Linear(16, 3))
    enc = KeyEncoder(16, [6, 16], [32], 0.5)
    with torch.no_grad():  # a non-zero head: every code moves the deltas
        for p in enc.parameters():
            p.normal_(0, 0.3)
    km = KeyedModel(module.eval(), enc, ["0", "2"]).eval().requires_grad_(False)
    x = torch.randn(12, 6)
    with torch.inference_mode():
        b = module(x)
    p = b + 0.5 if task == "regression" else torch.randint(0, 3, (12,))
    ref = Reference(x, b.clone(), p, task)
    s = AuditSettings(**({"restarts": 5, "search_steps": 4, "search_batch": 0} | settings))
    shots = Reference(torch.randn(8, 6), b[:8].clone(), p[:8].clone(), task)
    return ProbeContext(km, ref, s, [], "hashed", probe="test", shots=shots)


def _rows_per_forward(monkeypatch) -> list[int]:
    rows = []
    run = KeyedModel.run_keys

    def counted(self, x, deltas):
        if torch.is_grad_enabled():
            rows.append(len(x) * len(deltas[0]))
        return run(self, x, deltas)

    monkeypatch.setattr(KeyedModel, "run_keys", counted)
    return rows


@pytest.mark.parametrize("task", ["regression", "classification"])
def test_a_chunked_search_finds_what_the_unchunked_one_finds(task, monkeypatch):
    """T2's search with every step in one backward, and with a bound of 5 rows (chunks of restarts and of
    samples, gradients accumulated): the same deltas and scores within fp32 tolerance."""
    [whole] = latent._search(_context(task))
    ctx = _context(task)
    ones = [torch.ones(1, f, requires_grad=True) for f in ctx.km.encoder.features]
    per_row = saved_bytes(ctx.km, ctx.ref.x[:4], ones) / 4  # as graph_rows measures it
    monkeypatch.setattr(base, "GRAPH_BYTES", int(5 * per_row) + 1)
    rows = _rows_per_forward(monkeypatch)
    [chunked] = latent._search(ctx)
    # the bound measured once (1 key x 4 samples, no backward), then 5 restarts x 12 samples a step in
    # backwards of at most 5 rows (5 + 5 + 2 samples: unequal shares)
    assert rows[0] == 4 and max(rows[1:]) <= 5 and len(rows) == 1 + 4 * 5 * 3
    for m in ("divergence", "fidelity", "leakage", "bounded"):
        torch.testing.assert_close(chunked.values[m], whole.values[m], rtol=1e-4, atol=1e-6)


def test_the_relaxed_and_fewshot_fits_are_unchanged_by_chunks(monkeypatch):
    """T1 (through the encoder) and T3's code and delta fits: the same results with a 3-row bound (8
    shots: 3 + 3 + 2)."""
    from prop_cli.attack.probes import relaxed

    whole = relaxed.run(_context())
    codes, losses = fewshot.fit_codes(_context(), _context().shots, torch.Generator().manual_seed(1), 4, 6)
    fitted = fewshot._fit_delta_run(_context(), _context().shots, torch.Generator().manual_seed(2))
    rows = _rows_per_forward(monkeypatch)
    monkeypatch.setattr(base, "graph_rows", lambda ctx, x, deltas: 3)
    chunked = relaxed.run(_context())
    codes2, losses2 = fewshot.fit_codes(_context(), _context().shots, torch.Generator().manual_seed(1), 4, 6)
    fitted2 = fewshot._fit_delta_run(_context(), _context().shots, torch.Generator().manual_seed(2))
    assert max(rows) <= 3
    for g, h in zip(whole, chunked, strict=True):
        torch.testing.assert_close(h.values["divergence"], g.values["divergence"], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(codes2, codes, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(losses2, losses, rtol=1e-4, atol=1e-6)
    for d, e in zip(fitted, fitted2, strict=True):
        torch.testing.assert_close(e, d, rtol=1e-4, atol=1e-5)


def test_a_chunk_holds_no_more_graph_than_the_bound(monkeypatch):
    """The measured graph of one backward's rows stays within GRAPH_BYTES; the rows of a whole step
    would not."""
    ctx = _context(restarts=8, search_steps=1)
    deltas = [torch.ones(8, f, requires_grad=True) for f in ctx.km.encoder.features]
    step = saved_bytes(ctx.km, ctx.ref.x, deltas)
    monkeypatch.setattr(base, "GRAPH_BYTES", step // 6)
    held = []
    backward = torch.Tensor.backward

    def measured(self, *a, **k):
        held.append(sum(t.untyped_storage().nbytes() for t in graph))
        graph.clear()
        return backward(self, *a, **k)

    graph: list[torch.Tensor] = []
    monkeypatch.setattr(torch.Tensor, "backward", measured)
    with torch.autograd.graph.saved_tensors_hooks(lambda t: graph.append(t) or t, lambda t: t):
        latent._search(ctx)
    assert len(held) > 6 and max(held) <= step // 6 + 16 * 16 * 4 * 4  # the weights the graph saves too


def test_a_budget_still_stops_a_chunked_search(monkeypatch):
    monkeypatch.setattr(base, "graph_rows", lambda ctx, x, deltas: 2)
    ctx = _context(search_steps=50)
    ctx.deadline = time.perf_counter() - 1
    steps = []
    monkeypatch.setattr(torch.optim.Adam, "step", lambda self, *a, **k: steps.append(1))
    latent._search(ctx)
    assert steps == [] and "latent" in ctx.cut
