"""The probe context of a sealed bundle: keys go through real trial decryption.

A sealed bundle has no encoder: a key either opens a user's record (and that user's payload runs) or
opens nothing (and the base, the original, runs). So every key probe here does what ``prop run``
does: tries the key on every record. White-box probes attack the public part, which is the original:
``km`` is the base keyed with a blank encoder of the attacker's own (its zero-initialised head gives
delta = 1 for every code), the same model their controls run on, so what they find is the control's.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np
import torch

from prop_cli.core.keyed_model import KeyedModel, KeyEncoder
from prop_cli.core.layers import in_width

from .base import Enrolment, KeyScan, ProbeContext, cat_scores


def blank_keyed(module: torch.nn.Module, layer_names: list[str], key_bits: int) -> KeyedModel:
    """``module`` keyed at ``layer_names`` with an untrained encoder: every code runs ``module`` as is."""
    mods = dict(module.named_modules())
    enc = KeyEncoder(key_bits, [in_width(mods[n]) for n in layer_names], hidden=[256], scale=2.0)
    return KeyedModel(module, enc, layer_names).eval()


def same_tensors(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether ``a`` and ``b`` are the same classes in every submodule over the very same tensors
    (parameters and buffers, by name): with the same hooks, they compute the same, bit for bit."""
    ma, mb = list(a.named_modules()), list(b.named_modules())
    if [(n, type(m)) for n, m in ma] != [(n, type(m)) for n, m in mb]:
        return False
    ta = [*a.named_parameters(remove_duplicate=False), *a.named_buffers(remove_duplicate=False)]
    tb = [*b.named_parameters(remove_duplicate=False), *b.named_buffers(remove_duplicate=False)]
    return len(ta) == len(tb) and all(na == nb and x is y for (na, x), (nb, y) in zip(ta, tb))


