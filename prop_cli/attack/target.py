"""What the audit attacks, decided here for every mode and kind of model.

- A policy with named features (LeRobot) is audited as an array model: its flat view
  (``PolicyProtocol.flat``), its data as flat rows (``prop_cli.fit``).
- White-box probes read ``km``: an unsealed bundle's own key encoder over its base; for a sealed
  bundle, which has no encoder, a blank one of the attacker's over the public base (its zero head
  gives delta = 1 for every code).
- Key probes turn keys into behaviour as ``prop run`` does: through the encoder, or (sealed) by trial
  decryption of the records (``probes.sealed_context``).
- The searches' controls run on the original: ``--original``, or where none is given a sealed
  bundle's base (it is the original) and a base trained with ``--freeze-base``.
- The key rows' control is the reference model keyed with a fresh encoder (``unenrolled_model``):
  what the same keys give where no user was enrolled. Always available.
- A search's control can reach the leakage ceiling while the bundle leaks (``controls_can_saturate``),
  except on a sealed bundle, whose searches run on the control's own model.
"""

from __future__ import annotations

import contextlib
import copy
from dataclasses import fields, replace

import torch
from torch import nn

from prop_adapters.base import FlatView
from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.bundle.read import rebuild_original
from prop_cli.config import AUDIT_BUDGET_POLICY, BLACKBOX_KEYS_POLICY, FEWSHOT_RESTARTS_POLICY, AuditSettings
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder
from prop_cli.datasources import Dataset
from prop_cli.fit import flat_dataset

from .probes.base import ProbeContext
from .probes.sealed_context import SealedContext, blank_keyed, equal_values, same_tensors


def as_array(bundle: Bundle, data: Dataset, settings: AuditSettings) -> tuple[Bundle, Dataset, AuditSettings]:
    """A policy bundle, its data and the audit's defaults as an array model's (others as they are).

    The flat view's KeyedModel hooks the same layer objects; the bundle's own hooks are removed so that
    each layer is scaled once."""
    loaded = bundle.loaded
    if loaded.policy is None:
        return bundle, data, settings
    data = flat_dataset(loaded.policy, data, "--data")
    flat = loaded.policy.flat()
    view = replace(loaded, module=flat, input_shape=(flat.width,), policy=None)
    return replace(bundle, loaded=view, mode=bundle.mode.on(flat)), data, policy_settings(settings)


def policy_settings(settings: AuditSettings) -> AuditSettings:
    """The audit's defaults for a policy, where not given: an ACT key is a transformer forward, so fewer
    keys in the scan and fewer restarts of the few-shot code fit; and a time budget (a real-size VLA's
    key is a sampler run per sample)."""
    if settings.blackbox is None:
        settings = replace(settings, blackbox=BLACKBOX_KEYS_POLICY)
    if settings.fewshot_restarts is None:
        settings = replace(settings, fewshot_restarts=FEWSHOT_RESTARTS_POLICY)
    if settings.budget is None:
        settings = replace(settings, budget=AUDIT_BUDGET_POLICY)
    return settings


def load_original(
    bundle: Bundle, path: str, trust_remote_code: bool = False, noise_seed: int = 0
) -> nn.Module:
    """The original checkpoint as the reference b, rebuilt the way the bundle's base is (a policy: its
    flat view, as the bundle is audited, its chunks sampled from ``noise_seed`` like the bundle's)."""
    loaded = rebuild_original(bundle, path, trust_remote_code)
    if loaded.policy is not None:
        loaded.policy.noise_seed = noise_seed
        return loaded.policy.flat()
    return loaded.module.eval()


# A policy's (key, sample) rows per forward: ROW_PARAMS / its parameters (SmolVLA at its published size,
# 450 M parameters: 8 rows, each a whole sampler run; the examples' small policies: no limit in effect).
ROW_PARAMS = 4e9


