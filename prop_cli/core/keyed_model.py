"""The keyed model (paper Eq. 5): ``z -> W diag(delta) z + b`` at chosen linear layers, and at
convolutions with one delta per input channel (``prop_cli.core.layers``).

The key transform is attached with forward pre-hooks, so the module tree and its state-dict names are
exactly the loaded checkpoint's. With no key the hooks do nothing: the model *is* the loaded module.

Many (sample, key) rows go through one forward. ``sample_index`` picks, for every row, which input
sample it uses; the first keyed layer gathers its input by that index, so everything before it runs
once per distinct sample instead of once per row.
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from prop_cli.constants import KEY_ENCODINGS
from prop_cli.errors import PropError

from .layers import is_conv, scale_inputs

# Domain separation for the hashed key code; changing it changes every trained bundle's meaning.
_CODE_DOMAIN = b"prop/key-code/v1"


def key_codes(bits: np.ndarray, encoding: str) -> torch.Tensor:
    """Key bits (n,) or (K, n) of 0/1 -> the encoder's input, ±1 float32 of shape (K, n).

    ``raw`` feeds the bits as ±1, as in the paper. ``hashed`` (default) first expands them through
    SHAKE-256: a key one bit off then gives an unrelated code, so Hamming neighbours of the user's
    key are, to the encoder, as far away as random keys.
    """
    bits = np.atleast_2d(np.asarray(bits, dtype=np.uint8))
    n = bits.shape[1]
    if encoding == "raw":
        out = bits
    elif encoding == "hashed":
        # One digest per key, joined and unpacked at once: the audit's key scan hashes millions.
        # Copies of one hash already fed the domain: a fresh shake_256 per key cost a third more.
        packed = np.packbits(bits, axis=1).tobytes()
        w = n // 8
        blob = b"".join([_keyed_digest(packed[i : i + w], w) for i in range(0, len(packed), w)])
        out = np.unpackbits(np.frombuffer(blob, dtype=np.uint8).reshape(len(bits), n // 8), axis=1)
    else:
        raise PropError(f"unknown key encoding {encoding!r}", f"use one of {', '.join(KEY_ENCODINGS)}")
    return torch.from_numpy(out).float().mul_(2.0).sub_(1.0)


_CODE_HASH = hashlib.shake_256(_CODE_DOMAIN)


def _keyed_digest(row: bytes, size: int) -> bytes:
    h = _CODE_HASH.copy()
    h.update(row)
    return h.digest(size)


class KeyEncoder(nn.Module):
    """MLP from a ±1 key code to one scale vector per keyed layer: ``delta = 1 + scale * tanh(.)``.

    The last layer starts at zero, so before training every key gives delta = 1 (base behaviour).
    ``scale`` > 1 lets delta change sign, which a hidden feature needs to flip its contribution.
    """

    def __init__(self, code_bits: int, features: list[int], hidden: list[int], scale: float) -> None:
        super().__init__()
        self.code_bits = code_bits
        self.features = list(features)
        self.scale = float(scale)
        dims = [code_bits, *hidden]
        layers: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(a, b), nn.Tanh()]
        last = nn.Linear(dims[-1], sum(features))
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*layers, last)

    def forward(self, codes: torch.Tensor) -> list[torch.Tensor]:
        return list(self.joined(codes).split(self.features, dim=1))

    def joined(self, codes: torch.Tensor) -> torch.Tensor:
        """Every layer's delta side by side, (K, sum(features)): what ``forward`` splits."""
        return 1.0 + self.scale * torch.tanh(self.net(codes))

    def blank(self) -> bool:
        """Whether every code gives delta = 1 exactly: the head (last layer) is all zero and every weight
        before it finite, so the head's output is 0 for any finite code (a fresh encoder; the attacker's
        blank one over a sealed bundle's base)."""
        last = self.net[-1]
        with torch.no_grad():
            return not (last.weight.any() or last.bias.any()) and all(
                bool(p.isfinite().all()) for p in self.net[:-1].parameters()
            )

    def latent(self, codes: torch.Tensor) -> torch.Tensor:
        """All layers' delta concatenated, (K, sum(features))."""
        return torch.cat(self(codes), dim=1)


class JoinedDeltas(list):
    """Per-layer deltas (a list, as everywhere) that are column blocks of one (K, sum(features)) tensor,
    ``joined``: ``KeyedModel.run_rows`` then picks every layer's rows with one gather instead of one per
    layer (the 38k MLP's step: docs/speed.md, "The small-model step"). The blocks are ``split`` views
    of ``joined``, so gradients through either reach the encoder."""

    def __init__(self, joined: torch.Tensor, features: list[int]) -> None:
        super().__init__(joined.split(features, dim=1))
        self.joined = joined
        self.features = list(features)


