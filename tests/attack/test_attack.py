"""prop attack: probe keys, the audit's verdicts on a leaky and a well-trained bundle, its outputs."""

from __future__ import annotations

import builtins
import json
from pathlib import Path

import numpy as np
import pytest

from prop_cli import constants as C
from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.attack.audit import audit
from prop_cli.attack.probes import select
from prop_cli.bundle import load_bundle
from prop_cli.config import AuditSettings, PersonalizeConfig, parse_hamming
from prop_cli.core.key_files import read_key_file
from prop_cli.datasources import load_data
from prop_cli.errors import PropError
from prop_cli.files import sha256_file
from tests.conftest import write_keys, write_user_data

# Small audits: the verdicts below do not need the default 4096 random keys or 200 search steps.
QUICK = [
    "--random",
    "128",
    "--per-distance",
    "128",
    "--search-steps",
    "30",
    "--restarts",
    "4",
    "--blackbox",
    "1024",
    "--fewshot-restarts",
    "4",
    "--fewshot-steps",
    "20",
]


@pytest.fixture(scope="module")
def bundles(tmp_path_factory) -> Path:
    """A leaky bundle (raw key bits, no neighbour negatives, none of issue 32's pull or far codes) and a
    well-trained one, same user."""
    d = tmp_path_factory.mktemp("attack")
    rng = np.random.default_rng(0)
    write_user_data(d, 200, rng)
    np.savez(d / "public.npz", x=rng.uniform(-1, 1, (50, 4)).astype(np.float32))
    write_keys(d, ("k.bin", "k2.bin"), rng)
    key = KeySource(read_key_file(d / "k.bin"), "file")
    ckpt = str(d / "model.safetensors")
    leaky = PersonalizeConfig.of(steps=60, key_encoding="raw", neighbour_keys=0, delta_pull=0, far_codes=0)
    personalize_checkpoint(ckpt, [(d / "mine.npz", key)], d / "leaky.prop", leaky)
    personalize_checkpoint(ckpt, [(d / "mine.npz", key)], d / "good.prop", PersonalizeConfig.of(steps=300))
    return d


# --- parsing and probe keys -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "spec,want",
    [("1..8", list(range(1, 9))), ("1,2,4", [1, 2, 4]), ("3", [3]), ("4,1..2", [1, 2, 4])],
)
def test_parse_hamming(spec, want):
    assert parse_hamming(spec) == want


@pytest.mark.parametrize("spec", ["", "0", "3..1", "a", "1..x", "1,,-2", "1...3"])
def test_parse_hamming_rejects_bad_specs(spec):
    with pytest.raises(PropError, match="--hamming"):
        parse_hamming(spec)


def test_probe_selection_and_the_older_search_flag():
    keys = ["null", "random", "hamming", "blackbox"]
    assert select() == [*keys, "structure", "drift", "relaxed", "latent", "fewshot", "cross-user"]
    assert select(["latent", "null"]) == ["null", "latent"]  # registry order
    assert select(search=["latent"]) == [*keys, "latent", "cross-user"]  # black-box key probes + searches
    assert select(search=[]) == [*keys, "cross-user"]
    with pytest.raises(PropError, match="--search"):
        select(search=["gradient"])
    with pytest.raises(PropError, match="--search 'random' is not a search"):
        select(search=["random"])
    with pytest.raises(PropError, match="--probes"):
        select(["gradient"])


# --- it must be able to fail ----------------------------------------------------------------------


