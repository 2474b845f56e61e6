"""A tiny user-defined model for the --arch tests: a CNN with a linear head."""

from __future__ import annotations

from torch import nn


class TinyCNN(nn.Module):
    input_shape = (1, 6, 6)

    def __init__(self, hidden: int = 8, classes: int = 3) -> None:
        super().__init__()
        self.features = nn.Sequential(nn.Conv2d(1, 4, 3), nn.ReLU(), nn.Flatten())
        self.head = nn.Sequential(nn.Linear(4 * 4 * 4, hidden), nn.ReLU(), nn.Linear(hidden, classes))

    def forward(self, x):
        return self.head(self.features(x))


def make_cnn(hidden: int = 8, classes: int = 3) -> nn.Module:
    return TinyCNN(hidden=hidden, classes=classes)


def make_conv_only() -> nn.Module:
    return nn.Sequential(nn.Conv2d(1, 2, 3))


def make_bn_only() -> nn.Module:
    return nn.Sequential(nn.BatchNorm1d(2))


def not_a_module() -> dict:
    return {"hello": 1}
