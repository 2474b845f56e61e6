"""Where the batch is in each keyed layer's input, and whether the layer runs at all when deployed.

KeyedModel scales row r of a keyed layer's input by that row's delta, so it must know which axis holds
the rows. Batch-first layers take (B, ..., D); sequence-first transformer layers (PyTorch's
nn.Transformer* without batch_first, used by LeRobot's ACT) take (S, B, D). The axis is found by
running the deployed path at two batch sizes and taking the one axis whose size follows the batch.

The same run shows which chosen layers are never called through their forward there: a key on them
would do nothing the user deploys. nn.MultiheadAttention reads ``out_proj.weight`` directly (its
pre-hooks never fire) and ACT's VAE encoder runs only in training; both are refused by name.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from prop_cli.errors import PropError

# Two batch sizes: an axis that is one at the first and the other at the second follows the batch (a
# fixed axis cannot be both). Small, as each is a run of the deployed path (a real-size VLA's prefix).
PROBE_SIZES = (2, 3)


@torch.no_grad()
def probe_batch_axes(
    module: nn.Module, layer_names: list[str], deployed: Callable[[int], object], what: str
) -> dict[str, int]:
    """``deployed(b)`` runs the deployed path on b rows; returns each layer's batch axis (name -> axis)."""
    mods = dict(module.named_modules())
    shapes: dict[str, list[tuple[int, ...]]] = {n: [] for n in layer_names}
    handles = []
    for name in layer_names:

        def record(mod, args, name=name):
            shapes[name].append(tuple(args[0].shape))
            if all(shapes.values()):  # every layer seen once: the rest of the run tells nothing more
                raise _Seen

        handles.append(mods[name].register_forward_pre_hook(record))
    try:
        per_size = []
        for b in PROBE_SIZES:
            for s in shapes.values():
                s.clear()
            try:
                deployed(b)
            except _Seen:  # a sampler's later steps (SmolVLA: 9 of 10) and layers after the last keyed one
                pass
            per_size.append({n: list(s) for n, s in shapes.items()})
    finally:
        for h in handles:
            h.remove()
    silent = [n for n in layer_names if not per_size[0][n]]
    if silent:
        raise PropError(
            f"{what}: keyed layers {', '.join(silent)} are not called when the policy acts "
            "(attention out_proj is read directly; ACT's VAE encoder runs only in training)",
            "drop them from --layers; `prop inspect` shows the default choice",
        )
    axes = {}
    small, large = PROBE_SIZES
    for n in layer_names:
        a, b = per_size[0][n][0], per_size[1][n][0]
        found = [i for i in range(len(a) - 1) if a[i] == small and b[i] == large]
        if len(found) != 1:
            raise PropError(
                f"{what}: cannot tell the batch axis of keyed layer {n} (input shapes {a} and {b})",
                "key other layers with --layers",
            )
        axes[n] = found[0]
    return axes


class _Seen(Exception):
    """Raised from a probe hook once every keyed layer has shown its input: stops the deployed run."""
