"""The keyed model: hooks leave the module alone, and every evaluation path computes Eq. 5."""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from tests.fixtures_arch import make_cnn as build_cnn


def _keyed(module: nn.Module, names: list[str], seed: int = 0) -> KeyedModel:
    mods = dict(module.named_modules())
    enc = KeyEncoder(32, [mods[n].in_features for n in names], [16], 2.0)
    torch.manual_seed(seed)
    nn.init.normal_(enc.net[-1].weight, std=0.5)  # a non-trivial delta for every key
    return KeyedModel(module, enc, names).eval()


def _mlp() -> nn.Sequential:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 8), nn.ReLU(), nn.Linear(8, 3))


def _codes(k: int) -> torch.Tensor:
    return key_codes(np.random.default_rng(0).integers(0, 2, (k, 32), dtype=np.uint8), "hashed")


def _reference(module: nn.Module, names: list[str], deltas: list[torch.Tensor], x: torch.Tensor):
    """Eq. 5 by hand: a copy of the module per key with W_i diag(delta_i)."""
    outs = []
    for k in range(deltas[0].shape[0]):
        m = copy.deepcopy(module)
        mods = dict(m.named_modules())
        with torch.no_grad():
            for name, d in zip(names, deltas):
                mods[name].weight.mul_(d[k][None, :])
            outs.append(m(x))
    return torch.stack(outs)


def test_no_key_is_the_module_and_names_are_unchanged():
    module = _mlp()
    before = list(module.state_dict())
    km = _keyed(module, ["2", "4"])
    assert list(km.module.state_dict()) == before
    x = torch.randn(5, 4)
    assert torch.equal(km(x), module(x))


def test_grid_rows_and_fold_agree_with_eq5():
    module = _mlp()
    names = ["2", "4"]
    km = _keyed(module, names)
    x, codes = torch.randn(6, 4), _codes(3)
    with torch.no_grad():
        deltas = km.layer_deltas(codes)
        ref = _reference(module, names, deltas, x)
        grid = km.run_keys(x, deltas)
        k, b = 3, 6
        rows = km.run_rows(x, deltas, torch.arange(k).repeat_interleave(b), torch.arange(b).repeat(k))
        folded = torch.stack([km.fold(codes[i : i + 1])(x) for i in range(k)])
    assert km.share_prefix is True
    assert torch.allclose(grid, ref, atol=1e-6)
    assert torch.allclose(rows.view(k, b, -1), ref, atol=1e-6)
    assert torch.allclose(folded, ref, atol=1e-6)
    # the folded copy is a plain module: no hooks of ours, and the original weights are untouched
    assert torch.equal(km(x), module(x))


def test_null_rows_are_the_base():
    km = _keyed(_mlp(), ["2"])
    x = torch.randn(4, 4)
    with torch.no_grad():
        deltas = km.layer_deltas(_codes(2), null=1)
        out = km.run_keys(x, deltas)
    assert torch.allclose(out[-1], km(x), atol=1e-6)


class _BatchMixing(nn.Module):
    """Rows are not independent after the keyed layer (a batch mean): sharing must be refused."""

    def __init__(self) -> None:
        super().__init__()
        self.a, self.b = nn.Linear(4, 8), nn.Linear(8, 2)

    def forward(self, x):
        h = torch.relu(self.a(x))
        h = self.b(h)
        return h - h.mean(0, keepdim=True)


def test_batch_mixing_module_falls_back_to_gathering_at_the_input():
    torch.manual_seed(0)
    module = _BatchMixing()
    km = _keyed(module, ["b"])
    x, codes = torch.randn(5, 4), _codes(3)
    with torch.no_grad():
        deltas = km.layer_deltas(codes)
        out = km.run_keys(x, deltas)
        expected = []
        for k in range(3):  # each key on its own batch, as a user would run it
            expected.append(km.fold(codes[k : k + 1])(x))
    assert km.share_prefix is False
    assert torch.allclose(out, torch.stack(expected), atol=1e-5)


def test_cnn_with_linear_head_shares_the_conv_prefix():
    module = build_cnn()
    names = [n for n, m in module.named_modules() if isinstance(m, nn.Linear)]
    km = _keyed(module, names)
    x = torch.randn(3, *module.input_shape)
    with torch.no_grad():
        deltas = km.layer_deltas(_codes(2))
        out = km.run_keys(x, deltas)
        folded = torch.stack([km.fold(_codes(2)[i : i + 1])(x) for i in range(2)])
    assert km.share_prefix is True
    assert torch.allclose(out, folded, atol=1e-5)


