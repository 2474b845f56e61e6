"""Random draws a policy makes inside its own loss, made per row: the same for a row whichever process
computes it and whichever rows share its forward.

LeRobot's policies draw inside their training forward: ACT its dropout masks and the VAE latent's
noise, Diffusion the noise and timestep of each row, SmolVLA (and pi0) the flow-matching noise and
Beta-distributed time. From torch's global generator, a row's draws depend on the rows drawn before it,
so a step split between processes (``distributed``) would train on other noise than one process.

``RowNoise`` makes each seeded aten operator of the forward (a ``TorchDispatchMode``, ``_Draws``) as the
whole step would draw it, from one generator per (run, step, call), and keeps this forward's rows; a
draw from per-row parameters (a Beta's) is made per row, from one generator per (run, step, call, row).
Either way row r's draws are the same whether r is computed alone, beside the step's other rows, or on
another process. ``probe`` finds, for each random call of the forward, the axis that holds the rows
(and how many entries each row has on it) by running the forward at two row counts; a draw whose shape
does not follow the rows (a random crop's offset) is made once per step and call, the same on every
process. Operators it cannot draw per row (an attention kernel with dropout inside, a sequence of draws
that depends on the data) are reported by name.

The mode makes every operator a trip through Python. Where the probe saw every draw made inside one of
torch's random functions (``torch.randn``, ``F.dropout``, ``Tensor.bernoulli_``, ...: all of LeRobot's
policies), only those run inside it, swapped for wrapped ones during the step's forward
(``_random_functions``: prop trains in one thread); otherwise the whole forward does.

One process draws this way too, so one process and several train the same model. It only changes where
the numbers come from: each draw keeps its distribution, dtype and device.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from prop_cli.errors import PropError

_MASK64 = (1 << 64) - 1

# In-place fills of ``self`` (the first argument); each takes a ``generator``.
_FILLS = {"bernoulli_", "normal_", "uniform_", "random_", "exponential_", "cauchy_", "log_normal_",
          "geometric_"}  # fmt: skip
# Draws from tensor arguments, shaped like the first one; each takes a ``generator``.
_FROM_TENSORS = {"bernoulli", "_sample_dirichlet", "_standard_gamma", "poisson", "binomial", "multinomial",
                 "normal"}  # fmt: skip
# Factories (a ``size``, or a tensor whose shape they take): the in-place fill each one's draw is.
_FACTORIES = {"randn": "normal_", "randn_like": "normal_", "rand": "uniform_", "rand_like": "uniform_",
              "randint": "random_", "randint_like": "random_", "normal": "normal_"}  # fmt: skip


def _mix(*parts: int) -> int:
    """A 63-bit seed from integers (splitmix64 over them): cheap enough to call per row and call."""
    h = 0x9E3779B97F4A7C15
    for p in parts:
        h = (h ^ (p & _MASK64)) * 0xBF58476D1CE4E5B9 & _MASK64
        h = (h ^ (h >> 31)) * 0x94D049BB133111EB & _MASK64
        h ^= h >> 29
    return h >> 1


def _name(func) -> str:
    return func.overloadpacket.__name__


_SEEDED: dict = {}  # operator -> whether it is seeded (read once: ``tags`` is built on every read)


def _seeded(func) -> bool:
    seeded = _SEEDED.get(func)
    if seeded is None:
        seeded = _SEEDED[func] = torch.Tag.nondeterministic_seeded in func.tags
    return seeded


_NAMES: dict = {}  # operator -> its schema's argument names (the schema is rebuilt on every read)


def _arg_names(func) -> list[str]:
    names = _NAMES.get(func)
    if names is None:
        names = _NAMES[func] = [a.name for a in func._schema.arguments]
    return names


def _args(func, args: tuple, kwargs: dict) -> dict:
    """The call's arguments by their schema names (those given; defaults left to the operator)."""
    out = dict(zip(_arg_names(func), args))
    for k, v in kwargs.items():
        out[k] = v
    return out


def _kind(func, named: dict) -> str | None:
    """How a seeded operator is drawn per row: "fill", "factory", "tensors", "dropout"; None: it draws
    nothing with these arguments (dropout off); "unsupported": prop cannot draw it per row."""
    name = _name(func)
    if name == "native_dropout":
        return None if named.get("train") is False or named["p"] == 0 else "dropout"
    if name in _FILLS:
        return "fill"
    if name in _FACTORIES and ("size" in named or name.endswith("_like")):
        return "factory"
    if name in _FROM_TENSORS:
        return "tensors"
    # Kernels that draw inside (attention with dropout): nothing to draw at probability 0.
    takes_p = "dropout_p" in _arg_names(func)
    return None if takes_p and named.get("dropout_p", 0.0) == 0 else "unsupported"


