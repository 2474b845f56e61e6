"""The probe contract: one attack on a bundle, what it returns, and what every probe shares.

A probe is a :class:`Probe` entry in the registry (``prop_cli.attack.probes.PROBES``): its ``run`` scores
keys, codes or deltas against the reference and returns :class:`Group` s, one table row each. Its
optional ``control`` runs the same attack where the bundle gives nothing (e.g. on the original
checkpoint); the report then shows leakage beyond the control. Threat names: docs/threat-model.md.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F

from prop_cli.config import AuditSettings
from prop_cli.core import metrics
from prop_cli.core.key_sampling import random_keys
from prop_cli.core.keyed_model import KeyedModel, key_codes, keys_per_forward

from .screen import ChainKeys, KeyScan, chain_keys, scan_keys

THREATS = ("T0", "T1", "T2", "T3", "structure", "cross-user")
# key: concrete keys or codes anyone can run, scored on leakage; search: what an optimiser reaches,
# scored on bounded leakage (metrics.bounded_leakage). Both are gated on what lies beyond their control.
KINDS = ("key", "search")

Progress = Callable[[str, int, int], None]  # (stage, done, total)


@dataclass
class Reference:
    """What the audit compares against: inputs, the reference output b and the owner's targets p."""

    x: torch.Tensor
    b: torch.Tensor  # the original's output (or the bundle's without a key)
    p: torch.Tensor | None  # the owner's targets; None in a no-key audit
    task: str


@dataclass
class Group:
    """One row of the report: per-key scores of one set of probed keys, codes or deltas."""

    name: str
    values: dict[str, torch.Tensor]  # per key: fidelity, divergence, and leakage when targets exist
    is_key: bool  # false for codes or deltas that no known key gives
    distance: int | None = None  # Hamming rows
    search: dict | None = None  # searches: {"restarts", "steps", and any extra per-restart lists}
    bits: np.ndarray | None = None  # the probed keys, where a control re-runs exactly these
    codes: torch.Tensor | None = None  # the probed codes (a search's rounding), for the same reason
    kind: str | None = None  # None: the probe's kind; "key" for the concrete codes a search rounds to
    threat: str | None = None  # None: the probe's threat
    note: str | None = None  # one line for the report's warnings (e.g. a key that is not a user's)
    extra: dict | None = None  # more fields for the report's row (e.g. a key's enrolment)
    model: str | None = None  # a control's group: what it ran on, where not the usual control model


@dataclass(frozen=True)
class Enrolment:
    """Whether another key is a user of the bundle (only users get a cross-user row), and how that
    user's behaviour relates to the audited user's."""

    user: bool  # the key runs an enrolled user's behaviour
    yours: bool  # ... the audited user's own (the same record, or the same key)
    independent: bool  # that user's behaviour was trained without the audited user's data (sealed)
    how: str  # one line: how this was told


# Random keys an unsealed bundle's other key is compared with: a user's key moves the outputs further
# from the reference than any of them (the fallback trains random keys towards the reference).
ENROLMENT_KEYS = 256


@dataclass
class Counter:
    """Key x sample evaluations and their wall time, for the report's speed figures."""

    evals: int = 0
    seconds: float = 0.0
    # (key, sample) rows the model actually ran, and their wall time: the speed ``affordable`` plans by
    model_rows: int = 0
    model_seconds: float = 0.0

    def ran(self, rows: int, seconds: float) -> None:
        self.model_rows += rows
        self.model_seconds += seconds


