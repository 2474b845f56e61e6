"""Payload kinds are classes (core.payload.KINDS): one per name the manifest records, the rank rule once."""

import pytest
import torch

from prop_cli.config import PAYLOAD_KINDS, PersonalizeConfig
from prop_cli.core.payload import KINDS, Payload, PayloadSpec, payload_kind
from prop_cli.errors import PropError

LAYER = {"name": "fc", "in_features": 3, "out_features": 2}


def test_every_configurable_kind_is_a_class():
    assert tuple(KINDS) == PAYLOAD_KINDS
    assert all(KINDS[name].name == name for name in KINDS)


@pytest.mark.parametrize("name", PAYLOAD_KINDS)
def test_the_rank_rule(name):
    kind = payload_kind(name)
    assert kind.rank(4) == (4 if name in ("lora", "peft-lora") else 0)


def test_an_unknown_kind_is_one_line():
    with pytest.raises(PropError, match="--payload 'qlora' is unknown"):
        payload_kind("qlora")
    with pytest.raises(PropError, match="--payload"):
        PersonalizeConfig.of(seal=True, payload="qlora")


@pytest.mark.parametrize("name", PAYLOAD_KINDS)
def test_each_kind_starts_at_the_base(name):
    spec = PayloadSpec(name, [LAYER], payload_kind(name).rank(2)).validate()
    p = Payload(spec, torch.Generator().manual_seed(0))
    w = torch.randn(2, 3)
    assert torch.equal(p.weight("fc", w), w)


def test_kinds_differ_where_they_should():
    w = torch.randn(2, 3)
    lora = Payload(PayloadSpec("lora", [LAYER], 2))
    peft = Payload(PayloadSpec("peft-lora", [LAYER], 2))
    with torch.no_grad():
        for p in (lora, peft):
            p.tensor("fc", "lora_b").fill_(0.5)
        lora.tensor("fc", "delta").fill_(2.0)
        lora.tensor("fc", "lora_a").copy_(peft.tensor("fc", "lora_a"))
    update = 0.5 * torch.ones(2, 2) @ peft.tensor("fc", "lora_a")
    assert torch.allclose(peft.weight("fc", w), w + update)
    assert torch.allclose(lora.weight("fc", w), (w + update) * 2.0)
    assert KINDS["full"].changes_bias and not KINDS["lora"].changes_bias
    assert KINDS["peft-lora"].peft_lora and not KINDS["lora"].peft_lora


@pytest.mark.parametrize("name", ["lora", "full"])
def test_a_folded_payload_copies_only_the_keyed_layers(name):
    from torch import nn

    torch.manual_seed(0)
    module = nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2)).eval().requires_grad_(False)
    layer = {"name": "2", "in_features": 4, "out_features": 2}
    p = Payload(PayloadSpec(name, [layer], payload_kind(name).rank(2)), torch.Generator().manual_seed(0))
    with torch.no_grad():
        for t in p.parameters():
            t.add_(0.3)
    folded = p.fold(module)
    assert folded[0].weight is module[0].weight and folded[0].bias is module[0].bias  # shared
    assert folded[2].weight is not module[2].weight  # the keyed layer: its own copy, the payload in it
    x = torch.randn(5, 3)
    with p.attached(module), torch.no_grad():
        attached = module(x)
    with torch.no_grad():
        assert torch.allclose(folded(x), attached, atol=1e-6) and not torch.allclose(module(x), attached)


@pytest.mark.parametrize("name", PAYLOAD_KINDS)
def test_the_kind_says_what_it_adds_to_a_bias(name):
    """Issue 41: runners (the sealed ONNX export) ask the kind for the bias delta, not a part name."""
    spec = PayloadSpec(name, [LAYER], payload_kind(name).rank(2)).validate()
    p = Payload(spec, torch.Generator().manual_seed(0))
    delta = p.bias_delta("fc")
    assert (delta is not None) == KINDS[name].changes_bias
    if delta is not None:
        with torch.no_grad():
            p.tensor("fc", "bias_delta").fill_(0.25)
        assert torch.equal(p.bias_delta("fc"), torch.full((2,), 0.25))
