"""The activations prop can rebuild exactly: parameter-free torch modules, built with no arguments.

That is how SB3's ``create_mlp`` builds them (``activation_fn()``), so a rebuilt SB3 network equals
the original exactly; a plain MLP state dict names its activation in metadata or ``--activation``.
An activation outside this table is refused: guessing another one would silently change the network.
"""

from __future__ import annotations

from torch import nn

from prop_cli.errors import PropError

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
    "leaky_relu": nn.LeakyReLU,
    "gelu": nn.GELU,
    "silu": nn.SiLU,
    "softplus": nn.Softplus,
    "sigmoid": nn.Sigmoid,
    "selu": nn.SELU,
    "celu": nn.CELU,
    "mish": nn.Mish,
    "hardswish": nn.Hardswish,
    "hardsigmoid": nn.Hardsigmoid,
    "hardtanh": nn.Hardtanh,
    "relu6": nn.ReLU6,
    "softsign": nn.Softsign,
    "tanhshrink": nn.Tanhshrink,
    "logsigmoid": nn.LogSigmoid,
}
# torch class name (what SB3 writes as str(activation_fn)) -> our name.
BY_CLASS_NAME = {cls.__name__: name for name, cls in ACTIVATIONS.items()}
# Stateless instances for forward passes that apply an activation by name.
_INSTANCES = {name: cls() for name, cls in ACTIVATIONS.items()}


def check(name: str, where: str) -> str:
    """The canonical name, or a PropError listing what prop rebuilds."""
    act = name.strip().lower()
    if act not in ACTIVATIONS:
        raise PropError(f"{where}: unknown activation '{act}'", f"use one of: {', '.join(ACTIVATIONS)}")
    return act


def make(name: str) -> nn.Module:
    return ACTIVATIONS[name]()


def apply(name: str, x):
    return _INSTANCES[name](x)