@dataclass
class ProbeContext:
    """Everything a probe may use. ``km`` is the model under attack (the bundle, or the original for a
    control); ``original`` is the original checkpoint keyed the same way, or None if not available."""

    km: KeyedModel
    ref: Reference
    settings: AuditSettings
    keys: list[np.ndarray]  # [the audited user's key, other users' keys...]; [] without a key
    encoding: str
    original: KeyedModel | None = None
    # The reference model keyed with a fresh, untrained encoder (zero head: delta = 1 for every key):
    # what the same keys give where no user was enrolled. The key rows' control.
    unenrolled: KeyedModel | None = None
    progress: Progress | None = None
    counter: Counter = field(default_factory=Counter)
    probe: str = ""  # the running probe's name: seeds its random streams
    shots: Reference | None = None  # labelled owner's rows outside the audit sample (few-shot attacks)
    seed_hint: int | None = None  # the training seed the manifest records, if any (what an attacker reads)
    users: int = 1  # users the manifest lists
    # time.perf_counter() after which probes stop early (--budget; None: no limit), and what the
    # budget cut short; shared by every copy of the context (``replace`` keeps the same objects).
    deadline: float | None = None
    cut: list[str] = field(default_factory=list)
    kept: dict = field(default_factory=dict)  # outputs computed once (the plain model's, per model)
    notes: list[str] = field(default_factory=list)  # lines for the report's warnings (shared, like cut)
    # The attacked model is the searches' control model (a sealed bundle's base, keyed at the same layers
    # and range): a search and its control are one computation, so one run serves both, cut short or not.
    shared_searches: bool = False
    # (probe, line): the work a probe did not repeat because its answer was known, said in its rows
    # (shared, like notes).
    shortcuts: list[tuple[str, str]] = field(default_factory=list)

    def affordable(self, rows: int, stage: str, passes: float = 3.0) -> bool:
        """Whether ``rows`` (key, sample) rows, each ``passes`` forwards' cost (3: a forward and its
        backward), end before the budget's deadline at the speed the model has run at so far; if not,
        ``stage`` is recorded as cut short. A search step cannot stop half-way: a large policy's first
        step alone can outlast any budget."""
        if self.deadline is None:
            return True
        c = self.counter
        need = passes * rows * c.model_seconds / c.model_rows if c.model_rows else 0.0
        if time.perf_counter() + need <= self.deadline:
            return True
        if stage not in self.cut:
            self.cut.append(stage)
        return False

    def keys_per_chunk(self) -> int:
        """Keys scored per chunk on every sample: within the model's ``max_rows`` where it has one, so
        the budget is checked between chunks of a few forwards."""
        n = self.ref.x.shape[0]
        per = keys_per_forward(n)
        return per if self.km.max_rows is None else max(1, min(per, self.km.max_rows // n))

    def out_of_time(self, stage: str | None = None) -> bool:
        """Past the budget's deadline; ``stage`` is recorded as cut short when it is."""
        late = self.deadline is not None and time.perf_counter() > self.deadline
        if late and stage and stage not in self.cut:
            self.cut.append(stage)
        return late

    def plain(self, km: KeyedModel | None = None) -> torch.Tensor:
        """``km``'s module (default: the attacked one) on the reference inputs, computed once, within
        its ``max_rows`` rows per forward: what any key whose deltas are all 1 gives."""
        km = km or self.km
        x = self.ref.x
        held = self.kept.get(id(km.module))
        if held is None or held[1] is not x:
            step = km.max_rows or len(x)
            t0 = time.perf_counter()
            with torch.inference_mode():
                out = torch.cat([km.module(x[i : i + step]) for i in range(0, len(x), step)])
            self.counter.ran(len(x), time.perf_counter() - t0)
            held = self.kept[id(km.module)] = (km.module, x, out)  # the module held: its id stays its own
        return held[2]

    def chain(self) -> ChainKeys | None:
        """The attacked model's exact fp32 chain on the reference inputs (``screen.ChainKeys``), built
        once per model, inputs and weights before the first keyed layer; None where the model is not a
        chain MLP or runs within ``max_rows``."""
        km, x = self.km, self.ref.x
        if km.max_rows is not None:
            return None
        versions = tuple(p._version for p in km.module.parameters())
        key = ("chain", id(km.module), id(x))
        held = self.kept.get(key)
        if held is None or held[2] != versions:
            held = self.kept[key] = (km.module, x, versions, chain_keys(km, x))  # held: ids stay theirs
        return held[3]

    def shortcut(self, line: str) -> None:
        """Say in the running probe's rows that ``line``'s work was done once, not repeated."""
        if (self.probe, line) not in self.shortcuts:
            self.shortcuts.append((self.probe, line))

    @property
    def has_key(self) -> bool:
        return bool(self.keys)

    def rng(self) -> np.random.Generator:
        """This probe's own numpy stream: its keys do not depend on which other probes run."""
        return np.random.default_rng([self.settings.seed, zlib.crc32(self.probe.encode())])

    def generator(self) -> torch.Generator:
        return torch.Generator().manual_seed(self.settings.seed * 1_000_003 + zlib.crc32(self.probe.encode()))

    def on(self, km: KeyedModel) -> ProbeContext:
        """The same context on another model (a control)."""
        return replace(self, km=km)

    def codes(self, bits: np.ndarray) -> torch.Tensor:
        return key_codes(bits, self.encoding).to(self.ref.x.device)

    def scores(self, o: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per key: fidelity, leakage (with targets) and divergence (the attacker's criterion)."""
        ref = self.ref
        fid = metrics.fidelity(o, ref.b, ref.task)
        out = {
            "fidelity": fid,
            # What the attacker picks restarts by: 1 - agreement (classification), mse (regression).
            "divergence": 1.0 - fid if ref.task == "classification" else fid,
        }
        if ref.p is not None:
            out["leakage"] = metrics.leakage(o, ref.p, ref.b, ref.task)
            out["bounded"] = metrics.bounded_leakage(o, ref.p, ref.b, ref.task)
        return out

    def enrolment(self, bits: np.ndarray) -> Enrolment:
        """Is ``bits`` a user of this (unsealed) bundle? Users share one encoder, so a user's key is told
        by its behaviour: with more than one user in the manifest, a key whose outputs move further from
        the reference than every one of ``ENROLMENT_KEYS`` random keys (seeded) is a user's."""
        if self.has_key and np.array_equal(bits, self.keys[0]):
            return Enrolment(True, True, False, "it is your own key")
        if self.users < 2:
            return Enrolment(False, False, False, "the manifest lists one user")
        rng = np.random.default_rng([self.settings.seed, zlib.crc32(b"enrolment")])
        others = random_keys(ENROLMENT_KEYS, self.km.encoder.code_bits, rng, exclude=self.keys[:1] or None)
        floor = float(self.probe_keys(others, "enrolment")["divergence"].max())
        div = float(self.probe_keys(bits, "enrolment")["divergence"][0])
        user = div > floor
        where = "beyond" if user else "within"
        floor_ = f"the {floor:.3g} of {ENROLMENT_KEYS} random keys"
        how = f"its outputs move {div:.3g} from the reference, {where} {floor_}"
        return Enrolment(user, False, False, how)

    def key_deltas(self, bits: np.ndarray, null: int = 0, low_precision: bool = False) -> list[torch.Tensor]:
        """Each key's delta per keyed layer, then ``null`` rows of no key (delta = 1).

        The one place where a key becomes behaviour: ``probe_keys`` and ``probe_keys_stream`` both
        come through here, so a bundle that maps keys differently (sealed: trial decryption) replaces
        this method and every key probe follows. ``low_precision``: the caller only screens (bf16 is
        enough); exact scores come later.
        """
        bits = np.asarray(bits, dtype=np.uint8).reshape(-1, self.km.encoder.code_bits)
        codes = self.codes(bits) if len(bits) else None
        if low_precision and codes is not None and codes.device.type == "cpu":
            with torch.autocast("cpu", dtype=torch.bfloat16):
                return self.km.layer_deltas(codes, null)
        return self.km.layer_deltas(codes, null)

    @torch.inference_mode()
    def probe_keys(
        self, bits: np.ndarray, stage: str, null: int = 0, outputs: bool = False
    ) -> dict[str, torch.Tensor]:
        """Score keys (K, key_bits) of 0/1, then ``null`` no-key rows, on every sample (``outputs``:
        the model's outputs (K, B, ...) too, under "outputs").

        Every key-based probe (null, random, hamming, cross-user, the user's own key, the black-box
        scan's re-score) goes through here; white-box probes read ``km`` and use ``probe_codes``.
        """
        bits = np.asarray(bits, dtype=np.uint8).reshape(-1, self.km.encoder.code_bits)
        per = self.keys_per_chunk()
        rows = len(bits) + null
        if self.km.encoder.blank():
            return self._blank(rows, stage, outputs)
        return self._probe(
            rows,
            lambda i, j: self.key_deltas(bits[i : min(j, len(bits))], max(0, j - max(i, len(bits)))),
            per,
            stage,
            outputs,
        )

    @torch.inference_mode()
    def probe_codes(self, codes: torch.Tensor, stage: str) -> dict[str, torch.Tensor]:
        """Score every encoder code (K, n) on every sample, all codes of a chunk in one forward."""
        per = self.keys_per_chunk()
        if self.km.encoder.blank() and bool(codes.isfinite().all()):
            return self._blank(len(codes), stage)
        return self._probe(
            len(codes), lambda i, j: self.km.layer_deltas(codes[i:j].to(self.ref.x.device)), per, stage
        )

    def _blank(self, rows: int, stage: str, outputs: bool = False) -> dict[str, torch.Tensor]:
        """``rows`` keys or codes through an encoder whose head is zero (``KeyEncoder.blank``): each one's
        delta is 1 exactly, so each runs the plain model; its outputs (computed once) scored once."""
        t0 = time.perf_counter()
        base = self.plain()
        one = self.scores(base[None])
        values = {k: v.detach().cpu().expand(rows, *v.shape[1:]).clone() for k, v in one.items()}
        if outputs:
            values["outputs"] = base.expand(rows, *base.shape)
        self.shortcut(
            "every key's delta is 1 (the encoder's head is zero): the plain model, its outputs computed once"
        )
        self.counter.evals += rows * self.ref.x.shape[0]
        self.counter.seconds += time.perf_counter() - t0
        if self.progress:
            self.progress(stage, rows, rows)
        return values

    def _probe(
        self, rows: int, deltas_of: Callable, per: int, stage: str, outputs: bool = False
    ) -> dict[str, torch.Tensor]:
        t0 = time.perf_counter()
        x = self.ref.x
        parts, done = [], 0
        for i in range(0, rows, per):
            if parts and self.out_of_time(stage):  # the budget: what ran so far is the group
                break
            deltas = deltas_of(i, min(i + per, rows))
            if all(bool((d == 1).all()) for d in deltas):  # delta 1 everywhere: the plain model, exactly
                base = self.plain()
                o = base.expand(len(deltas[0]), *base.shape)
            else:
                t1 = time.perf_counter()
                fast = self.chain()
                o = fast(deltas) if fast is not None else self.km.run_keys(x, deltas)
                self.counter.ran(len(deltas[0]) * len(x), time.perf_counter() - t1)
                if outputs and fast is not None:
                    o = o.clone()  # the chain's buffer: the next chunk overwrites it
            parts.append({**self.scores(o), **({"outputs": o} if outputs else {})})
            done = min(i + per, rows)
            if self.progress:
                self.progress(stage, done, rows)
        self.counter.evals += done * x.shape[0]
        self.counter.seconds += time.perf_counter() - t0
        return cat_scores(parts)

    def probe_keys_stream(
        self, chunks: Iterable[np.ndarray], total: int, stage: str, *, screen: int, keep: int
    ) -> KeyScan:
        """Streamed key scan: each chunk of keys screened on ``screen`` samples (bf16 where the model
        allows), the ``keep`` best by divergence (and, with targets, by screening leakage) kept and
        re-scored exactly with ``probe_keys``. Memory stays at one chunk, whatever ``total`` is."""
        return scan_keys(self, chunks, total, stage, screen=screen, keep=keep)

    @torch.inference_mode()
    def probe_deltas(self, deltas: list[torch.Tensor], stage: str = "deltas") -> dict[str, torch.Tensor]:
        """Score delta rows (K per layer) on every sample, in chunks within the budget, as keys are."""
        rows = len(deltas[0])
        return self._probe(rows, lambda i, j: [d[i:j] for d in deltas], self.keys_per_chunk(), stage)


def model_key(km: KeyedModel) -> tuple:
    """What decides a keyed model's outputs for given deltas: its module's class and tensors (by identity
    and version: a sealed bundle's attacked model and its control share the base's), its keyed layers,
    their batch axes and its encoder's range and widths."""
    tensors = tuple((id(t), t._version) for t in (*km.module.parameters(), *km.module.buffers()))
    return (type(km.module), tensors, tuple(km.layer_names), tuple(sorted(km.batch_axis.items())),
            float(km.encoder.scale), tuple(km.encoder.features))  # fmt: skip


def cat_scores(parts: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([p[k].detach().cpu() for p in parts]) for k in parts[0]}


def divergence(o: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """The searches' objective per key (differentiable): mse to b, or KL(softmax b || softmax o)."""
    if task == "classification":
        logp_b = F.log_softmax(b, -1)
        return (logp_b.exp() * (logp_b - F.log_softmax(o, -1))).sum(-1).flatten(1).mean(-1)
    return ((o - b) ** 2).flatten(1).mean(-1)


def maximise_divergence(
    ctx: ProbeContext, params: list[torch.Tensor], make_deltas: Callable[[], list[torch.Tensor]], stage: str
) -> None:
    """Adam on all restarts at once (each restart is one key row); maximise each one's divergence."""
    s = ctx.settings
    first = make_deltas()
    if not moves(params, first):  # no delta depends on the parameters: every gradient is 0 and Adam
        ctx.shortcut(NOT_STEPPED)  # leaves them as they are
        return
    opt = torch.optim.Adam(params, lr=s.search_lr)
    n = len(ctx.ref.x)
    x, b = ctx.ref.x, ctx.ref.b
    gen = ctx.generator()
    rows = len(first[0]) * (min(n, s.search_batch) if s.search_batch else n)
    for step in range(s.search_steps):
        if not ctx.affordable(rows, stage):  # the budget: the steps done so far are the search
            break
        if s.search_batch and s.search_batch < n:  # a fresh minibatch each step: cheaper, as good
            i = torch.randperm(n, generator=gen)[: s.search_batch].to(x.device)
            x, b = ctx.ref.x[i], ctx.ref.b[i]
        opt.zero_grad(set_to_none=True)
        # restarts are independent: the sum's gradient is each one's own
        backward_rows(ctx, x, b, make_deltas(), lambda o, t: -divergence(o, t, ctx.ref.task))
        opt.step()
        if ctx.progress and (step % 10 == 9 or step == s.search_steps - 1):
            ctx.progress(stage, step + 1, s.search_steps)


# Bytes one backward's autograd graph may hold (the activations its rows save, measured): a search step's
# (restart, sample) rows run in chunks within it, their gradients accumulated, as ``max_rows`` bounds a
# forward. A step of 128 restarts x 32 samples of the tiny pi0.5's 10-step flow sampler held over 5 GiB.
GRAPH_BYTES = 512 << 20


def saved_bytes(km: KeyedModel, x: torch.Tensor, deltas: list[torch.Tensor]) -> int:
    """Bytes the autograd graph of ``km.run_keys(x, deltas)`` holds: the distinct storages its backward
    saves, less the model's own tensors (held anyway). Runs the forward once; nothing is kept."""
    own = {t.untyped_storage().data_ptr() for t in (*km.module.parameters(), *km.module.buffers())}
    seen: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        st = t.untyped_storage()
        if st.data_ptr() not in own:
            seen[st.data_ptr()] = st.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = km.run_keys(x, deltas)
    del out
    return sum(seen.values())


def graph_rows(ctx: ProbeContext, x: torch.Tensor, deltas: list[torch.Tensor]) -> int:
    """(key, sample) rows one backward may run within ``GRAPH_BYTES``: a row's graph measured once per
    model and input shape on one key and a few samples (their shared work counted per row: the bound
    errs low), then kept in ``ctx.kept``."""
    key = ("graph bytes", model_key(ctx.km), tuple(x.shape[1:]))
    held = ctx.kept.get(key)
    if held is None:
        m = min(len(x), 4)
        per_row = saved_bytes(ctx.km, x[:m], [d[:1] for d in deltas]) / m
        held = ctx.kept[key] = (per_row, ctx.km.module)  # the module held: its id stays its own
    return max(1, int(GRAPH_BYTES // max(held[0], 1.0)))


def backward_rows(
    ctx: ProbeContext, x: torch.Tensor, t: torch.Tensor, deltas: list[torch.Tensor],
    loss: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
) -> torch.Tensor:  # fmt: skip
    """Backward of ``loss(km.run_keys(x, deltas), t).sum()`` into what ``deltas`` depend on, where
    ``loss`` gives each key's mean over its samples (outputs (K, B, ...), targets (B, ...)); returns each
    key's loss (detached). Where the rows outgrow ``graph_rows``, they run in chunks of keys and samples
    (a sample chunk's loss weighted by its share of the samples), the gradients accumulated on the
    deltas and carried back once: the same loss and gradient, within one chunk's graph of memory."""
    k, n = len(deltas[0]), len(x)
    cap = graph_rows(ctx, x, deltas) if k * n > 1 else 1
    if k * n <= cap:
        value = loss(ctx.km.run_keys(x, deltas), t)
        value.sum().backward()
        return value.detach()
    per_s = min(n, cap)
    per_k = max(1, cap // per_s)
    leaves = [d.detach().requires_grad_(True) for d in deltas]
    values = torch.zeros(k, device=x.device)
    for i in range(0, k, per_k):
        for j in range(0, n, per_s):
            xs, ts = x[j : j + per_s], t[j : j + per_s]
            part = loss(ctx.km.run_keys(xs, [d[i : i + per_k] for d in leaves]), ts) * (len(xs) / n)
            part.sum().backward()
            values[i : i + per_k] += part.detach()
    grads = [d.grad if d.grad is not None else torch.zeros_like(d) for d in leaves]
    torch.autograd.backward(deltas, grads)
    return values


NOT_STEPPED = (
    "the search's deltas do not depend on what it optimises (a blank encoder's zero head): not stepped"
)


def moves(params: list[torch.Tensor], deltas: list[torch.Tensor]) -> bool:
    """Whether ``deltas`` change with ``params`` at all: a random vector's product with the Jacobian is
    non-zero (an attacker's blank encoder over a sealed bundle's base: its zero head makes every
    gradient exactly 0, so a search there cannot move)."""
    if not any(d.requires_grad for d in deltas):
        return False
    gen = torch.Generator().manual_seed(0)
    v = [torch.randn(d.shape, generator=gen).to(d) for d in deltas]
    grads = torch.autograd.grad(deltas, params, v, allow_unused=True)
    return any(g is not None and bool(g.any()) for g in grads)


def on_original(
    run: Callable[[ProbeContext], list[Group]],
) -> Callable[[ProbeContext, list[Group]], list[Group]]:
    """A search's control: the same probe, same restarts, on the original checkpoint keyed at the same
    layers (nothing when there is no original: the report says the control is unavailable)."""

    def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
        return [] if ctx.original is None else run(ctx.on(ctx.original))

    return control


def on_unenrolled(
    run: Callable[[ProbeContext], list[Group]],
) -> Callable[[ProbeContext, list[Group]], list[Group]]:
    """A key probe's control: the same keys where no user was enrolled (``ProbeContext.unenrolled``)."""

    def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
        return run(ctx.on(ctx.unenrolled))

    return control


def codes_unenrolled(ctx: ProbeContext, found: list[Group]) -> list[Group]:
    """The control of concrete codes (a search's rounding): the same codes where no user was enrolled."""
    out = ctx.on(ctx.unenrolled)
    return [Group(g.name, out.probe_codes(g.codes, f"{g.name} control"), is_key=g.is_key, kind="key")
            for g in found if g.codes is not None]  # fmt: skip


@dataclass(frozen=True)
class Probe:
    """One registry entry. ``needs`` says what the probe cannot run without: "key" (the audited user's
    key), "other-keys" (a second user's key), "original" (the original checkpoint: ``--original``, or a
    base that is the original's), or nothing."""

    name: str
    threat: str  # one of THREATS
    kind: str  # one of KINDS
    summary: str  # one line for help texts and docs/audit.md
    run: Callable[[ProbeContext], list[Group]]
    # (context, the groups run found) -> the control's groups, matched to run's by name
    control: Callable[[ProbeContext, list[Group]], list[Group]] | None = None
    needs: str | None = None
    default: bool = True  # part of the default audit
    white_box: bool = False  # reads the bundle's weights (not only runs keys): left out by --search
    # Whether its answer is already in hand in this audit (a search another probe ran on the same model),
    # so that it still runs, at no cost, once the budget is spent
    known: Callable[[ProbeContext], bool] | None = None

    def __post_init__(self) -> None:
        if self.threat not in THREATS or self.kind not in KINDS:
            raise ValueError(f"probe {self.name}: threat {self.threat!r} / kind {self.kind!r} unknown")