def rows_per_forward(module: nn.Module) -> int | None:
    """At most this many rows per forward of a policy's flat view (None: an array model, as it is)."""
    if not isinstance(module, FlatView):
        return None
    return max(1, int(ROW_PARAMS // max(1, sum(p.numel() for p in module.parameters()))))


def memo(module: nn.Module) -> contextlib.AbstractContextManager:
    """What a policy computes once for every key while the audit runs (its ``PolicyProtocol.memo``)."""
    return module.protocol.memo() if isinstance(module, FlatView) else contextlib.nullcontext()


def cheap_when_late(bundle: Bundle, probe) -> bool:
    """Whether a probe still runs once the budget is spent: a sealed bundle's key probes run no model for
    the keys that open no record (the base's outputs are kept), so they cost trial decryptions only."""
    return bundle.is_sealed and probe.kind == "key"


def unhooked_copy(module: nn.Module) -> nn.Module:
    """``module`` without the bundle's hooks, sharing its tensors (the audit never changes a weight:
    a 450 M-parameter base is not held twice)."""
    shared = {id(t): t for t in (*module.parameters(), *module.buffers())}
    copied = copy.deepcopy(module, shared)
    for m in copied.modules():
        m._forward_pre_hooks.clear()  # a copied bundle module carries the bundle's hooks: drop them
    return copied


def attacked_model(bundle: Bundle, dev: torch.device) -> KeyedModel:
    """The keyed model white-box probes read (see the module docstring)."""
    if not bundle.is_sealed:
        km = bundle.keyed.to(dev).eval()
        km.max_rows = rows_per_forward(km.module)
        return km
    km = blank_keyed(unhooked_copy(bundle.loaded.module), bundle.layer_names, bundle.key_bits).to(dev)
    layers = bundle.manifest[C.M_KEYED_LAYERS]  # sequence-first layers (ACT): their batch axes
    km.batch_axis = {x["name"]: int(x[C.M_BATCH_AXIS]) for x in layers if C.M_BATCH_AXIS in x}
    km.max_rows = rows_per_forward(km.module)
    return km


def unenrolled_model(km: KeyedModel, reference: nn.Module, seed: int) -> KeyedModel:
    """``reference`` keyed at the bundle's layers with a fresh, untrained encoder of the bundle's
    encoder's shape, built from ``seed`` (the same on every run). Its head starts at zero, so every key
    gives delta = 1 and runs the reference: what the keys give where no user was enrolled. Training
    Eq. 8 without a user leaves it there (the fallback's loss is 0 at delta = 1), so this is also what
    a bundle trained without you would give."""
    enc = km.encoder
    dev = enc.net[0].weight.device
    hidden = [m.out_features for m in enc.net if isinstance(m, nn.Linear)][:-1]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        fresh = KeyEncoder(enc.code_bits, enc.features, hidden, enc.scale)
    keyed = KeyedModel(unhooked_copy(reference).to(dev).eval(), fresh.to(dev), km.layer_names).eval()
    keyed.batch_axis = dict(km.batch_axis)
    keyed.max_rows = rows_per_forward(keyed.module)
    return keyed.requires_grad_(False)


def remedy(bundle: Bundle) -> str:
    """What a user can do about a leak, by mode (the verdict's first line ends with it)."""
    if bundle.is_sealed:
        return "keep your key secret; a key that opens your record is yours"
    return "seal it with --seal (wrong keys then run the original; docs/sealed.md)"


def key_rows(bundle: Bundle) -> str:
    """What the key rows measure, and how that differs from `prop run`, by mode (report and table)."""
    run = (
        "prop run refuses a key enrolled in nothing in the bundle (--allow-unenrolled-key runs the "
        "bundle's base for it, exactly)"
    )
    if bundle.is_sealed:
        return f"key rows try each key on the sealed records, as anyone holding the files can; {run}"
    return (
        "key rows run each key through the unsealed encoder, as anyone holding the files can run it "
        f"(the method, not prop run); {run}"
    )


def default_original(bundle: Bundle, km: KeyedModel) -> tuple[nn.Module | None, str]:
    """Where no --original is given: the module that is the original anyway, and how to name it."""
    # "the bundle's base": prop writes the original there, but without --original nothing checks it.
    if bundle.is_sealed:
        return bundle.loaded.module, "the bundle's base (a sealed bundle is written with the original's)"
    if bundle.manifest.get(C.M_CONFIG, {}).get("freeze_base"):
        return km.module, "the bundle's base (trained with --freeze-base: written with the original's)"
    return None, "no original checkpoint: pass --original (the bundle's base was trained with the key)"


def is_the_base(bundle: Bundle, km: KeyedModel, original: nn.Module) -> bool:
    """Whether ``original`` (--original) is a sealed bundle's base tensor for tensor (prop writes the base
    from it): the searches' rows and controls then run on one module, so each search runs once for both,
    not twice on two copies, each on its own share of the budget."""
    return bundle.is_sealed and equal_values(original, km.module)


def probe_context(bundle: Bundle, ctx: ProbeContext) -> ProbeContext:
    """``ctx`` for this bundle: a sealed bundle's keys are tried on its records, as prop run does, a key
    that opens none runs what prop run runs for it (the base), and its searches are their controls'."""
    if not bundle.is_sealed:
        return ctx
    shared = ctx.original is not None and same_tensors(ctx.original.module, ctx.km.module)
    given = {f.name: getattr(ctx, f.name) for f in fields(ctx)} | {"shared_searches": shared}
    return SealedContext(**given, records=bundle.records, base=bundle.loaded.module)


def controls_can_saturate(bundle: Bundle) -> bool:
    """Whether a search's control may reach the leakage ceiling while the search finds a leak. Not on a
    sealed bundle: its searches run on the public base, the control's own model."""
    return not bundle.is_sealed