# (key, sample) rows per forward when evaluating many keys: activations stay in cache (best on the IL MLP).
KEY_ROWS = 4096
# Rows per forward when keys cannot share a prefix and run as batch copies. ACT on one CPU thread, vs
# one forward per key: 3.7x at 8 samples, 1.6x at 32, 1.07x at 120 (all keys in one forward of 3840
# rows was 0.73x: big forwards lose).
COPY_ROWS = 512


def keys_per_forward(samples: int) -> int:
    return max(1, KEY_ROWS // max(1, samples))


@dataclass
class _Rows:
    """What the hooks apply during one forward.

    rows mode: ``deltas`` (N, d) per layer, one per (sample, key) row; the first keyed layer gathers its
    input by ``sample_index``. grid mode: ``deltas`` (K, d) and every key on every sample; the first
    keyed layer broadcasts (B, d) -> (K*B, d) in one multiply, later ones multiply a (K, B, d) view.
    """

    deltas: list[torch.Tensor]
    sample_index: torch.Tensor | None
    grid: bool = False
    gathered: bool = False
    samples: int = 0


class KeyedModel(nn.Module):
    """A loaded module plus a key encoder, joined by pre-hooks on the keyed linear layers."""

    def __init__(self, module: nn.Module, encoder: KeyEncoder, layer_names: list[str]) -> None:
        super().__init__()
        self.module = module
        self.encoder = encoder
        self.layer_names = list(layer_names)
        mods = dict(module.named_modules())
        self._rows: _Rows | None = None
        # None = not probed yet; see _probe_modes.
        self.share_prefix: bool | None = None
        # Axis of the batch in each keyed layer's input (name -> axis; absent = 0). Sequence-first
        # layers (nn.Transformer* without batch_first, as in LeRobot's ACT) take (S, B, D): see
        # prop_cli.core.batch_axes, which finds them by probing.
        self.batch_axis: dict[str, int] = {}
        # None = not probed yet: may K keys run as K copies of the batch in one forward (rows independent)?
        self.rows_independent: bool | None = None
        # At most this many (key, sample) rows per forward of ``run_keys`` (None: as many as its modes
        # take): a large policy's row is a whole sampler run (the audit sets it by the model's size).
        self.max_rows: int | None = None
        self._hooks = {
            name: mods[name].register_forward_pre_hook(self._make_hook(i))
            for i, name in enumerate(self.layer_names)
        }
        self._hook_ids = {name: h.id for name, h in self._hooks.items()}

    def on(self, module: nn.Module) -> KeyedModel:
        """This encoder and these keyed layers (names, batch axes) over another module that has them."""
        other = KeyedModel(module, self.encoder, self.layer_names)
        other.batch_axis = dict(self.batch_axis)
        return other

    def remove_hooks(self) -> None:
        """Detach this model from its layers (another KeyedModel takes them over, e.g. a flat view)."""
        for h in self._hooks.values():
            h.remove()

    def _make_hook(self, i: int):
        name = self.layer_names[i]
        conv = is_conv(dict(self.module.named_modules())[name])

        def pre(mod: nn.Module, args: tuple):
            rows = self._rows
            if rows is None:
                return None
            z = args[0]
            if conv:
                return (self._channels(rows, i, z), *args[1:])
            axis = self.batch_axis.get(name, 0)
            if axis:
                if rows.grid or rows.sample_index is not None:  # sharing assumes the batch on axis 0
                    raise _RowMismatch()
                return (z * self._along(rows.deltas[i], z, axis), *args[1:])
            if rows.grid:
                return (self._grid(rows, i, z), *args[1:])
            if rows.sample_index is not None and not rows.gathered:
                z = z.index_select(0, rows.sample_index)
                rows.gathered = True
            d = rows.deltas[i]
            if z.shape[0] != d.shape[0] and d.shape[0] != 1:
                raise _RowMismatch()
            if z.dim() > 2:
                d = d.view(d.shape[0], *([1] * (z.dim() - 2)), d.shape[1])
            return (z * d, *args[1:])

        return pre

    @staticmethod
    def _channels(rows: _Rows, i: int, z: torch.Tensor) -> torch.Tensor:
        """A convolution's input (B, C, *spatial): each row's channels scaled by that row's delta, in the
        same three modes as a linear layer's features (rows, grid first / later layer)."""
        d = rows.deltas[i]
        spatial = [1] * (z.dim() - 2)
        if rows.grid:
            k = d.shape[0]
            view = d.view(k, 1, d.shape[1], *spatial)
            if not rows.gathered:
                rows.gathered, rows.samples = True, z.shape[0]
                return (z.unsqueeze(0) * view).reshape(k * z.shape[0], *z.shape[1:])
            b = rows.samples
            if z.shape[0] != k * b:
                raise _RowMismatch()
            return (z.view(k, b, *z.shape[1:]) * view).reshape(k * b, *z.shape[1:])
        if rows.sample_index is not None and not rows.gathered:
            z = z.index_select(0, rows.sample_index)
            rows.gathered = True
        if z.shape[0] != d.shape[0] and d.shape[0] != 1:
            raise _RowMismatch()
        return z * d.view(d.shape[0], d.shape[1], *spatial)

    @staticmethod
    def _along(d: torch.Tensor, z: torch.Tensor, axis: int) -> torch.Tensor:
        """(R, d) deltas shaped to scale z along its batch ``axis``; one row broadcasts over the batch."""
        if d.shape[0] not in (1, z.shape[axis]):
            raise _RowMismatch()
        shape = [1] * z.dim()
        shape[axis], shape[-1] = d.shape[0], d.shape[1]
        return d.view(shape)

    def call_rows(self, deltas: list[torch.Tensor], fn, *args, **kwargs):
        """``fn(*args, **kwargs)`` with row r of every keyed layer's input scaled by ``deltas[l][r]``.

        For modules that take more than one tensor (dict batches) or bring their own loss: no sample
        sharing, one delta row per batch row (or a single row for the whole batch).
        """
        self._rows = _Rows(deltas, None)
        try:
            return fn(*args, **kwargs)
        finally:
            self._rows = None

    @staticmethod
    def _grid(rows: _Rows, i: int, z: torch.Tensor) -> torch.Tensor:
        d = rows.deltas[i]
        k = d.shape[0]
        shape = (k, 1, *([1] * (z.dim() - 2)), d.shape[1])
        if not rows.gathered:
            rows.gathered, rows.samples = True, z.shape[0]
            return (z.unsqueeze(0) * d.view(shape)).reshape(k * z.shape[0], *z.shape[1:])
        b = rows.samples
        if z.shape[0] != k * b:
            raise _RowMismatch()
        return (z.view(k, b, *z.shape[1:]) * d.view(shape)).reshape(k * b, *z.shape[1:])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """No key: exactly the loaded module."""
        return self.module(x)

    def layer_deltas(self, codes: torch.Tensor | None, null: int = 0) -> list[torch.Tensor]:
        """delta per layer for K codes, then ``null`` rows of ones (the null key, delta = 1)."""
        if codes is None or len(codes) == 0:
            return [torch.ones(null, f, device=self._device()) for f in self.encoder.features]
        if null and type(self.encoder) is KeyEncoder:
            # One tensor for all layers, the null rows appended once (the same values as below).
            joined = self.encoder.joined(codes)
            joined = torch.cat([joined, joined.new_ones(null, joined.shape[1])])
            return JoinedDeltas(joined, self.encoder.features)
        parts = self.encoder(codes)
        if null:
            return [torch.cat([p, p.new_ones(null, p.shape[1])]) for p in parts]
        return parts

    def _device(self) -> torch.device:
        return next(self.encoder.parameters()).device

    def run_rows(
        self,
        x: torch.Tensor,
        deltas: list[torch.Tensor],
        key_index: torch.Tensor,
        sample_index: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Output for rows (sample_index[r], key_index[r]); key_index picks a row of each delta."""
        if isinstance(deltas, JoinedDeltas):
            row_deltas = list(deltas.joined.index_select(0, key_index).split(deltas.features, dim=1))
        else:
            row_deltas = [d.index_select(0, key_index) for d in deltas]
        if sample_index is not None and not self._sharing_ok(x, deltas):
            x, sample_index = x.index_select(0, sample_index), None
        self._rows = _Rows(row_deltas, sample_index)
        try:
            out = self.module(x)
        finally:
            self._rows = None
        return out

    def run_keys(self, x: torch.Tensor, deltas: list[torch.Tensor]) -> torch.Tensor:
        """Every key (row of deltas) on every sample, one forward: output of shape (K, B, ...); within
        ``max_rows`` rows per forward, in pieces of keys and samples."""
        k, b = deltas[0].shape[0], x.shape[0]
        if self.max_rows is not None and k * b > self.max_rows:
            per_s = min(b, self.max_rows)
            per_k = max(1, self.max_rows // per_s)
            limit, self.max_rows = self.max_rows, None
            try:
                return torch.cat([
                    torch.cat([self.run_keys(x[j : j + per_s], [d[i : i + per_k] for d in deltas])
                               for j in range(0, b, per_s)], dim=1)
                    for i in range(0, k, per_k)
                ])  # fmt: skip
            finally:
                self.max_rows = limit
        if self._sharing_ok(x, deltas):
            self._rows = _Rows(deltas, None, grid=True)
            try:
                out = self.module(x)
            finally:
                self._rows = None
        elif k > 1 and b < COPY_ROWS and self._rows_ok(x, deltas):
            # No shared prefix (e.g. residual sums before the first keyed layer), but rows are independent:
            # small batches run as copies, several keys per forward (see COPY_ROWS).
            per = max(1, COPY_ROWS // b)
            out = torch.cat([self._run_copies(x, [d[i : i + per] for d in deltas]) for i in range(0, k, per)])
        else:
            # Rows interact after the first keyed layer: run each key on its own batch, as a user would.
            zeros = torch.zeros(b, dtype=torch.long, device=x.device)
            out = torch.cat([self.run_rows(x, [d[i : i + 1] for d in deltas], zeros) for i in range(k)])
        return out.view(k, b, *out.shape[1:])

    def _run_copies(self, x: torch.Tensor, deltas: list[torch.Tensor]) -> torch.Tensor:
        k, b = deltas[0].shape[0], x.shape[0]
        copies = x.repeat(k, *([1] * (x.dim() - 1)))
        return self.run_rows(copies, deltas, torch.arange(k, device=x.device).repeat_interleave(b))

    def _rows_ok(self, x: torch.Tensor, deltas: list[torch.Tensor]) -> bool:
        self._sharing_ok(x, deltas)
        return bool(self.rows_independent)

    def _sharing_ok(self, x: torch.Tensor, deltas: list[torch.Tensor]) -> bool:
        # Gathering or broadcasting at the first keyed layer is only valid if everything after it treats
        # rows independently; running keys as batch copies only if rows do not mix. Checked once, on two
        # samples x two keys, against one forward per key (one key needs neither: not decided then).
        if self.share_prefix is None:
            if deltas[0].shape[0] < 2:
                return False
            self.share_prefix, self.rows_independent = self._probe_modes(x[:2], [d[:2] for d in deltas])
        return self.share_prefix

    @torch.no_grad()
    def _probe_modes(self, x: torch.Tensor, deltas: list[torch.Tensor]) -> tuple[bool, bool]:
        """(prefix sharing gives one forward per key's outputs, batch copies give them)."""
        k, b = deltas[0].shape[0], x.shape[0]
        key_index = torch.arange(k, device=x.device).repeat_interleave(b)
        sample_index = torch.arange(b, device=x.device).repeat(k)
        row_deltas = [d.index_select(0, key_index) for d in deltas]

        def with_rows(rows: _Rows) -> torch.Tensor:
            self._rows = rows
            return self.module(x)

        def agrees(run) -> bool:
            try:
                got = run()
            except (_RowMismatch, RuntimeError):
                return False
            finally:
                self._rows = None
            return got.shape == ref.shape and torch.allclose(got, ref, atol=1e-5, rtol=1e-4)

        was_training = self.module.training
        self.module.eval()
        try:
            # the truth: each key on its own batch, as a user would run it
            ref = torch.cat(
                [with_rows(_Rows([d[i : i + 1].expand(b, -1) for d in deltas], None)) for i in range(k)]
            )
            share = agrees(lambda: with_rows(_Rows(row_deltas, sample_index))) and agrees(
                lambda: with_rows(_Rows(deltas, None, grid=True))
            )
            copies = agrees(lambda: self._run_copies(x, deltas))
        except (_RowMismatch, RuntimeError):
            share = copies = False
        finally:
            self._rows = None
            self.module.train(was_training)
        return bool(share), bool(copies)

    @torch.no_grad()
    def fold(self, codes: torch.Tensor, module: nn.Module | None = None) -> nn.Module:
        """A copy of the module (or of ``module``, which has the keyed layers by the same names) with one
        key's delta folded into the weights, in memory only.

        A keyed call then costs what a base call costs. Never write the result to disk: it is the
        personalized policy in the clear.
        """
        folded = copy.deepcopy(self.module if module is None else module)
        mods = dict(folded.named_modules())
        for name, d in zip(self.layer_names, self.layer_deltas(codes[:1])):
            # The copy carries our hooks along; drop them so it is a plain module.
            mods[name]._forward_pre_hooks.pop(self._hook_ids[name], None)
            w = mods[name].weight
            w.mul_(scale_inputs(w, d[0].to(w.dtype)))
        return folded


@torch.no_grad()
def outputs_for_codes(km: KeyedModel, x: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """Outputs of every code on every sample, (K, B, ...), in chunks of keys."""
    per = keys_per_forward(x.shape[0])
    outs = [
        km.run_keys(x, km.layer_deltas(codes[i : i + per].to(x.device))) for i in range(0, len(codes), per)
    ]
    return torch.cat(outs)


class _RowMismatch(RuntimeError):
    """A keyed layer saw a batch that is not one row per (sample, key): sharing is not possible."""