def _shape(func, named: dict) -> tuple[int, ...]:
    """The shape of what a random call draws."""
    name = _name(func)
    if "size" in named:
        return tuple(int(s) for s in named["size"])
    for name in _arg_names(func):
        v = named.get(name)
        if isinstance(v, torch.Tensor):
            return tuple(v.shape)
    raise PropError(f"the policy draws with aten.{name} on no tensor", "report this as a bug")


@dataclass(frozen=True)
class Draw:
    """One random call of the forward: its operator, and the axis holding the rows (``None``: the draw
    does not follow the rows) with ``per_row`` entries per row on it."""

    op: str
    axis: int | None
    per_row: int


# torch's random functions (and Tensor methods) a policy's Python code draws with: while a step's forward
# runs, each is wrapped to run inside the per-row dispatch mode (``_random_functions``), and the rest of
# the forward runs without it. A dispatch mode costs every operator a trip through Python: over a whole
# forward it made the small ACT's PRoP step 1.5x slower.
_TORCH_FUNCTIONS = ("randn", "rand", "randint", "randn_like", "rand_like", "randint_like", "normal",
                    "bernoulli", "multinomial", "poisson", "binomial", "_sample_dirichlet",
                    "_standard_gamma")  # fmt: skip
_FUNCTIONAL = ("dropout", "dropout1d", "dropout2d", "dropout3d", "alpha_dropout", "feature_alpha_dropout")
_METHODS = ("normal_", "uniform_", "bernoulli_", "random_", "exponential_", "cauchy_", "log_normal_",
            "geometric_", "bernoulli", "multinomial")  # fmt: skip


class _Inside:
    """Whether a wrapped random function is running (the flag the probe reads; nested calls pass)."""

    depth = 0


@contextlib.contextmanager
def _random_functions(mode: Callable[[], contextlib.AbstractContextManager]) -> Iterator[None]:
    """torch's random functions, each run inside ``mode()`` while called (the outermost call only)."""

    def wrap(fn):
        @functools.wraps(fn)
        def inner(*args, **kwargs):
            if _Inside.depth:
                return fn(*args, **kwargs)
            _Inside.depth += 1
            try:
                with mode():
                    return fn(*args, **kwargs)
            finally:
                _Inside.depth -= 1

        return inner

    saved = []
    for owner, names in ((torch, _TORCH_FUNCTIONS), (F, _FUNCTIONAL), (torch.Tensor, _METHODS)):
        for name in names:
            if hasattr(owner, name):
                saved.append((owner, name, owner.__dict__.get(name), getattr(owner, name)))
                setattr(owner, name, wrap(getattr(owner, name)))
    try:
        yield
    finally:
        for owner, name, own, _ in reversed(saved):
            if own is None:
                delattr(owner, name)  # a Tensor method inherited from TensorBase
            else:
                setattr(owner, name, own)


class _Record(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[str, tuple[int, ...]]] = []
        self.unsupported: set[str] = set()
        self.covered = True  # every draw made inside a wrapped random function

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if _seeded(func):
            named = _args(func, args, kwargs)
            kind = _kind(func, named)
            if kind == "unsupported":
                self.unsupported.add(f"aten.{_name(func)}")
            elif kind is not None:
                self.calls.append((_name(func), _shape(func, named)))
                self.covered = self.covered and _Inside.depth > 0
        return func(*args, **kwargs)


def _layout(sizes: tuple[int, int], runs: list[list[tuple[str, tuple[int, ...]]]]) -> list[Draw] | str:
    """The draws' row axes from the same forward at ``sizes`` rows; a reason where they cannot be found."""
    a, b = runs
    if [n for n, _ in a] != [n for n, _ in b]:
        return "its random draws change with the number of rows"
    out = []
    for (name, sa), (_, sb) in zip(a, b):
        if len(sa) != len(sb):
            return f"aten.{name} draws {len(sa)}-d at {sizes[0]} rows and {len(sb)}-d at {sizes[1]}"
        axes = [i for i, (x, y) in enumerate(zip(sa, sb)) if x != y]
        if not axes:
            out.append(Draw(name, None, 0))
            continue
        per_row = sa[axes[0]] // sizes[0]
        if len(axes) > 1 or sa[axes[0]] != per_row * sizes[0] or sb[axes[0]] != per_row * sizes[1]:
            return f"aten.{name} draws {sa} at {sizes[0]} rows and {sb} at {sizes[1]}"
        out.append(Draw(name, axes[0], per_row))
    return out