def test_leaky_bundle_fails_the_audit(bundles, cli):
    d = bundles
    r = cli(
        "attack", d / "leaky.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin",
        "--hamming", "1,2", "--search", "none", *QUICK, "--max-leak", "0.5", "--json", d / "leaky.json",
    )  # fmt: skip
    assert r.code == 1, r.err
    assert "leak check failed" in r.err and "hamming" in r.err and "--max-leak 0.5" in r.err
    assert r.err.strip().splitlines()[-1].startswith("prop: leak check failed")
    report = json.loads((d / "leaky.json").read_text())
    ham1 = next(g for g in report["groups"] if g["name"] == "hamming 1")
    assert ham1["keys"] == 128  # every 1-bit neighbour
    assert ham1["leakage"]["mean"] > 0.5  # the 1-bit neighbours unlock most of the behaviour
    verdict = report["max_leak"]
    assert verdict["threshold"] == 0.5 and verdict["passed"] is False
    assert sorted(verdict["failing"]) == ["hamming 1", "hamming 2"]
    assert verdict["failing"][0] == "hamming 1"  # by severity: the 1-bit neighbours leak most
    # The decision comes first: one line, pass/fail and the main reason, then the failing rows.
    lines = r.out.splitlines()
    assert lines[0] == verdict["verdict"]
    assert lines[0].startswith("FAILED --max-leak 0.5: hamming 1: keys a few")
    assert lines[2].split()[:2] == ["hamming", "1"] and lines[3].split()[:2] == ["hamming", "2"]
    assert "T0 hamming 1" in r.out and "FAIL" in r.out


def test_well_trained_bundle_passes_the_black_box_audit(bundles, cli):
    d = bundles
    r = cli(
        "attack", d / "good.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin",
        "--hamming", "1..3", "--search", "none", *QUICK, "--max-leak", "0.5", "--json", d / "good.json",
    )  # fmt: skip
    assert r.code == 0, r.err
    report = json.loads((d / "good.json").read_text())
    assert report["user"]["personalization"] > 0.8  # the key works: passing is not vacuous
    assert report["max_leak"]["passed"] is True
    ham = [g for g in report["groups"] if g["distance"]]
    assert [g["distance"] for g in ham] == [1, 2, 3]
    assert all(g["leakage"]["mean"] < 0.1 for g in ham)


# --- the report -----------------------------------------------------------------------------------


def test_json_report_schema(bundles, cli):
    d = bundles
    out = d / "full.json"
    r = cli(
        "attack", d / "good.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin", "--key-file",
        d / "k2.bin", "--hamming", "1", *QUICK, "--samples", "64", "--seed", "3", "--json", out,
    )  # fmt: skip
    assert r.code == 0, r.err
    rep = json.loads(out.read_text())
    assert rep["schema"] == "prop-audit/3" and rep["mode"] == "owner"
    assert rep["bundle"]["manifest_sha256"] == sha256_file(d / "good.prop" / C.MANIFEST)
    assert rep["settings"]["seed"] == 3 and rep["settings"]["hamming"] == [1]
    assert rep["data"]["samples"] == 64
    names = [g["name"] for g in rep["groups"]]
    fewshot = [n for k in (1, 4, 16, 64) for n in (f"fewshot k={k}", f"fewshot k={k} rounded")]
    assert names == ["null", "random", "hamming 1", "blackbox", "structure", "relaxed", "relaxed-rounded",
                     "latent", *fewshot, "key 2"]  # fmt: skip
    for g in rep["groups"]:
        assert set(g["leakage"]) == {"n", "mean", "ci95", "worst"}
        assert g["leakage"]["ci95"][0] <= g["leakage"]["mean"] <= g["leakage"]["ci95"][1]
        assert 0 <= g["leakage"]["worst"] <= 1 and g["leakage"]["n"] == g["keys"]
    relaxed = rep["groups"][names.index("relaxed-rounded")]["search"]
    assert relaxed["restarts"] == 4 and len(relaxed["divergence"]) == 8  # each rounded code, negated too
    assert relaxed["best_divergence"] == max(relaxed["divergence"])
    assert len(relaxed["code_distance"]) == 8
    # k2.bin is no user of this one-user bundle: a plain key row, named in one warning line
    key2 = rep["groups"][names.index("key 2")]
    assert key2["threat"] == "T0" and key2["leakage"]["worst"] < 0.2
    assert [w for w in rep["warnings"] if "--key-file 2 is not a user" in w]
    kinds = {g["name"]: g["kind"] for g in rep["groups"]}
    assert kinds["relaxed"] == "search" and kinds["relaxed-rounded"] == "key"
    assert kinds["fewshot k=4"] == "search" and kinds["fewshot k=4 rounded"] == "key"
    assert "leakage_unbounded" in rep["groups"][names.index("relaxed")]
    assert "T1 relaxed" in r.out and "T2 latent" in r.out and "personalization" in r.out


