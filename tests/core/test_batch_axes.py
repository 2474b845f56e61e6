"""Keys on sequence-first layers (per-layer batch axis), the deployed-path probe, and the LeRobot data
source's checks that run before lerobot is imported. No lerobot needed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from prop_cli.core.batch_axes import probe_batch_axes
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.datasources import load_data
from prop_cli.datasources.lerobot import parse_episodes, parse_list, split_path
from prop_cli.errors import PropError


class SeqFirst(nn.Module):
    """A transformer layer without batch_first (its FFN sees (S, B, D)) and a batch-first head."""

    def __init__(self) -> None:
        super().__init__()
        self.block = nn.TransformerEncoderLayer(8, 2, 16, dropout=0.0)
        self.head = nn.Linear(8, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x: (B, S, 8)
        return self.head(self.block(x.transpose(0, 1)).transpose(0, 1))


def keyed(names: list[str]) -> KeyedModel:
    torch.manual_seed(0)
    m = SeqFirst().eval()
    mods = dict(m.named_modules())
    enc = KeyEncoder(32, [mods[n].in_features for n in names], [16], 2.0)
    nn.init.normal_(enc.net[-1].weight, std=0.5)  # keys that do something
    return KeyedModel(m, enc, names)


def test_probe_finds_sequence_first_axes_and_rows_get_their_own_keys():
    names = ["block.linear1", "block.linear2", "head"]
    km = keyed(names)
    km.batch_axis = probe_batch_axes(km.module, names, lambda b: km.module(torch.randn(b, 4, 8)), "m")
    assert km.batch_axis == {"block.linear1": 1, "block.linear2": 1, "head": 0}
    x = torch.randn(3, 4, 8)
    codes = key_codes(np.random.default_rng(0).integers(0, 2, (3, 32)), "hashed")
    deltas = km.layer_deltas(codes)
    with torch.no_grad():
        rows = km.call_rows(deltas, km.module, x)
        one_by_one = torch.cat(
            [km.call_rows([d[i : i + 1] for d in deltas], km.module, x[i : i + 1]) for i in range(3)]
        )
        folded = torch.cat([km.fold(codes[i : i + 1])(x[i : i + 1]) for i in range(3)])
    assert torch.allclose(rows, one_by_one, atol=1e-5)
    assert torch.allclose(rows, folded, atol=1e-5)
    assert not torch.allclose(rows, km.module(x), atol=1e-3)  # the keys changed something


def test_probe_refuses_layers_the_deployed_path_never_calls():
    names = ["block.self_attn.out_proj", "head"]  # MultiheadAttention reads out_proj.weight directly
    km = keyed(names)
    with pytest.raises(PropError, match="block.self_attn.out_proj"):
        probe_batch_axes(km.module, names, lambda b: km.module(torch.randn(b, 4, 8)), "m")


def test_episode_selection_is_checked_against_the_root():
    assert parse_episodes("0-2,5", 6, "r") == [0, 1, 2, 5]
    with pytest.raises(PropError, match=r"episodes \[6\]"):
        parse_episodes("5-6", 6, "r")
    with pytest.raises(PropError, match="not a list of episodes"):
        parse_episodes("first", 6, "r")


def test_lerobot_root_checks_before_lerobot(tmp_path):
    root = tmp_path / "ds"
    (root / "meta").mkdir(parents=True)
    info = {"codebase_version": "v2.1", "features": {}, "fps": 25, "total_episodes": 3}
    (root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(PropError, match="codebase 'v2.1'"):
        load_data(root)
    info["codebase_version"] = "v3.0"
    (root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(PropError, match="episodes \\[3\\]"):
        load_data(f"{root}:episodes=1-3")
    with pytest.raises(PropError, match="no 'action' feature"):
        load_data(root)


def test_many_keys_at_once_fall_back_to_one_run_per_key_on_sequence_first_layers():
    names = ["block.linear1", "head"]
    km = keyed(names)
    km.batch_axis = {"block.linear1": 1}
    x = torch.randn(4, 3, 8)
    codes = key_codes(np.random.default_rng(1).integers(0, 2, (2, 32)), "hashed")
    with torch.no_grad():
        out = km.run_keys(x, km.layer_deltas(codes))
        ref = torch.stack([km.fold(codes[i : i + 1])(x) for i in range(2)])
    assert km.share_prefix is False
    assert torch.allclose(out, ref, atol=1e-5)


def test_lerobot_root_selections_split_in_any_order():
    assert split_path(Path("/d/r")) == (Path("/d/r"), None, None)
    assert split_path(Path("/d/r:episodes=0-3")) == (Path("/d/r"), "0-3", None)
    assert split_path(Path("/d/r:episodes=0-3:frames=5-9")) == (Path("/d/r"), "0-3", "5-9")
    assert split_path(Path("/d/r:frames=5-9:episodes=1")) == (Path("/d/r"), "1", "5-9")
    with pytest.raises(PropError, match="frame 99999999 is out of range"):
        parse_list("0-99999999", "r", "frame")


def test_the_probe_stops_once_every_layer_has_shown_its_input():
    names = ["block.linear1", "head"]
    km = keyed(names)
    calls = []

    def deployed(b: int) -> None:  # a sampler: the model several times, then something after
        for _ in range(3):
            calls.append(b)
            km.module(torch.randn(b, 4, 8))
        calls.append("after")

    assert probe_batch_axes(km.module, names, deployed, "m") == {"block.linear1": 1, "head": 0}
    assert calls == [2, 3]  # one pass per probe size: the head (the last keyed layer) ends it
