"""A sealed bundle's audit does only the work whose answer is not already known (issue 40 item 3): keys
that open no record score the base once, encoders with a zero head are not run, and a search (or few-shot
delta fit) whose model is its control's runs once. The rows and verdicts are those of the audit without
these shortcuts; a key that opens a record still runs its payload."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest
import torch

from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.attack import target
from prop_cli.attack.probes import sealed_context
from prop_cli.attack.probes.base import ProbeContext, Reference
from prop_cli.bundle import load_bundle
from prop_cli.config import AuditSettings, PersonalizeConfig
from prop_cli.core.key_files import read_key_file
from prop_cli.core.keyed_model import KeyEncoder
from prop_cli.datasources import load_data
from tests.conftest import write_keys, write_user_data

audit_mod = importlib.import_module("prop_cli.attack.audit")  # the package exports its function `audit`

# Every default probe, small. 300 rows and 256 samples: 44 rows outside the sample, so T3 runs k = 1..16.
SMALL = dict(random=64, per_distance=8, hamming=[1, 2], restarts=4, search_steps=10, blackbox=2048,
             fewshot_restarts=4, fewshot_steps=10, samples=256)  # fmt: skip
FIGURES = ("name", "probe", "kind", "keys", "leakage", "fidelity", "beyond", "gate")


@pytest.fixture(scope="module")
def sealed(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("sealed-shortcuts")
    rng = np.random.default_rng(7)
    write_user_data(d, 300, rng)
    write_keys(d, ("k.bin", "stranger.bin"), rng)
    me = KeySource(read_key_file(d / "k.bin"), "file")
    personalize_checkpoint(str(d / "model.safetensors"), [(d / "mine.npz", me)], d / "sealed.prop",
                           PersonalizeConfig.of(steps=200, seal=True))  # fmt: skip
    return d


def _audit(d: Path, *keys: str) -> dict:
    bundle = load_bundle(d / "sealed.prop")
    data = load_data(d / "mine.npz")
    bits = [read_key_file(d / k, bundle.key_bits) for k in keys]
    return audit_mod.audit(bundle, data, bits, AuditSettings(**SMALL))


def _figures(report: dict) -> list[dict]:
    def row(g: dict) -> dict:
        out = {f: g.get(f) for f in FIGURES}
        c = g["control"] or {}
        out["control"] = {f: c.get(f) for f in ("available", "keys", "leakage", "fidelity")}
        return out

    return [row(g) for g in report["groups"]]


def _without_shortcuts(monkeypatch) -> None:
    """The audit as it ran before: every encoder run, a wrong key's outputs computed from the bundle's base
    module itself, and a search or fit shared between a row and its control only when complete."""
    monkeypatch.setattr(KeyEncoder, "blank", lambda self: False)
    monkeypatch.setattr(sealed_context, "runs_as", lambda base, km: False)
    real = target.probe_context

    def unshared(bundle, ctx):
        out = real(bundle, ctx)
        out.shared_searches = False
        return out

    monkeypatch.setattr(target, "probe_context", unshared)


def test_the_sealed_audit_gives_the_same_rows_and_verdicts_with_its_shortcuts(sealed, monkeypatch):
    fast = _audit(sealed, "k.bin", "stranger.bin")
    with monkeypatch.context() as m:
        _without_shortcuts(m)
        slow = _audit(sealed, "k.bin", "stranger.bin")
    assert fast["coverage"] == slow["coverage"] == {"budget_seconds": None, "not_tried": [], "cut_short": []}
    assert _figures(fast) == _figures(slow)
    assert fast["user"] == slow["user"] and fast["user"]["leakage"] > 0.5  # the user's record ran
    names = {g["name"] for g in fast["groups"]}
    assert {"null", "random", "blackbox", "structure", "relaxed", "latent", "fewshot k=1", "key 2"} <= names
    said = {g["name"]: g["shortcuts"] for g in fast["groups"]}
    assert any("opens no record" in s for s in said["random"])
    assert any("head is zero" in s for s in said["structure"])
    assert any("same model as control" in s for s in said["latent"])
    assert any("same model as control" in s for s in said["fewshot k=1"])
    assert not any("same model as control" in s for g in slow["groups"] for s in g["shortcuts"])
    for g in fast["groups"]:  # searches on the base: the row is its control's, beyond 0
        if g["probe"] == "latent" or (g["probe"] == "fewshot" and g["kind"] == "search"):
            assert g["leakage"]["worst"] == g["control"]["leakage"]["worst"] and g["beyond"] == 0, g["name"]


def test_the_search_on_the_base_runs_once(sealed, monkeypatch):
    """T2's search on a sealed bundle: relaxed's control, latent's row and latent's control are one run."""
    from prop_cli.attack.probes import latent

    calls = []
    real = latent._search
    monkeypatch.setattr(latent, "_search", lambda ctx: calls.append(1) or real(ctx))
    _audit(sealed, "k.bin")
    assert len(calls) == 1
    calls.clear()
    with monkeypatch.context() as m:
        _without_shortcuts(m)
        _audit(sealed, "k.bin")
    assert len(calls) == 1  # ran to its end: shared before too; a search cut short is shared only now


def test_a_key_that_opens_a_record_runs_its_payload_and_a_wrong_key_is_the_base_bit_for_bit(sealed):
    bundle = load_bundle(sealed / "sealed.prop")
    km = target.attacked_model(bundle, torch.device("cpu"))
    data = np.load(sealed / "mine.npz")
    x = torch.from_numpy(data["x"][:32])
    with torch.inference_mode():
        base = bundle.loaded.module.eval()(x)  # what prop run runs for a key that opens nothing
    ref = Reference(x, base.clone(), torch.from_numpy(data["y"][:32]), bundle.task)
    mine, other = (read_key_file(sealed / k, bundle.key_bits) for k in ("k.bin", "stranger.bin"))
    ctx = target.probe_context(bundle, ProbeContext(km, ref, AuditSettings(), [mine], bundle.key_encoding))
    assert sealed_context.runs_as(bundle.loaded.module, km)  # checked, then used: no forward for it
    got = ctx.probe_keys(np.stack([mine, other]), "t", null=1, outputs=True)["outputs"]
    assert torch.equal(got[1], base) and torch.equal(got[2], base)
    opened = bundle.records.open(mine)
    with torch.inference_mode():
        folded = opened.payload.fold(km.module)(x)
    assert torch.equal(got[0], folded) and not torch.allclose(got[0], base)
    # Where the check fails (a hook on the base), a wrong key runs the base module itself: the same outputs.
    hook = bundle.loaded.module.register_forward_pre_hook(lambda m, a: None)
    try:
        assert not sealed_context.runs_as(bundle.loaded.module, km)
        fresh = target.probe_context(
            bundle, ProbeContext(km, ref, AuditSettings(), [mine], bundle.key_encoding)
        )
        assert torch.equal(fresh.probe_keys(other, "t", outputs=True)["outputs"][0], base)
    finally:
        hook.remove()


def test_a_blank_encoder_is_told_from_a_trained_one():
    enc = KeyEncoder(16, [4, 3], [8], 2.0)
    assert enc.blank()
    codes = torch.where(torch.randn(5, 16) >= 0, 1.0, -1.0)
    assert all(torch.equal(d, torch.ones_like(d)) for d in enc(codes))
    with torch.no_grad():
        enc.net[-1].bias[2] = 1e-30
    assert not enc.blank()
    with torch.no_grad():
        enc.net[-1].bias.zero_()
        enc.net[0].weight[0, 0] = float("inf")  # 0 x inf is not 0: not blank
    assert not enc.blank()


def test_a_search_the_budget_cuts_short_is_still_run_once_for_the_row_and_its_controls(sealed, monkeypatch):
    """Under a budget the search on the base is cut short; it is one computation for relaxed's control,
    latent's row and latent's control, so it runs once and the row equals its control (beyond 0), where
    before each ran its own share (and the last ran on nothing)."""
    import prop_cli.attack.probes.base as base
    from prop_cli.attack.probes import latent

    calls = []
    real = latent._search
    monkeypatch.setattr(latent, "_search", lambda ctx: calls.append(1) or real(ctx))

    def budgeted(shared: bool) -> dict:
        clock = iter(range(10**7))  # every look at the clock moves it a second
        with monkeypatch.context() as m:
            m.setattr(base.time, "perf_counter", lambda: float(next(clock)))
            m.setattr(audit_mod.time, "perf_counter", lambda: float(next(clock)))
            if not shared:
                _without_shortcuts(m)
            bundle = load_bundle(sealed / "sealed.prop")
            data = load_data(sealed / "mine.npz")
            s = AuditSettings(**(SMALL | {"probes": ["relaxed", "latent"], "budget": 40.0}))
            return audit_mod.audit(bundle, data, [read_key_file(sealed / "k.bin", bundle.key_bits)], s)

    cut = budgeted(True)
    assert "latent" in cut["coverage"]["cut_short"] and cut["coverage"]["not_tried"] == []
    assert len(calls) == 1
    row = next(g for g in cut["groups"] if g["name"] == "latent")
    assert row["control"]["leakage"] == row["leakage"] and row["beyond"] == 0
    calls.clear()
    budgeted(False)
    assert len(calls) >= 2  # before: relaxed's control and latent's row each ran the search


def test_max_leak_is_no_pass_when_the_budget_left_every_probe_untried(sealed, cli, monkeypatch):
    """A real-size policy's reference and key can spend the whole budget: no row, so no decision, exit 1."""
    import prop_cli.attack.probes.base as base

    clock = iter(range(10**7))  # every look at the clock moves it a second: past a 1 s budget at once
    monkeypatch.setattr(base.time, "perf_counter", lambda: float(next(clock)))
    monkeypatch.setattr(audit_mod.time, "perf_counter", lambda: float(next(clock)))
    d = sealed
    r = cli("attack", d / "sealed.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin", "--probes",
            "relaxed", "--budget", "1", "--max-leak", "0.05")  # fmt: skip
    assert r.code == 1, r.out
    assert r.out.splitlines()[0].startswith("NO DECISION at --max-leak 0.05: no probe ran")
    assert r.err.strip().splitlines()[-1].startswith("prop: leak check not done at --max-leak 0.05")