def test_latent_search_moves_further_than_random_keys(bundles):
    d = bundles
    b = load_bundle(d / "good.prop")
    s = AuditSettings(hamming=[], random=64, probes=["random", "latent"], restarts=2, search_steps=25)
    rep = audit(b, load_data(d / "mine.npz"), [read_key_file(d / "k.bin")], s)
    g = {x["name"]: x for x in rep["groups"]}
    assert g["latent"]["search"]["best_fidelity"] > 10 * g["random"]["fidelity"]["mean"]


def test_no_key_audit_reports_reachable_divergence(bundles, cli):
    d = bundles
    r = cli("attack", d / "good.prop", "--data", d / "public.npz", *QUICK, "--json", "-")
    assert r.code == 0, r.err
    rep = json.loads(r.out)
    assert rep["mode"] == "no-key" and rep["user"] is None
    names = ["null", "random", "blackbox", "structure", "relaxed", "relaxed-rounded", "latent"]
    assert [g["name"] for g in rep["groups"]] == names  # few-shot needs the key and targets
    assert all(g["leakage"] is None for g in rep["groups"])
    assert rep["groups"][-1]["fidelity"]["mean"] > 0  # the search moves the output
    r = cli("attack", d / "good.prop", "--data", d / "public.npz", "--max-leak", "0.1")
    assert r.code == 2 and "--max-leak" in r.err
    r = cli("attack", d / "good.prop", "--data", d / "public.npz", "--hamming", "1")
    assert r.code == 2 and "--hamming" in r.err


def test_usage_errors_exit_2(bundles, cli):
    d = bundles
    base = ["attack", d / "good.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin"]
    r = cli(*base, "--hamming", "2..1")
    assert r.code == 2 and "--hamming" in r.err
    r = cli(*base, "--search", "bogus")
    assert r.code == 2 and "--search" in r.err
    r = cli(*base, "--hamming", "200")
    assert r.code == 2 and "--hamming" in r.err
    (d / "exists.json").write_text("{}")
    r = cli(*base, "--json", d / "exists.json")
    assert r.code == 2 and "--force" in r.err
    r = cli("attack", d / "good.prop", "--data", d / "public.npz", "--key-file", d / "k.bin")
    assert r.code == 2 and "'y'" in r.err


def test_record_writes_summary_and_bundle_still_verifies(bundles, cli, tmp_path):
    import shutil

    bundle = tmp_path / "rec.prop"
    shutil.copytree(bundles / "good.prop", bundle)
    weights = sha256_file(bundle / C.BASE_WEIGHTS)
    r = cli(
        "attack", bundle, "--data", bundles / "mine.npz", "--key-file", bundles / "k.bin",
        "--hamming", "1", "--search", "none", *QUICK, "--record", "--max-leak", "0.5",
    )  # fmt: skip
    assert r.code == 0, r.err
    manifest = json.loads((bundle / C.MANIFEST).read_text())
    rec = manifest[C.M_AUDIT]
    assert rec["schema"] == "prop-audit/3" and rec["max_leak"]["passed"] is True
    assert [g["name"] for g in rec["groups"]] == ["null", "random", "hamming 1", "blackbox"]
    assert load_bundle(bundle).manifest[C.M_AUDIT] == rec  # hashes of the weights still match
    assert sha256_file(bundle / C.BASE_WEIGHTS) == weights
    key_hex = (bundles / "k.bin").read_bytes().hex()
    assert key_hex not in (bundle / C.MANIFEST).read_text()


