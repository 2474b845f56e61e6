"""Layer selection as in peft: exact names, dotted suffixes, regexes, all-linear; --exclude; the default."""

from __future__ import annotations

import json

import pytest
from torch import nn

from prop_cli.core.layers import ALL_LINEAR, default_layers, linear_layers, select_layers
from prop_cli.errors import PropError


class Policy(nn.Module):
    """Nested names like an SB3 actor-critic: two trunks, two heads."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp_extractor = nn.Module()
        self.mlp_extractor.policy_net = nn.Sequential(nn.Linear(4, 8), nn.Tanh(), nn.Linear(8, 8), nn.Tanh())
        self.mlp_extractor.value_net = nn.Sequential(nn.Linear(4, 8), nn.Tanh())
        self.norm = nn.LayerNorm(8)
        self.action_net = nn.Linear(8, 2)

    def forward(self, x):
        return self.action_net(self.norm(self.mlp_extractor.policy_net(x)))


NAMES = [
    "mlp_extractor.policy_net.0",
    "mlp_extractor.policy_net.2",
    "mlp_extractor.value_net.0",
    "action_net",
]


def test_linear_layers_in_module_order():
    assert [n for n, _ in linear_layers(Policy())] == NAMES


@pytest.mark.parametrize(
    "patterns,chosen",
    [
        (["action_net"], ["action_net"]),  # exact
        (["mlp_extractor.policy_net.2"], ["mlp_extractor.policy_net.2"]),  # exact, dotted
        (["policy_net.0"], ["mlp_extractor.policy_net.0"]),  # dotted suffix
        (["0"], ["mlp_extractor.policy_net.0", "mlp_extractor.value_net.0"]),  # suffix matches both trunks
        ([r".*policy_net\.\d+"], ["mlp_extractor.policy_net.0", "mlp_extractor.policy_net.2"]),  # regex
        (["action_net", "policy_net.0"], ["mlp_extractor.policy_net.0", "action_net"]),  # module order
        ([ALL_LINEAR], NAMES[:-1]),  # every linear layer but the output head
    ],
)
def test_patterns(patterns, chosen):
    assert select_layers(Policy(), patterns) == chosen


def test_suffix_is_dotted_and_regex_is_whole_name():
    # "net.0" is not a dotted suffix of "policy_net.0" and, as a regex, must match the whole name.
    with pytest.raises(PropError, match="matches no linear layer"):
        select_layers(Policy(), ["et.0"])
    assert select_layers(Policy(), ["value_net.0"]) == ["mlp_extractor.value_net.0"]
    assert select_layers(Policy(), [".*net"]) == ["action_net"]


def test_exclude_takes_the_same_forms():
    assert select_layers(Policy(), [ALL_LINEAR], exclude=["value_net.0"]) == NAMES[:2]
    assert select_layers(Policy(), None, exclude=[r".*value_net.*"]) == [
        "mlp_extractor.policy_net.2",
        "action_net",
    ]
    assert select_layers(Policy(), None, exclude=[ALL_LINEAR]) == ["action_net"]


def test_default_is_every_linear_layer_but_the_first():
    assert default_layers(NAMES) == NAMES[1:]
    assert select_layers(Policy()) == NAMES[1:]
    assert default_layers(["only"]) == ["only"]
    assert select_layers(nn.Sequential(nn.Linear(3, 2))) == ["0"]
    assert select_layers(nn.Sequential(nn.Linear(3, 2)), [ALL_LINEAR]) == ["0"]


@pytest.mark.parametrize(
    "patterns,exclude,match",
    [
        (["nope"], None, r"--layers 'nope' matches no linear layer or convolution; use .*action_net"),
        (["norm"], None, "matches no linear layer"),  # a module, but not a linear one
        (["(unclosed"], None, "not a valid regex"),
        (None, ["nope"], "--exclude 'nope' matches no linear layer"),
        (["action_net"], ["action_net"], "leave no layer to key"),
    ],
)
def test_errors_name_the_flag_and_list_layers(patterns, exclude, match):
    with pytest.raises(PropError, match=match):
        select_layers(Policy(), patterns, exclude)


def test_no_linear_layers():
    with pytest.raises(PropError, match="no nn.Linear"):
        select_layers(nn.Sequential(nn.ReLU()))


def test_cli_inspect_layers_and_exclude(cli, workdir):
    ckpt = workdir / "model.safetensors"  # linear layers "0", "2", "4"

    def keyed(*args: str) -> list[str]:
        r = cli("inspect", ckpt, *args, "--json")
        assert r.code == 0, r.err
        return [x["name"] for x in json.loads(r.out)["layers"] if x["keyed"]]

    assert keyed() == ["2", "4"]
    assert keyed("--layers", ALL_LINEAR) == ["0", "2"]
    assert keyed("--layers", "0", "--layers", "4") == ["0", "4"]
    assert keyed("--layers", "[0-9]", "--exclude", "4") == ["0", "2"]


def test_cli_bad_pattern_is_one_line(cli, workdir):
    r = cli("inspect", workdir / "model.safetensors", "--layers", "(")
    assert r.code == 2 and r.err.count("\n") == 1 and "not a valid regex" in r.err