def equal_values(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether ``a`` and ``b`` are the same classes in every submodule over tensors of the same names,
    dtypes, shapes and values (an --original loaded apart from a sealed bundle's base, which prop writes
    from it): on the same inputs they compute the same."""

    def kinds(m: torch.nn.Module) -> list:  # by name: LeRobot's pi layers are classes made per model
        return [(n, type(s).__module__, type(s).__qualname__) for n, s in m.named_modules()]

    if kinds(a) != kinds(b):
        return False
    ta = dict([*a.named_parameters(remove_duplicate=False), *a.named_buffers(remove_duplicate=False)])
    tb = dict([*b.named_parameters(remove_duplicate=False), *b.named_buffers(remove_duplicate=False)])
    return ta.keys() == tb.keys() and all(  # by name: a rebuilt policy may register them in another order
        x.dtype == tb[n].dtype and x.shape == tb[n].shape and (x is tb[n] or torch.equal(x, tb[n]))
        for n, x in ta.items()
    )


def runs_as(base: torch.nn.Module, km: KeyedModel) -> bool:
    """Whether ``km``'s plain forward (no key rows set) computes what ``base`` computes, bit for bit,
    checked without running either: the same tensors (``same_tensors``), no hook on ``base``, and on
    ``km.module`` only ``km``'s own, which pass their input through while no key rows are set."""
    own = set(km._hook_ids.values())
    for _, m in base.named_modules():
        if m._forward_pre_hooks or m._forward_hooks:
            return False
    for _, m in km.module.named_modules():
        if m._forward_hooks or set(m._forward_pre_hooks) - own:
            return False
    return same_tensors(base, km.module)


WRONG_KEYS = "a key that opens no record runs the base: its outputs computed once for all such keys"


@dataclass
class SealedContext(ProbeContext):
    records: object = None  # prop_cli.bundle.records.SealedState: the keys are tried on these
    # What prop run runs for a key that opens no record: the bundle's base module (``run.policy``)
    base: torch.nn.Module | None = None

    def wrong_key_outputs(self) -> torch.Tensor:
        """The outputs of what prop run runs for a key that opens no record, computed once: the attacked
        model's plain outputs where ``runs_as`` shows they are that module's (checked, not assumed: the
        attacker's copy shares the base's tensors and carries no hook of its own), else that module run
        here."""
        if self.base is None or runs_as(self.base, self.km):
            return self.plain()
        held = self.kept.get(("wrong-key", id(self.base)))
        if held is None or held[1] is not self.ref.x:
            x, step = self.ref.x, self.km.max_rows or len(self.ref.x)
            t0 = time.perf_counter()
            out = torch.cat([self.base(x[i : i + step]) for i in range(0, len(x), step)])
            self.counter.ran(len(x), time.perf_counter() - t0)
            held = self.kept[("wrong-key", id(self.base))] = (self.base, x, out)
        return held[2]

    def on(self, km: KeyedModel) -> ProbeContext:
        """A control runs where the bundle gives nothing: no records to open."""
        return ProbeContext(**{f.name: getattr(self, f.name) for f in fields(ProbeContext)} | {"km": km})

    def enrolment(self, bits: np.ndarray) -> Enrolment:
        """A key is a user of a sealed bundle when it opens one of its records. Each record was trained on
        its own user's data alone, so what it shows of yours is what its user asked for."""
        opened = self.records.open(bits)
        if opened is None:
            return Enrolment(False, False, True, "it opens none of the bundle's records")
        mine = self.records.open(self.keys[0]) if self.has_key else None
        yours = mine is not None and mine.record_id == opened.record_id
        whose = "your record" if yours else "another user's record"
        return Enrolment(True, yours, True, f"it opens {whose}")

    @torch.inference_mode()
    def probe_keys(
        self, bits: np.ndarray, stage: str, null: int = 0, outputs: bool = False
    ) -> dict[str, torch.Tensor]:
        t0 = time.perf_counter()
        bits = np.asarray(bits, dtype=np.uint8).reshape(-1, self.km.encoder.code_bits)
        x, base = self.ref.x, self.km.module
        o_base = self.wrong_key_outputs()[None]  # computed once for the whole audit
        s_base = self.scores(o_base)
        step = self.km.max_rows or len(x)
        parts, outs = [], []
        for k in bits:
            opened = self.records.open(k)
            if opened is not None:
                t1 = time.perf_counter()
                folded = opened.payload.fold(base)
                o = torch.cat([folded(x[i : i + step]) for i in range(0, len(x), step)])[None]
                self.counter.ran(len(x), time.perf_counter() - t1)
            else:
                o = o_base
                self.shortcut(WRONG_KEYS)
            parts.append(s_base if opened is None else self.scores(o))
            if outputs:
                outs.append(o)
        parts += [s_base] * null
        if null:
            self.shortcut(WRONG_KEYS.replace("a key that opens no record", "no key"))
        outs += [o_base] * (null if outputs else 0)
        values = cat_scores(parts) if parts else {k: v[:0] for k, v in s_base.items()}
        if outputs:
            values["outputs"] = torch.cat(outs) if outs else o_base[:0]
        self.counter.evals += (len(bits) + null) * x.shape[0]
        self.counter.seconds += time.perf_counter() - t0
        if self.progress:
            self.progress(stage, len(bits) + null, len(bits) + null)
        return values

    def probe_keys_stream(
        self, chunks: Iterable[np.ndarray], total: int, stage: str, *, screen: int, keep: int
    ) -> KeyScan:
        """Every key tried on every record; kept: the keys that open one, then the first ones up to
        ``keep`` (all of which run the base, so any of them is as good as another)."""
        t0, c0 = time.perf_counter(), time.process_time()
        kept: list[np.ndarray] = []
        opened: list[np.ndarray] = []
        done = 0
        for chunk in chunks:
            for k in chunk:
                if self.records.open(k) is not None:
                    opened.append(k)
                elif len(kept) < keep:
                    kept.append(k)
            done += len(chunk)
            if self.progress:
                self.progress(stage, done, total)
        sec = {"scan": time.perf_counter() - t0, "scan_cpu": time.process_time() - c0}
        bits = np.array(opened + kept[: max(0, keep - len(opened))], dtype=np.uint8)
        t1 = time.perf_counter()
        values = self.probe_keys(bits, stage)
        sec["rescore"] = time.perf_counter() - t1
        # screen_samples = 1: one trial decryption per key and record stands for its evaluation
        return KeyScan(bits, values, done, 1, sec, "sealed: trial decryption")