def test_plot_writes_png(bundles, cli):
    pytest.importorskip("matplotlib")
    d = bundles
    png = d / "audit.png"
    r = cli(
        "attack", d / "good.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin",
        "--hamming", "1,2", *QUICK, "--plot", png,
    )  # fmt: skip
    assert r.code == 0, r.err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_plot_without_matplotlib_says_how_to_install(monkeypatch, tmp_path):
    from prop_cli import present as audit_report

    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.startswith("matplotlib"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    with pytest.raises(PropError, match=r"pip install 'prop-keys\[plot\]'"):
        audit_report.plot({"bundle": {"task": "regression"}, "user": None, "groups": []}, tmp_path / "x.png")


def test_plot_without_matplotlib_fails_before_any_probe_runs(bundles, cli, monkeypatch, tmp_path):
    import importlib.util

    from prop_cli import api

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "matplotlib" else real(n, *a))
    ran = []
    monkeypatch.setattr(api, "audit_bundle", lambda *a, **k: ran.append(1))
    d = bundles
    r = cli("attack", d / "good.prop", "--data", d / "mine.npz", "--plot", tmp_path / "p.png",
            "--json", tmp_path / "a.json")  # fmt: skip
    assert r.code == 2 and "prop-keys[plot]" in r.err and len(r.err.strip().splitlines()) == 1
    assert not ran and not (tmp_path / "a.json").exists() and not (tmp_path / "p.png").exists()


# --- controls (where the bundle gives nothing) and the gate ---------------------------------------


def test_latent_control_runs_on_the_original_and_the_gate_uses_leakage_beyond_it(bundles, cli):
    d = bundles
    base = ["attack", d / "good.prop", "--data", d / "mine.npz", "--key-file", d / "k.bin"]
    quick = ["--probes", "null,latent", "--restarts", "2", "--search-steps", "20", "--samples", "64"]
    r = cli(*base, *quick, "--json", "-")
    assert r.code == 0, r.err
    latent = next(g for g in json.loads(r.out)["groups"] if g["name"] == "latent")
    assert latent["kind"] == "search" and latent["probe"] == "latent"
    assert latent["control"] == {
        "available": False,
        "reason": "no original checkpoint: pass --original (the bundle's base was trained with the key)",
    }
    assert latent["gate"] == {"on": "raw", "value": latent["leakage"]["worst"], "why": "no control"}
    r = cli(*base, *quick, "--original", d / "model.safetensors", "--json", "-")
    assert r.code == 0, r.err
    rep = json.loads(r.out)
    assert rep["reference"] == "original" and "--original" in rep["control_model"]
    latent = next(g for g in rep["groups"] if g["name"] == "latent")
    c = latent["control"]
    assert c["available"] and c["keys"] == 2 and 0 <= c["leakage"]["worst"] <= 1
    assert latent["beyond"] == pytest.approx(max(0.0, latent["leakage"]["worst"] - c["leakage"]["worst"]))
    assert latent["gate"] == {"on": "beyond-control", "value": latent["beyond"], "why": None}
    null = rep["groups"][0]
    assert null["control"]["available"] and null["control"]["leakage"]["worst"] == 0  # the original itself
    assert null["gate"] == {"on": "beyond-control", "value": null["beyond"], "why": None}


def test_frozen_base_is_its_own_control(tmp_path, bundles):
    d = bundles
    key = KeySource(read_key_file(d / "k.bin"), "file")
    cfg = PersonalizeConfig.of(steps=30, freeze_base=True)
    personalize_checkpoint(str(d / "model.safetensors"), [(d / "mine.npz", key)], tmp_path / "f.prop", cfg)
    s = AuditSettings(probes=["latent"], restarts=2, search_steps=10, samples=32)
    rep = audit(load_bundle(tmp_path / "f.prop"), load_data(d / "mine.npz"), [key.bits], s)
    latent = rep["groups"][0]
    assert latent["control"]["available"] and "--freeze-base" in rep["control_model"]


def test_wrong_key_warns(bundles, cli):
    """Issue 10, fix 10: a key at base level gets a one-line hint that it may not be the bundle's.
    Issue 31: a key enrolled in nothing is refused unless --allow-unenrolled-key, and the warning says
    what prop run does with it."""
    d = bundles
    args = ["attack", d / "good.prop", "--data", d / "mine.npz", "--probes", "null", "--samples", "32"]
    r = cli(*args, "--key-file", d / "k2.bin")
    assert r.code == 2 and "enrolled in nothing" in r.err and "--allow-unenrolled-key" in r.err, r.err
    assert len(r.err.strip().splitlines()) == 1
    r = cli(*args, "--key-file", d / "k2.bin", "--allow-unenrolled-key")
    assert r.code == 0, r.err
    warning = [ln for ln in r.err.splitlines() if ln.startswith("prop: warning:")]
    assert len(warning) == 2 and "may not be this bundle's key" in warning[1]
    assert "enrolled in nothing" in warning[0] and "prop run refuses this key" in warning[0]
    r = cli(*args, "--key-file", d / "k.bin")
    assert "prop: warning:" not in r.err


