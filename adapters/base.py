"""The adapter contract: what a checkpoint format provides, and what it returns (``LoadedModel``).

An adapter turns one checkpoint format into a ``torch.nn.Module`` whose state-dict names are the
checkpoint's own. It is one file holding a subclass of :class:`Adapter`, plus one line in the
registry (``prop_adapters.ADAPTERS``); dispatch, option checks, help text and ``prop formats`` come
from the registry.
"""

from __future__ import annotations

import builtins
import contextlib
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import torch

from prop_cli.core.rules import Rule
from prop_cli.errors import PropError


@dataclass
class CheckpointOptions:
    """What the user may say about a checkpoint (``--arch``, ``--arch-kwargs``, ``--activation``), and
    whether they trust code the checkpoint's own files name (``--trust-remote-code``)."""

    arch: str | None = None
    arch_kwargs: dict | None = None
    activation: str | None = None
    trust_remote_code: bool = False  # not a format option: every adapter takes it
    # Not a format option either (personalize sets it under --precision bf16): each weight held in the
    # dtype the checkpoint stores it in, not fp32, from the load on (a LeRobot policy; the others ignore it).
    keep_dtypes: bool = False

    FLAGS: ClassVar[dict[str, str]] = {
        "arch": "--arch",
        "arch_kwargs": "--arch-kwargs",
        "activation": "--activation",
    }

    def given(self) -> list[str]:
        """Names of the options that are set."""
        return [name for name in self.FLAGS if getattr(self, name) not in (None, {})]


@dataclass
class LoadedModel:
    """A checkpoint turned into a module whose state-dict names are the checkpoint's names."""

    module: torch.nn.Module  # built, weights loaded, eval mode, float32 (``keep_dtypes``: the checkpoint's)
    spec: dict  # JSON-serialisable; spec["adapter"] names the adapter; rebuilds the module
    dtypes: dict[str, torch.dtype]  # original dtype of every checkpoint tensor, by name
    input_shape: tuple[int, ...] | None  # per-sample input shape if known, e.g. (4,)
    source: str  # the path it came from
    # Checkpoint tensors the module does not use (e.g. an SB3 critic): written back into the bundle's
    # base file untouched, so the whole original state dict round-trips.
    extra: dict[str, torch.Tensor] = field(default_factory=dict)
    # What the outputs are, where the format says: True = continuous actions/targets (regression),
    # False = a discrete choice over the outputs (classification: logits), None = not known.
    continuous: bool | None = None
    # Bounds of a continuous action space (one value per output), where the checkpoint records them.
    action_low: tuple[float, ...] | None = None
    action_high: tuple[float, ...] | None = None
    # Set for policies that bring their own loss, batch layout and control loop (LeRobot): the trainer,
    # the bundle and `prop eval` talk to it instead of calling module(x).
    policy: PolicyProtocol | None = None
    # Files the bundle carries besides the weights (relative path -> bytes), e.g. a LeRobot folder's
    # config and processors, so that the bundle's base loads in the original library.
    files: dict[str, bytes] = field(default_factory=dict)
    # Where in the bundle a second copy (hard link) of the base weights goes, next to ``files``.
    base_alias: str | None = None


FRAME = "frame"  # a fallback pool row's frame: an index into the frames the pool was drawn for


