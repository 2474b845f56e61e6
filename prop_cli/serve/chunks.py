"""Many users' LeRobot observations in one forward of the base policy (issue 39): each connection's frame
is a row of one ``predict_action_chunk`` call, each row under its own user's behaviour, as ``rows`` does
for array models.

Batched: the policies whose chunk depends on the frame alone (``Controller.stateless_chunk``: ACT,
SmolVLA, pi0, pi0.5), and, for the sampling ones, whose ``predict_action_chunk`` takes its noise: each
request's noise is drawn from that connection's own seed (``call_seed``, as ``Controller.action_chunk``
draws it) and the rows' noises concatenated, so a row's chunk is the one its connection would get alone.
Diffusion keeps an observation history on its module: its connections each run their own (``sessions``).

A row's behaviour is applied on the keyed layers along each layer's batch axis (ACT's transformer is
sequence-first: (S, B, D)): an unsealed key's deltas through ``KeyedModel.call_rows``, a sealed payload
through ``rows``' gathered hooks (LoRA: Punica's BGMV), a ``Folded`` behaviour on its own module. Requests
whose preprocessed tensors differ in shape (a VLA's instructions tokenized to different lengths) run as
separate forwards of the same call; nothing is padded, so no row sees another's tokens.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from prop_cli.bundle import Bundle
from prop_cli.constants import TASK
from prop_cli.core.batch_axes import probe_batch_axes
from prop_cli.errors import PropError

from .rows import (
    Behaviour,
    Deltas,
    Folded,
    PayloadTable,
    RowMismatch,
    payload_handles,
    row_deltas,
    runs_alone,
)


@dataclass
class ChunkRequest:
    """One connection's frame(s), as its controller's ``_inputs`` made them, under its behaviour."""

    behaviour: Behaviour
    x: dict
    rows: int
    single: bool
    seed: int


def batchable(bundle: Bundle) -> bool:
    """Whether a LeRobot ``bundle``'s connections can share forwards (``ChunkRunner``)."""
    loaded = bundle.loaded
    controller = loaded.policy.on(loaded.module).controller(loaded.module)
    if not controller.stateless_chunk:
        return False
    takes_noise = "noise" in inspect.signature(loaded.module.predict_action_chunk).parameters or (
        loaded.policy.denoiser is not None and hasattr(loaded.module.model, "sample_noise")
    )
    return loaded.policy.denoiser is None or takes_noise


