"""Smoke run of benchmarks/bench_harden.py (the figures themselves are the benchmark's, not a test's)."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_harden


def _tiny_il(name, out, seed):  # the IL example, with a base trained for seconds, not a minute
    from examples.il_task import write_example

    if not (out / "test.npz").exists():
        write_example(out, seed=seed, base_samples=512, user_samples=200, base_steps=50)


@pytest.mark.slow  # every attack on two bundles and their controls: scripts/test.sh skips it, .ci/run runs it
def test_quick_run_prints_both_modes_with_controls(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(bench_harden, "write_task", _tiny_il)
    out = tmp_path / "rows.json"
    bench_harden.main(
        ["--quick", "--steps", "5", "--keys", "512", "--workdir", str(tmp_path), "--json", str(out)]
    )
    rows = json.loads(out.read_text())
    assert [r["mode"] for r in rows] == ["default", "hardened"]
    for r in rows:
        assert set(r["t1"]) == {"bundle", "control", "beyond"} and r["random"]["keys"] == 512
        assert 0 <= r["t1"]["beyond"] <= 1 and set(r["fewshot"]) == {"1", "4"}
    text = capsys.readouterr().out
    assert "Few-shot T3" in text and "hardened / default" in text
