"""Plain MLP state dicts (any key prefix) -> a module with exactly the checkpoint's names.

The layer order is inferred from the names and shapes; the activation comes from ``--activation``,
else the file's ``activation`` metadata, else relu (a state dict does not record it).
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import nn

from prop_cli.core.rules import BOOL, DIM, Rule, list_of, text
from prop_cli.errors import PropError, plural

from . import activations
from .base import Adapter, CheckpointOptions, LoadedModel, finish
from .weights import is_weights_file, read_weights

DEFAULT_ACTIVATION = "relu"
ARCH_HINT = "if it is not a plain MLP, pass its class with --arch package.module:factory"
# Past this many tried orderings we stop and call the chain ambiguous rather than hang.
_MAX_SEARCH = 100_000


class ChainMLP(nn.Module):
    """Linears applied in a given order with an activation between them (not after the last).

    Layers live at their checkpoint paths ("actor.fc1" is child "fc1" of a plain container
    "actor"), so ``state_dict()`` names are exactly the checkpoint's.
    """

    def __init__(self, layers: list[str], sizes: list[int], bias: dict[str, bool], activation: str) -> None:
        super().__init__()
        self.activation = activations.check(activation, "model spec")
        self.layer_paths = list(layers)
        for i, path in enumerate(layers):
            parent = self
            *containers, leaf = path.split(".")
            for part in containers:
                child = parent._modules.get(part)
                if child is None:
                    child = nn.Module()
                    parent.add_module(part, child)
                elif isinstance(child, nn.Linear):
                    raise PropError(f"layer '{path}' is nested inside linear layer '{part}'", ARCH_HINT)
                parent = child
            if leaf in parent._modules:
                raise PropError(f"layer '{path}' clashes with another module name", ARCH_HINT)
            parent.add_module(leaf, nn.Linear(sizes[i], sizes[i + 1], bias=bias[path]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.layer_paths) - 1
        # Looked up each call (cheap) so copies and swapped submodules are always honoured.
        for i, p in enumerate(self.layer_paths):
            x = self.get_submodule(p)(x)
            if i < last:
                x = activations.apply(self.activation, x)
        return x


def natural_key(name: str) -> list:
    """Sort key comparing digit runs as numbers: 'fc2' < 'fc10', 'net.2' < 'net.10'."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name) if t]


def _layers_from_tensors(
    tensors: dict[str, torch.Tensor], path: str
) -> tuple[dict[str, tuple[int, int]], dict[str, bool]]:
    """Group tensors into linear layers {path: (in, out)}; refuse anything that is not one."""
    weights: dict[str, torch.Tensor] = {}
    biases: dict[str, torch.Tensor] = {}
    other: list[str] = []
    for name, t in tensors.items():
        prefix, _, leaf = name.rpartition(".")
        if leaf == "weight" and t.ndim == 2:
            weights[prefix] = t
        elif leaf == "bias" and t.ndim == 1:
            biases[prefix] = t
        else:
            other.append(f"{name} {tuple(t.shape)}")
    if not weights:
        raise PropError(
            f"no linear layers in {path} (no 2-D '.weight' tensors)",
            "prop keys nn.Linear layers; " + ARCH_HINT,
        )
    if other:
        shown = ", ".join(other[:3]) + (f" (+{len(other) - 3} more)" if len(other) > 3 else "")
        raise PropError(
            f"{path} is not a plain MLP: tensors {shown} are not linear weights or biases",
            ARCH_HINT,
        )
    orphans = sorted(set(biases) - set(weights))
    if orphans:
        raise PropError(
            f"{path} is not a plain MLP: bias '{orphans[0]}.bias' has no matching weight", ARCH_HINT
        )
    if "" in weights:
        raise PropError(
            f"{path} holds a bare layer ('weight'/'bias' without a module name)",
            "save it inside a container, e.g. nn.Sequential(layer).state_dict(), or use --arch",
        )
    dims: dict[str, tuple[int, int]] = {}
    for p, w in weights.items():
        if not w.is_floating_point():
            raise PropError(f"{path}: '{p}.weight' has dtype {w.dtype}, not a float", ARCH_HINT)
        out_f, in_f = w.shape
        b = biases.get(p)
        if b is not None and b.shape[0] != out_f:
            raise PropError(
                f"{path} is not a plain MLP: '{p}.bias' has {plural(b.shape[0], 'entry', 'entries')} but "
                f"'{p}.weight' has {out_f} outputs",
                ARCH_HINT,
            )
        dims[p] = (int(in_f), int(out_f))
    return dims, {p: p in biases for p in weights}


def _is_chain(order: list[str], dims: dict[str, tuple[int, int]]) -> bool:
    return all(dims[a][1] == dims[b][0] for a, b in zip(order[:-1], order[1:], strict=True))