class _ResidualAfterKey(nn.Module):
    """The keyed layer's output is added to an unkeyed path (as in a transformer's residual): the prefix
    cannot be shared, but rows are independent, so keys run as copies of the batch in one forward."""

    def __init__(self) -> None:
        super().__init__()
        self.a, self.b = nn.Linear(4, 4), nn.Linear(4, 2)

    def forward(self, x):
        return self.b(x + self.a(x))


def test_independent_rows_run_every_key_in_one_forward():
    torch.manual_seed(0)
    module = _ResidualAfterKey()
    km = _keyed(module, ["a"])
    x, codes = torch.randn(5, 4), _codes(3)
    calls = []
    module.b.register_forward_pre_hook(lambda m, args: calls.append(args[0].shape[0]))
    with torch.no_grad():
        deltas = km.layer_deltas(codes)
        out = km.run_keys(x, deltas)
        expected = torch.stack([km.fold(codes[k : k + 1])(x) for k in range(3)])
    assert km.share_prefix is False and km.rows_independent is True
    assert calls[-4] == 15  # the audit's call: 3 keys x 5 samples in one forward (then 3 folds)
    assert torch.allclose(out, expected, atol=1e-5)


def test_batch_mixing_module_is_not_run_as_copies():
    torch.manual_seed(0)
    km = _keyed(_BatchMixing(), ["b"])
    with torch.no_grad():
        km.run_keys(torch.randn(5, 4), km.layer_deltas(_codes(3)))
    assert km.rows_independent is False


def test_on_another_module_keeps_batch_axes_and_remove_hooks_detaches():
    module = _mlp()
    km = _keyed(module, ["2"])
    km.batch_axis = {"2": 1}
    other = km.on(copy.deepcopy(module))
    assert other.batch_axis == {"2": 1} and other.encoder is km.encoder
    km.remove_hooks()
    assert not dict(module.named_modules())["2"]._forward_pre_hooks


def test_hashed_codes_are_shake256_of_the_domain_and_key():
    """The prepared-hash fast path gives the definition's bytes: SHAKE-256(domain || packed key)."""
    import hashlib

    bits = np.random.default_rng(3).integers(0, 2, (5, 128), dtype=np.uint8)
    got = key_codes(bits, "hashed")
    for row, code in zip(bits, got):
        digest = hashlib.shake_256(b"prop/key-code/v1" + np.packbits(row).tobytes()).digest(16)
        want = np.unpackbits(np.frombuffer(digest, np.uint8)).astype(np.float32) * 2 - 1
        assert np.array_equal(code.numpy(), want)
    assert torch.equal(key_codes(bits[0], "hashed"), got[:1])


def test_joined_deltas_give_the_per_layer_paths_outputs_and_gradients_bit_for_bit():
    """layer_deltas(null=1) returns every layer's delta as blocks of one tensor, and run_rows gathers them
    at once (the small-model step); outputs and every gradient, a term on the deltas themselves included,
    are those of one gather per layer of separately built deltas."""
    from prop_cli.core.keyed_model import JoinedDeltas

    module = _mlp()
    km = _keyed(module, ["2", "4"])
    codes = _codes(5)
    x = torch.randn(6, 4)
    key_index = torch.tensor([0, 0, 1, 2, 3, 4, 5, 5, 5])
    sample_index = torch.tensor([0, 1, 2, 3, 4, 5, 0, 2, 4])

    def run(joined: bool) -> tuple[torch.Tensor, list[torch.Tensor]]:
        km.zero_grad(set_to_none=True)
        if joined:
            deltas = km.layer_deltas(codes, null=1)
            assert isinstance(deltas, JoinedDeltas) and [d.shape for d in deltas] == [(6, 8), (6, 8)]
        else:
            deltas = [torch.cat([p, p.new_ones(1, p.shape[1])]) for p in km.encoder(codes)]
        out = km.run_rows(x, deltas, key_index, sample_index)
        pull = sum((d[1:3] - 1).pow(2).sum() for d in deltas)  # a second path into the same deltas
        (out.pow(2).sum() + pull).backward()
        return out.detach(), [p.grad.clone() for p in km.parameters()]

    out_joined, grads_joined = run(True)
    out_layers, grads_layers = run(False)
    assert torch.equal(out_joined, out_layers)
    assert all(torch.equal(a, b) for a, b in zip(grads_joined, grads_layers))
    assert all(g.abs().sum() > 0 for g in grads_joined[: len(list(km.encoder.parameters()))])
    ref = _reference(module, ["2", "4"], km.layer_deltas(codes, null=1), x)  # and still Eq. 5
    torch.testing.assert_close(out_joined, ref[key_index, sample_index])