def test_an_original_equal_to_the_sealed_base_shares_its_searches_a_changed_one_not(sealed, monkeypatch):
    """--original loaded apart from a sealed bundle's base (prop wrote the base from it): tensor for tensor
    equal, so T2's search runs once for its row and controls, as without --original (before: once on each
    copy, each on its own share of the budget, and a cut-short pair could differ into a false "leak").
    A checkpoint that differs in one value is a different original: its control runs on its own."""
    from prop_cli.attack.probes import latent

    bundle = load_bundle(sealed / "sealed.prop")
    data = load_data(sealed / "mine.npz")
    bits = [read_key_file(sealed / "k.bin", bundle.key_bits)]
    s = AuditSettings(**(SMALL | {"probes": ["relaxed", "latent"]}))
    calls = []
    real = latent._search
    monkeypatch.setattr(latent, "_search", lambda ctx: calls.append(1) or real(ctx))
    same = target.load_original(bundle, str(sealed / "model.safetensors"))
    report = audit_mod.audit(bundle, data, bits, s, original=same)
    assert len(calls) == 1
    row = next(g for g in report["groups"] if g["name"] == "latent")
    assert any("same model as control" in line for line in row["shortcuts"])
    assert "equal to the sealed base" in report["control_model"]

    calls.clear()
    changed = target.load_original(bundle, str(sealed / "model.safetensors"))
    with torch.no_grad():
        next(changed.parameters()).view(-1)[0] += 1e-3
    report = audit_mod.audit(bundle, data, bits, s, original=changed)
    assert len(calls) == 2  # the row on the base, the control on the other checkpoint
    assert report["control_model"] == "the original checkpoint (--original)"