class ChunkRunner:
    """``run(requests) -> [chunk (steps, dim) or (N, steps, dim) in action units]`` for a LeRobot bundle
    that ``batchable`` accepts; ``controller()`` makes a connection's own controller (its episode, its
    noise count) over the shared base module. ``table``: the server's payload slots (a sealed bundle);
    ``batch_no_key``: no-key requests share the forward too (else each runs alone: bit for bit)."""

    def __init__(self, bundle: Bundle, table: PayloadTable | None = None, batch_no_key: bool = False) -> None:
        loaded = bundle.loaded
        self.bundle, self.module, self.protocol = bundle, loaded.module.eval(), loaded.policy
        self.keyed = bundle.mode.keyed  # an unsealed bundle's encoder over the base: rows' deltas
        if self.keyed is not None and self.keyed.module is not self.module:
            self.keyed = None  # behaviours are then folded (``Folded``)
        self.sampling = loaded.policy.denoiser is not None
        self.table = table  # a sealed bundle's payload slots (the server's); None: stacked per batch
        self.batch_no_key = batch_no_key  # no-key rows join the others' forward (within float rounding)
        self.batches = 0
        self.axes = self._axes()

    def controller(self, module: torch.nn.Module | None = None):
        module = self.module if module is None else module
        return self.protocol.on(module).controller(module)

    def _axes(self) -> dict[str, int]:
        """Each keyed layer's batch axis: the manifest's (unsealed), else probed on the deployed chunk."""
        if self.keyed is not None:
            return dict(self.keyed.batch_axis)
        names = self.bundle.mode.layer_names
        if not names:
            return {}
        probe = self.controller()
        features = probe.features

        def deployed(b: int) -> None:
            obs = {k: np.zeros((b, *s), np.float32) for k, s in features.items()}
            if probe.instruction is not None or self.protocol.takes_instruction:
                obs["task"] = ["probe"] * b
            x, _ = probe.inputs(obs)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(0)
                self.module.predict_action_chunk(probe.pre(x))

        return probe_batch_axes(self.module, names, deployed, f"the policy in {self.bundle.path}")

    def request(self, controller, behaviour: Behaviour, obs) -> ChunkRequest:
        """A connection's ``obs`` checked (a PropError in one line) and its call's noise seed counted."""
        if not isinstance(obs, Mapping):
            raise PropError(f"an observation is a dict, not {type(obs).__name__}", "send {name: array}")
        x, single = controller.inputs(obs)
        rows = int(next(v for v in x.values() if isinstance(v, torch.Tensor)).shape[0])
        return ChunkRequest(behaviour, x, rows, single, controller.call_noise_seed())

    @torch.inference_mode()
    def run(self, requests: Sequence[ChunkRequest]) -> list[np.ndarray]:
        """Each request's chunk: requests whose frames take one shape (and one instruction) through the
        preprocessor, one forward of the base and the postprocessor together; ``Folded`` ones apart, and
        each no-key request alone unless ``batch_no_key`` (``rows.runs_alone``)."""
        chunks: list[np.ndarray | None] = [None] * len(requests)
        groups: dict[tuple, list[int]] = {}
        for i, r in enumerate(requests):
            if isinstance(r.behaviour, Folded):
                chunks[i] = self._group(r.behaviour.module, [r], keyed=False)[0]
            elif runs_alone(r.behaviour, self.batch_no_key):  # no key: the original's chunk, bit for bit
                chunks[i] = self._group(self.module, [r])[0]
            else:
                groups.setdefault(_shape_key(r.x), []).append(i)
        for idx in groups.values():
            try:
                outs = self._group(self.module, [requests[i] for i in idx])
            except RowMismatch:  # a keyed layer whose rows are not where probed: each request alone
                outs = [self._group(self.module, [requests[i]])[0] for i in idx]
            for i, y in zip(idx, outs):
                chunks[i] = y
        return chunks  # type: ignore[return-value]

    @property
    def steps(self) -> int:
        return int(self.module.config.n_action_steps)

    def _group(self, module, requests: Sequence[ChunkRequest], keyed: bool = True) -> list[np.ndarray]:
        """Requests of one shape: preprocessed together (row-wise: normalisation; the same instruction's
        tokens), one forward, postprocessed together; each request's chunk in action units."""
        batch = dict(self.protocol.pre(_concat([r.x for r in requests])))
        chunk = self._forward(module, requests, batch, keyed)[:, : self.steps]
        b, t = chunk.shape[:2]
        actions = self.protocol.post(chunk.reshape(b * t, -1)).reshape(b, t, -1).numpy()
        out, start = [], 0
        for r in requests:
            part = actions[start : start + r.rows]
            out.append(part[0] if r.single else part)
            start += r.rows
        return out

    def _noise(self, r: ChunkRequest, device: torch.device) -> torch.Tensor:
        """What this request's call draws first alone (``Controller.action_chunk`` seeds the same)."""
        c = self.module.config
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(r.seed)
            return self.module.model.sample_noise((r.rows, c.chunk_size, c.max_action_dim), device)

    def _forward(self, module, requests: Sequence[ChunkRequest], batch: dict, keyed: bool = True):
        """One ``predict_action_chunk`` of ``module`` on every request's rows, each under its behaviour
        (``keyed`` False: ``module`` is a folded copy, run as it is): the raw chunk of all rows."""
        sizes = [r.rows for r in requests]
        device = next(module.parameters()).device
        kwargs = {}
        if self.sampling:
            kwargs["noise"] = torch.cat([self._noise(r, device) for r in requests])
        self.batches += 1
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(requests[0].seed)  # a single request draws as it would alone
            behaviours = [r.behaviour for r in requests]
            if not keyed or all(b is None for b in behaviours):
                chunk = module.predict_action_chunk(batch, **kwargs)
            elif any(isinstance(b, Deltas) for b in behaviours):
                deltas = row_deltas(self.keyed, requests)
                try:
                    chunk = self.keyed.call_rows(deltas, module.predict_action_chunk, batch, **kwargs)
                except RuntimeError as e:  # keyed_model's row mismatch
                    raise RowMismatch() from e
            else:
                handles = payload_handles(module, requests, sum(sizes), self.table, self.axes)
                try:
                    chunk = module.predict_action_chunk(batch, **kwargs)
                finally:
                    for h in handles:
                        h.remove()
        return chunk


def _shape_key(x: dict) -> tuple:
    """What requests share to be preprocessed and run together: each tensor's frame shape and dtype, and
    the instructions (a VLA's tokens are padded to the longest of a batch: only equal texts join)."""
    key = tuple((k, tuple(v.shape[1:]), v.dtype) for k, v in x.items() if isinstance(v, torch.Tensor))
    task = x.get(TASK)
    return key if task is None else (*key, frozenset(task))


def _concat(batches: list[dict]) -> dict:
    """Batches joined along their rows (tensors and per-row lists; the rest the first's)."""
    if len(batches) == 1:
        return dict(batches[0])
    out = {}
    for k, v in batches[0].items():
        if isinstance(v, torch.Tensor):
            out[k] = torch.cat([b[k] for b in batches])
        elif isinstance(v, list):
            out[k] = [item for b in batches for item in b[k]]
        else:
            out[k] = v
    return out


__all__ = ["ChunkRequest", "ChunkRunner", "batchable"]