def test_a_search_whose_control_reaches_the_ceiling_is_gated_on_its_own_figure_and_warned():
    from prop_cli.attack.verdict import ceiling_warnings, gate

    def row(name, kind, worst, control):
        return {"name": name, "kind": kind, "leakage": {"worst": worst},
                "control": {"available": True, "leakage": {"worst": control}}}  # fmt: skip

    saturated = row("relaxed", "search", 0.6, 1.0)
    saturated["gate"] = gate(saturated, saturable=True)
    assert saturated["gate"] == {"on": "raw", "value": 0.6, "why": "control at the ceiling"}
    assert saturated["beyond"] == 0.0  # what "beyond" would have hidden
    warned = ceiling_warnings([saturated])
    assert len(warned) == 1 and warned[0].startswith("relaxed: its control reaches the leakage ceiling")
    # Below the ceiling, or on a sealed bundle (searches run on the control's own model): beyond.
    assert gate(row("latent", "search", 0.9, 0.4), saturable=True)["on"] == "beyond-control"
    assert gate(row("relaxed", "search", 0.6, 1.0), saturable=False)["on"] == "beyond-control"
    # Key rows are never gated on a ceiling: their control is the reference, or a user's own record.
    assert gate(row("user 2", "key", 0.99, 0.99), saturable=True) == {"on": "beyond-control", "value": 0.0,
                                                                     "why": None}  # fmt: skip


def test_the_verdict_ranks_failing_rows_by_value_then_by_what_the_attack_needs():
    from prop_cli.attack.verdict import apply_max_leak, headline

    def row(name, probe, threat, kind, value):
        return {"name": name, "probe": probe, "threat": threat, "kind": kind,
                "gate": {"on": "beyond-control", "value": value, "why": None}}  # fmt: skip

    report = {
        "user": {"leakage": 1.0}, "remedy": "seal it with --seal",
        "groups": [
            row("random", "random", "T0", "key", 0.09),
            row("fewshot k=1 rounded", "fewshot", "T3", "key", 0.997),
            row("relaxed-rounded", "relaxed", "T1", "key", 0.9971),
            row("structure", "structure", "structure", "key", 0.9921),  # 0.992 vs 0.997: one tier
            row("null", "null", "T0", "key", 0.0),
        ],
    }  # fmt: skip
    assert headline(report).startswith("most leaked: structure: your code can be read off")
    failing = apply_max_leak(report, 0.05)
    # 0.997 ties (within 0.01): reading the files beats a search, a search beats the user's samples.
    assert [n for n, _ in failing] == ["structure", "relaxed-rounded", "fewshot k=1 rounded", "random"]
    v = report["max_leak"]
    assert v["verdict"].startswith("FAILED --max-leak 0.05: structure:") and v["verdict"].endswith("--seal")
    assert v["rows"][-1]["finding"] == "random keys show part of your behaviour"
    assert apply_max_leak(report, 0.999) == [] and report["max_leak"]["verdict"].startswith("PASSED")


def test_policies_get_a_smaller_scan_and_few_shot_budget_unless_given():
    from prop_cli.attack import target
    from prop_cli.config import BLACKBOX_KEYS_POLICY, FEWSHOT_RESTARTS, FEWSHOT_RESTARTS_POLICY

    assert AuditSettings().validate(128, True, []).fewshot_restarts == FEWSHOT_RESTARTS  # array models
    s = target.policy_settings(AuditSettings())
    assert (s.blackbox, s.fewshot_restarts) == (BLACKBOX_KEYS_POLICY, FEWSHOT_RESTARTS_POLICY)
    s = target.policy_settings(AuditSettings(blackbox=10, fewshot_restarts=64))
    assert (s.blackbox, s.fewshot_restarts) == (10, 64)  # given explicitly: kept