class RowNoise:
    """The per-row draws of one forward (``probe`` makes one); ``rows(step, ids)`` is the context a
    step's forward runs in, over the rows ``ids`` (their indices among the step's rows)."""

    def __init__(self, draws: list[Draw], seed: tuple[int, ...], covered: bool = False) -> None:
        self.draws, self.seed = draws, seed
        # Every draw is made by a function ``_random_functions`` wraps: the mode runs only inside them.
        self.covered = covered

    @classmethod
    def probe(
        cls, forward: Callable[[int, int], object], seed: tuple[int, ...],
        module: torch.nn.Module | None = None,
    ) -> tuple[RowNoise | None, str | None]:  # fmt: skip
        """``forward(rows, other)``: the step's forward on ``rows`` rows whose draws are per row and
        ``other`` rows that must draw nothing (the fallback rows sharing the forward). Returns the
        RowNoise (None: the forward draws nothing) and, where its draws cannot be made per row, why
        (then None too). ``module``: its buffers (batch-norm statistics) are restored after."""
        saved = {k: v.clone() for k, v in module.named_buffers()} if module is not None else {}
        runs, covered = [], True
        try:
            for rows, other in ((2, 2), (3, 2), (2, 3)):
                rec = _Record()
                # The draws only, without a graph (a real-size policy's memory).
                with rec, _random_functions(contextlib.nullcontext), torch.no_grad():
                    forward(rows, other)
                if rec.unsupported:
                    return None, f"it draws with {', '.join(sorted(rec.unsupported))}"
                runs.append(rec.calls)
                covered = covered and rec.covered
        finally:
            if saved:
                with torch.no_grad():
                    for k, v in module.named_buffers():
                        v.copy_(saved[k])
        if runs[2] != runs[0]:
            return None, "its random draws change with the rows it does not train on"
        layout = _layout((2, 3), runs[:2])
        if isinstance(layout, str):
            return None, layout
        return (cls(layout, seed, covered) if layout else None), None

    @contextlib.contextmanager
    def rows(self, step: int, ids: torch.Tensor, total: int) -> Iterator[None]:
        """The context of step ``step``'s forward over its rows ``ids`` (of ``total``)."""
        draws = _Draws(self, step, ids, total)
        with _random_functions(lambda: draws) if self.covered else draws:
            yield


