"""ACT's backbone memo (adapters/lerobot/act.py): what the audit and the reports compute once per frame
for every key. It must give what LeRobot's forward gives, and never serve a feature map the backbone
would no longer compute."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from prop_adapters.lerobot import POLICIES  # noqa: E402


@pytest.fixture
def act():
    from lerobot.configs.types import FeatureType, PolicyFeature

    from examples import lerobot_reach_task as reach

    torch.manual_seed(0)
    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (4,)),
              "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 32, 32))}  # fmt: skip
    policy, pre, post = reach.build_act(
        None, input_features=inputs, output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        vision_backbone="resnet18",
    )  # fmt: skip
    protocol = POLICIES["act"](policy.eval(), pre, post)
    x = {"observation.state": torch.randn(6, 4), "observation.image": torch.rand(6, 3, 32, 32)}
    x["observation.image"][3] = x["observation.image"][0]  # a frame seen twice: computed once
    return protocol, x


def counting(backbone, monkeypatch) -> list[int]:
    """The rows each call of the backbone's convolutions runs (its first layer, the stem conv)."""
    rows = []
    stem = backbone.conv1
    forward = stem.forward
    monkeypatch.setattr(stem, "forward", lambda img: (rows.append(len(img)), forward(img))[1])
    return rows


def test_the_memo_gives_lerobots_chunk_and_runs_each_frame_once(act, monkeypatch):
    protocol, x = act
    rows = counting(protocol.model.backbone, monkeypatch)
    with torch.no_grad():
        plain = protocol.chunk(x)
        assert rows == [6]
        with protocol.memo():
            first, again = protocol.chunk(x), protocol.chunk(x)
    assert rows == [6, 5]  # 5 distinct frames, once; the second chunk ran no backbone at all
    torch.testing.assert_close(first, plain, rtol=1e-5, atol=1e-6)
    assert torch.equal(again, first)


def test_a_changed_backbone_is_run_again_and_a_training_one_is_never_memoised(act):
    protocol, x = act
    backbone = protocol.model.backbone
    with protocol.memo():
        with torch.no_grad():
            protocol.chunk(x)
            next(backbone.parameters()).mul_(1.5)  # an optimizer step, in place
            changed = protocol.chunk(x)
        grad = protocol.chunk(x)  # gradients flow into the backbone: LeRobot's forward as it is
        grad.sum().backward()
    with torch.no_grad():
        torch.testing.assert_close(changed, protocol.chunk(x), rtol=1e-5, atol=1e-6)
    assert next(backbone.parameters()).grad is not None
    assert type(backbone).forward.__qualname__ == "IntermediateLayerGetter.forward"  # the memo is gone


def test_a_copy_sharing_the_weights_shares_the_memo(act, monkeypatch):
    """The audit's sealed searches and their controls run copies of the module that share its tensors."""
    import copy

    protocol, x = act
    model = protocol.model
    shared = {id(t): t for t in (*model.parameters(), *model.buffers())}
    twin = copy.deepcopy(model, shared)
    rows = counting(twin.backbone, monkeypatch)
    with torch.no_grad(), protocol.memo():
        protocol.chunk(x)
        protocol.policy.model = twin
        try:
            protocol.chunk(x)
        finally:
            protocol.policy.model = model
    assert rows == []  # the twin's frames came from the memo the original filled


def test_batch_copies_of_a_few_frames_are_digested_and_run_once_each(act, monkeypatch):
    """The audit runs keys as batch copies of its frames (``KeyedModel.run_keys``): each distinct frame is
    digested once and run once, and the chunk is LeRobot's."""
    from prop_adapters.lerobot import act as act_module

    protocol, x = act
    copies = {k: v.repeat(4, *[1] * (v.dim() - 1)) for k, v in x.items()}
    digests = []
    digest = act_module.row_digest
    monkeypatch.setattr(act_module, "row_digest", lambda *t: (digests.append(1), digest(*t))[1])
    rows = counting(protocol.model.backbone, monkeypatch)
    with torch.no_grad():
        plain = protocol.chunk(copies)
        with protocol.memo():
            got = protocol.chunk(copies)
    assert rows == [24, 5] and len(digests) == 5  # 5 distinct frames in 24 rows
    torch.testing.assert_close(got, plain, rtol=1e-5, atol=1e-6)


def test_distinct_rows_compares_rows_bit_for_bit():
    from prop_adapters.lerobot.act import distinct_rows

    nan = float("nan")
    x = torch.tensor([[0.0, 1.0], [-0.0, 1.0], [0.0, 1.0], [nan, 1.0], [1.0, 2.0], [1.0, 2.0]])
    rows, which = distinct_rows(x)
    raw = x.view(torch.int32)
    assert all(torch.equal(raw[rows[w]], raw[i]) for i, w in enumerate(which.tolist()))  # each row's twin
    assert rows.tolist() == sorted(set(rows.tolist())) and rows[0] == 0
    assert which[2] == which[0] and which[1] != which[0]  # 0.0 twice is one row; -0.0 is another
    assert which[5] == which[4] and len(rows) == 4
    assert distinct_rows(torch.zeros(1, 3))[0].tolist() == [0]