class PolicyProtocol(ABC):
    """A policy that brings its own loss (paper Eq. 8's user term) and acts in a control loop.

    Batches are dicts of tensors in the policy's normalised units, one row per frame, with the action
    chunk (``action``) and its padding mask where the policy has them.

    Where policies differ in training, this is the one place: the user term (``loss``, split by its
    normaliser in ``loss_parts`` for several processes), the fallback term's rows, output and target
    (``fallback_pool``, ``fallback_output``, ``fallback_distance``) and the deployed chunk
    (``chunk``). The defaults are a policy whose deployed chunk is deterministic (ACT):
    the fallback distils the original's chunk, L1. A denoising policy (Diffusion) distils the original's
    denoiser on the same (observation, x_t, t) instead, and draws its chunks' noise from ``noise_seed``.
    """

    default_layers: ClassVar[list[str]]  # regexes over layer names keyed when --layers is not given
    fallbacks: ClassVar[tuple[str, ...]]  # fallback terms this policy supports, the default first
    # Seed of the noise a sampling policy's chunks start from (`--noise-seed`); unused by the others.
    noise_seed: int = 0
    # A language-conditioned policy's instruction in closed loop (`prop eval --instruction`); unused by
    # the others (data rows carry their own task text).
    instruction: str = ""

    @abstractmethod
    def on(self, module: torch.nn.Module) -> PolicyProtocol:
        """The same policy (processors, noise seed) over ``module``, a copy with the same layers."""

    def fallback_pool(
        self, batch: dict[str, torch.Tensor], chunks: torch.Tensor, original: PolicyProtocol,
        generator: torch.Generator,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:  # fmt: skip
        """The rows the fallback term samples from and the original's output on each, drawn once before
        training (``chunks``: the original's deployed chunk per frame of ``batch``). Default: the frames
        themselves, their targets the chunks (a deterministic policy's, cached as targets)."""
        return batch, chunks

    def memo(self) -> contextlib.AbstractContextManager:
        """Within: what this policy type computes the same under every key and at every step, from
        frozen weights, may be computed once (SmolVLA: each frame's image embedding). Default: nothing
        is kept."""
        return contextlib.nullcontext()

    # A denoising policy's fallback timesteps (``--fallback-times``, set by the trainer): "uniform" over
    # its training range, or "sampler": only those its deployed sampler visits. Unused by the others.
    fallback_times: str = "uniform"

    def fallback_noise(self, frames: int, generator: torch.Generator) -> dict[str, torch.Tensor] | None:
        """The random draws of the fallback pool of ``frames`` frames, made before any forward, so the
        trainer computes a row's target only when a step first draws it: per row, its frame
        (``FRAME``) and what ``fallback_inputs`` mixes with the frame's chunk (a denoising policy: its
        time and noise), in the order ``fallback_pool`` draws them. None: the pool's rows are the
        frames and their targets the original's chunks (this class's ``fallback_pool``).
        ``NotImplemented``: a policy with its own ``fallback_pool`` and no lazy form; it is drawn whole."""
        return None if type(self).fallback_pool is PolicyProtocol.fallback_pool else NotImplemented

    def fallback_inputs(self, x0: torch.Tensor, noise: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What a pool row feeds the policy besides its frame (e.g. ``{"x_t", "t"}``), from the clean
        chunk ``x0`` of each row's frame and the row's draws (``fallback_noise`` less ``FRAME``)."""
        raise NotImplementedError

    # True where the user term and the fallback output can share one forward (``joint_terms``): the
    # policy's training and eval paths compute the same thing (no dropout, no random crop, no batch norm).
    joins_terms: bool = False

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(loss(user), fallback_output(fallback))`` from one forward over the user rows, then the
        fallback rows (in that order: rows carry their own keys). Only where ``joins_terms``."""
        raise NotImplementedError

    def fallback_output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """What the fallback term compares between the keyed policy and the original (eval mode)."""
        return self.chunk(batch)

    def fallback_distance(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Per-row distance of the fallback term: L1 (ACT's own loss) by default."""
        return (pred - target).abs().flatten(1).mean(1)

    @property
    def row_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-row shape of each observation feature in a batch (a policy with an observation history
        has a time axis first); the environment gives ``input_features``."""
        return self.input_features

    def describe(self) -> dict:
        """What `prop inspect` shows of this policy beyond its adapter's fields."""
        return {}

    @abstractmethod
    def batches(self, data, flag: str) -> dict[str, torch.Tensor]:
        """A Dataset (prop_cli.datasources) -> training tensors, normalised; PropError if it does not fit."""

    @abstractmethod
    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The policy's own training loss on ``batch`` (a batch mean), in training mode."""

    def loss_parts(self, batch: dict[str, torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``loss(batch)`` as parts ``(value, weights)`` whose values add up to it: each value normalised
        over ``batch`` as the policy normalises it, ``weights`` (rows,) each row's share of that
        normaliser. Several processes (prop_cli.train.distributed) scale each process's value by its
        rows' weight over the step's, so their gradients add up to the whole step's. Default: one
        part, a mean over rows (``row_weights``)."""
        return [(self.loss(batch), self.row_weights(batch))]

    def row_weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Each row's weight in the normaliser of the policy's loss: 1 each (a mean over rows)."""
        first = next(iter(batch.values()))
        return torch.ones(len(first), device=first.device)

    def joint_parts(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
        """``joint_terms`` with its user loss as ``loss_parts``."""
        loss, out = self.joint_terms(user, fallback)
        return [(loss, self.row_weights(user))], out

    @abstractmethod
    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The deployed prediction (rows, ...) for the observations in ``batch``; differentiable."""

    @abstractmethod
    def example(self, rows: int, data: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """``rows`` rows of ``data`` (for probing the layers)."""

    @abstractmethod
    def controller(self, module: torch.nn.Module):
        """An object with ``reset(seed=None)`` and ``select_action(obs: dict) -> np.ndarray`` that drives
        ``module`` in closed loop (``KeyedPolicy`` and ``prop eval`` use it)."""

    @property
    @abstractmethod
    def input_features(self) -> dict[str, tuple[int, ...]]:
        """Observation feature name -> per-frame shape, as the environment must provide them."""

    @abstractmethod
    def flat(self) -> FlatView:
        """This policy as an array model (the audit's view, a sealed policy's reports): ``x`` (B, F), the
        rows of ``flat_rows``, -> the deployed chunk flattened; the same layers run."""

    @abstractmethod
    def flat_rows(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """A batch's row features (``row_shapes``) flattened and concatenated, as ``flat`` takes them."""


class FlatView(torch.nn.Module):
    """A policy seen as an array model (``PolicyProtocol.flat``): ``protocol`` is the policy it runs,
    ``width`` its input's width. What decides between an array model and a policy treats this as the
    array model it is."""

    protocol: PolicyProtocol
    width: int

    def __setattr__(self, name: str, value) -> None:
        if name == "protocol":  # the policy object stays out of _modules (its children are the view's)
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)


class Adapter(ABC):
    """One checkpoint format. Subclasses set ``name``, ``summary`` and ``options`` and implement
    ``recognise``, ``load`` and ``rebuild``; ``describe`` has a default."""

    name: ClassVar[str]  # stored in the manifest as model.adapter: never rename
    summary: ClassVar[str]  # one line for `prop formats`, help texts and docs/formats.md
    options: ClassVar[tuple[str, ...]] = ()  # the CheckpointOptions fields this format uses
    # What this adapter's model spec holds besides "adapter" (a manifest's ``model``), checked by the
    # bundle format (``prop_cli.core.rules.MODEL_FIELDS``). An empty table: any fields (an extension's).
    manifest_fields: ClassVar[dict[str, Rule]] = {}

    @staticmethod
    def check_spec(spec: dict) -> tuple[str, str] | None:
        """What ``manifest_fields`` cannot say: how a spec's fields fit together (the spec passed them).
        None, or (the field, what is wrong with it)."""
        return None

    @abstractmethod
    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        """Cheap: is ``path`` in this format (suffix, files present, a peek at a header)?"""

    @abstractmethod
    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        """Read the checkpoint; every problem is a one-line PropError naming the file."""

    @abstractmethod
    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        """The module a bundle describes (``spec`` from its manifest) with ``weights`` (its base file)."""

    def remote_code(self, spec: dict, source: str) -> list[str]:
        """What rebuilding ``spec`` (a bundle's manifest, and files at ``source``) would import or call
        that a *file* names, one entry each ("model.arch 'pkg.mod:fn'"); [] if nothing. Called before
        ``rebuild``: anything listed is refused unless the user passes --trust-remote-code."""
        return []

    def remote_code_at(self, path: Path, options: CheckpointOptions) -> list[str]:
        """The same for ``load``: code the checkpoint's files name (not what the user gave, such as
        --arch, which is their consent for that command)."""
        return []

    def weights(self, path: Path) -> dict[str, torch.Tensor]:
        """The checkpoint's tensors by name, as ``rebuild`` takes them (``--original`` is read so)."""
        from .weights import read_weights

        return read_weights(path)[0]

    def describe(self, loaded: LoadedModel) -> dict:
        """What this adapter knows about the model, for `prop inspect` (JSON-serialisable)."""
        info: dict = {"adapter": self.name}
        if loaded.continuous is not None:
            info["outputs"] = "continuous" if loaded.continuous else "discrete (logits)"
        if loaded.action_low is not None and loaded.action_high is not None:
            info["action_low"], info["action_high"] = list(loaded.action_low), list(loaded.action_high)
        if "activation" in loaded.spec:
            info["activation"] = loaded.spec["activation"]
        return info


def finish(module: torch.nn.Module, held: dict[str, torch.dtype] | None = None) -> torch.nn.Module:
    """Common last step of every adapter: float32, eval mode, no autograd surprises. ``held`` (the
    dtype the checkpoint stores each tensor in, by state-dict name; ``keep_dtypes``): each float tensor
    in its checkpoint's dtype instead, those the checkpoint does not hold float32."""
    if held is None:
        return module.float().eval()
    for name, t in (*module.named_parameters(), *module.named_buffers()):
        want = held.get(name, torch.float32)
        if t.is_floating_point() and t.dtype != want:
            t.data = t.data.to(want)
    return module.eval()


TRUST_FLAG = "--trust-remote-code"


def require_trust(named: list[str], source: str, trusted: bool) -> None:
    """Refuse, in one line naming it and the flag, code a file names that the user has not trusted.
    Nothing is imported before this check."""
    if named and not trusted:
        raise PropError(
            f"{source} names code to import and run: {'; '.join(named)}",
            f"pass {TRUST_FLAG} (trust_remote_code=True in the API) only if you trust whoever wrote them",
        )


def check_exists(path: Path) -> None:
    if not path.exists():
        raise PropError(f"checkpoint {path} does not exist", "check the path")


CODE_FIELD = "auto_map"  # transformers imports the code it names from the folder (or asks whether to)


def names_code(doc: object) -> bool:
    """Whether a parsed JSON file names code for transformers: an ``auto_map`` at its top or one level
    down (a processor config's sub-configs); deeper is data (a tokenizer's vocabulary may hold any
    word)."""
    inner = list(doc.values()) if isinstance(doc, dict) else []
    return any(isinstance(d, dict) and CODE_FIELD in d for d in [doc, *inner])


class PromptRefused(EOFError):
    """What a library gets if it asks a question at the terminal while prop loads a checkpoint."""


@contextlib.contextmanager
def no_prompt() -> Iterator[None]:
    """While a library (LeRobot, transformers) reads a checkpoint's files, nothing asks at the terminal.

    transformers asks "Do you wish to run the custom code? [y/N]" when a file names code (``auto_map``)
    and no ``trust_remote_code`` was given, which LeRobot never gives: a "y" ran a bundle's code (issue
    31). prop refuses such files before a library sees them (``bundle.read.check_tree``, the adapters'
    own checks); this is the guard behind that: ``input()`` fails at once, printing nothing, so no
    question reaches the terminal and no answer can come from it (transformers then refuses the code).
    ``input()`` is the process's: a thread reading the terminal meanwhile gets the same refusal."""

    def refuse(prompt: object = "") -> str:
        raise PromptRefused("prop answers no prompt while it loads a checkpoint")

    original, builtins.input = builtins.input, refuse
    try:
        yield
    finally:
        builtins.input = original