class _Draws(TorchDispatchMode):
    """The dispatch mode of one forward: each seeded operator drawn as the whole step would draw it
    (``RowNoise``), this forward's rows kept."""

    def __init__(self, noise: RowNoise, step: int, ids: torch.Tensor, total: int) -> None:
        super().__init__()
        self.noise, self.step, self.total = noise, step, total
        self.ids = [int(i) for i in ids.tolist()]
        self._index: dict[tuple[torch.device, int], torch.Tensor] = {}
        self.call = 0

    def _generator(self, device: torch.device, row: int = -1) -> torch.Generator:
        g = torch.Generator(device)
        g.manual_seed(_mix(*self.noise.seed, self.step, self.call, row))
        return g

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if not _seeded(func):
            return func(*args, **kwargs)
        named = _args(func, args, kwargs)
        kind = _kind(func, named)
        if kind is None:
            return func(*args, **kwargs)
        draws = self.noise.draws
        name = _name(func)
        if self.call >= len(draws) or draws[self.call].op != name:
            raise PropError(
                f"the policy's random draws differ from those probed before training (call {self.call}: "
                f"aten.{name})",
                "train it as one process (without accelerate launch); report this policy",
            )
        draw = draws[self.call]
        shape = _shape(func, named)
        if draw.axis is not None and shape[draw.axis] != draw.per_row * len(self.ids):
            raise PropError(
                f"the policy's draw aten.{name} has shape {shape}, not {draw.per_row} per row of "
                f"{len(self.ids)} on axis {draw.axis}",
                "train it as one process (without accelerate launch); report this policy",
            )
        try:
            return self._draw(func, kind, named, draw)
        finally:
            self.call += 1

    def _mine(self, whole: torch.Tensor, draw: Draw) -> torch.Tensor:
        """This forward's rows of a draw made for all the step's rows."""
        k, ids = draw.per_row, self.ids
        if ids == list(range(ids[0], ids[0] + len(ids))):
            return whole.narrow(draw.axis, ids[0] * k, len(ids) * k)
        key = (whole.device, k)
        if key not in self._index:
            rows = torch.tensor(ids, device=whole.device)
            self._index[key] = (rows[:, None] * k + torch.arange(k, device=whole.device)).flatten()
        return whole.index_select(draw.axis, self._index[key])

    def _fill(self, target: torch.Tensor, draw: Draw, fill: Callable) -> torch.Tensor:
        """``target`` filled by ``fill(tensor, generator)`` as it fills the whole step's draw (one
        generator per step and call), this forward's rows kept."""
        g = self._generator(target.device)
        if draw.axis is None:
            fill(target, g)
            return target
        shape = list(target.shape)
        shape[draw.axis] = self.total * draw.per_row
        whole = torch.empty(shape, dtype=target.dtype, device=target.device)
        fill(whole, g)
        return target.copy_(self._mine(whole, draw))

    def _per_row(self, func, named: dict, like: torch.Tensor, draw: Draw) -> list[torch.Tensor]:
        """``func`` on each row's cut of the tensor arguments, one generator per (step, call, row): for
        draws made from tensors that follow the rows (a Beta's parameters, a probability per entry)."""
        rest = {k: v for k, v in named.items() if k != "generator"}
        if draw.axis is None:
            return [func(**rest, generator=self._generator(like.device))]
        k = draw.per_row
        return [
            func(**_cut(rest, like, draw.axis, j * k, k), generator=self._generator(like.device, row))
            for j, row in enumerate(self.ids)
        ]

    def _draw(self, func, kind: str, named: dict, draw: Draw):
        if kind == "dropout":  # native_dropout (CUDA's): the mask drawn as above, applied as it does
            x, p = named["input"], named["p"]
            mask = torch.empty(x.shape, dtype=torch.bool, device=x.device)
            self._fill(mask, draw, lambda t, g: t.bernoulli_(1 - p, generator=g))
            return x * mask * (1.0 / (1 - p)), mask
        if kind == "factory":  # an empty tensor of the draw's dtype and device, filled as above
            name = _name(func)
            meta = func(**{k: v for k, v in named.items() if k != "generator"} | {"device": "meta"})
            like = named.get("self")
            device = named.get("device") or (like.device if isinstance(like, torch.Tensor) else "cpu")
            out = torch.empty(meta.shape, dtype=meta.dtype, device=device)
            if name.startswith("randint"):
                low, high = named.get("low", 0), named["high"]
                return self._fill(out, draw, lambda t, g: t.random_(low, high, generator=g))
            if name == "normal":
                mean, std = named["mean"], named["std"]
                return self._fill(out, draw, lambda t, g: t.normal_(mean, std, generator=g))
            if _FACTORIES[name] == "normal_":
                return self._fill(out, draw, lambda t, g: t.normal_(generator=g))
            return self._fill(out, draw, lambda t, g: t.uniform_(generator=g))
        if kind == "fill":
            target = named["self"]
            rest = {k: v for k, v in named.items() if k not in ("self", "generator")}
            if not any(isinstance(v, torch.Tensor) for v in rest.values()):
                return self._fill(target, draw, lambda t, g: func(t, **rest, generator=g))
            self._per_row(func, named, target, draw)  # in place, on each row's cut of ``target``
            return target
        # "tensors": drawn per row from the rows of the tensor arguments, joined on the row axis.
        first = next(v for v in named.values() if isinstance(v, torch.Tensor))
        pieces = self._per_row(func, named, first, draw)
        return pieces[0] if len(pieces) == 1 else torch.cat(pieces, draw.axis)


def _cut(named: dict, like: torch.Tensor, axis: int | None, start: int, n: int) -> dict:
    """The arguments of one row's piece: tensors shaped like ``like`` cut on the row axis (a broadcast
    one is shared); the rest as they are."""
    if n < 0:
        return named
    return {k: v.narrow(axis, start, n) if isinstance(v, torch.Tensor) and v.shape == like.shape else v
            for k, v in named.items()}  # fmt: skip