def _find_chains(dims: dict[str, tuple[int, int]], limit: int = 2) -> tuple[list[list[str]], bool]:
    """Up to ``limit`` orderings that chain all layers, and whether the search was cut short."""
    # A chain is an Euler trail through the dims: settle the impossible case without searching.
    balance: dict[int, int] = {}
    for i, o in dims.values():
        balance[i] = balance.get(i, 0) + 1
        balance[o] = balance.get(o, 0) - 1
    if sorted(v for v in balance.values() if v) not in ([], [-1, 1]):
        return [], False
    names = sorted(dims, key=natural_key)
    found: list[list[str]] = []
    steps = 0

    def extend(order: list[str], left: list[str]) -> bool:
        nonlocal steps
        steps += 1
        if steps > _MAX_SEARCH:
            return False
        if not left:
            found.append(list(order))
            return len(found) < limit
        want = dims[order[-1]][1] if order else None
        for i, n in enumerate(left):
            if want is None or dims[n][0] == want:
                order.append(n)
                keep_going = extend(order, left[:i] + left[i + 1 :])
                order.pop()
                if not keep_going:
                    return False
        return True

    extend([], names)
    return found, steps > _MAX_SEARCH


def infer_chain(dims: dict[str, tuple[int, int]], path: str) -> list[str]:
    """Layer order: natural name order if its dims chain, else the one order the dims allow."""
    natural = sorted(dims, key=natural_key)
    if _is_chain(natural, dims):
        return natural
    chains, cut = _find_chains(dims)
    listing = ", ".join(f"{n} {dims[n][0]}->{dims[n][1]}" for n in natural[:8])
    listing += f", ... ({len(natural)} layers)" if len(natural) > 8 else ""
    if len(chains) == 1 and not cut:
        return chains[0]
    if not chains and not cut:
        raise PropError(
            f"{path} is not a plain MLP: its linear layers ({listing}) do not form one chain "
            "(branches or skip connections?)",
            ARCH_HINT,
        )
    raise PropError(
        f"the layer chain of {path} is ambiguous: its names are not in layer order and the "
        f"shapes ({listing}) allow more than one order",
        "rename the layers so they sort in order (e.g. 0., 1., 2.), or pass the class with "
        "--arch package.module:factory",
    )


def spec_shapes(spec: dict) -> dict[str, tuple[int, ...]]:
    """The tensors (name -> shape) of the MLP ``spec`` describes, computed, not allocated."""
    layers, sizes, shapes = spec["layers"], spec["sizes"], {}
    for i, path in enumerate(layers):
        shapes[f"{path}.weight"] = (int(sizes[i + 1]), int(sizes[i]))
        if spec["bias"][path]:
            shapes[f"{path}.bias"] = (int(sizes[i + 1]),)
    return shapes


def check_fits(spec: dict, weights: dict[str, torch.Tensor], source: str) -> None:
    """The spec describes exactly the weights' tensors, checked before the module is built: a spec's
    sizes (a bundle's manifest) allocate nothing the weights file does not hold."""
    want = spec_shapes(spec)
    got = {k: tuple(v.shape) for k, v in weights.items()}
    if got == want:
        return
    order = [n for p in spec["layers"] for n in (f"{p}.weight", f"{p}.bias")]
    name = next(n for n in order + sorted(got, key=natural_key) if got.get(n) != want.get(n))
    shown = {d: str(x[name]) if name in x else "absent" for d, x in (("file", got), ("spec", want))}
    raise PropError(
        f"weights in {source} do not match the MLP its model spec describes (tensor '{name}': "
        f"{shown['file']} in the weights, {shown['spec']} in model.layers and model.sizes); "
        "nothing was built",
        "the file or its manifest was modified, or they belong to another model; re-create it",
    )


def build(spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
    check_fits(spec, weights, source)
    module = ChainMLP(spec["layers"], spec["sizes"], spec["bias"], spec["activation"])
    try:
        module.load_state_dict(weights, strict=True)
    except RuntimeError as e:
        raise PropError(
            f"weights in {source} do not match the MLP described by its spec ({e})".replace("\n", " "),
            "the file was modified or belongs to another model; re-create it",
        ) from None
    return LoadedModel(
        module=finish(module),
        spec=spec,
        dtypes={k: v.dtype for k, v in weights.items()},
        input_shape=(spec["sizes"][0],),
        source=source,
    )


class MLPAdapter(Adapter):
    name = "mlp"
    summary = (
        "a plain MLP state dict: .safetensors or .pt/.pth/.bin, layer order inferred, "
        "activation from --activation or the file's metadata (default relu)"
    )
    options = ("activation",)
    manifest_fields = {
        "layers": list_of(text(), 1),
        "sizes": list_of(DIM, 2),
        "bias": Rule((dict,), "an object of layer name -> true/false", values=BOOL, key_ok=bool),
        "activation": text(),
    }

    @staticmethod
    def check_spec(spec: dict) -> tuple[str, str] | None:
        if len(spec["sizes"]) != len(spec["layers"]) + 1:
            return "sizes", "must have one entry more than model.layers"
        return None

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return options.arch is None and is_weights_file(path)

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        tensors, metadata = read_weights(path)
        dims, bias = _layers_from_tensors(tensors, str(path))
        order = infer_chain(dims, str(path))
        if options.activation is not None:
            act = activations.check(options.activation, "--activation")
        else:
            act = activations.check(
                metadata.get("activation", DEFAULT_ACTIVATION), f"metadata 'activation' of {path}"
            )
        spec = {
            "adapter": self.name,
            "layers": order,
            "activation": act,
            "bias": {p: bias[p] for p in order},
            "sizes": [dims[order[0]][0]] + [dims[p][1] for p in order],
        }
        return build(spec, tensors, str(path))

    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        return build(spec, weights, source)
