"""The README and docs/ say what the code does: API names, the format table, the Extending sketches."""

from __future__ import annotations

import importlib
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from prop_cli import adapters
from prop_cli.attack import probes
from prop_cli.datasources import SOURCES

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README, flags=re.S)


def _file_block(path: str) -> str:
    (block,) = [b for b in _blocks() if b.startswith(f"# file: {path}\n")]
    return block


def _module(path: str, name: str) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__file__ = path
    sys.modules[name] = mod
    exec(compile(_file_block(path), path, "exec"), mod.__dict__)
    return mod


def test_every_name_the_readme_imports_exists():
    """Issue 10, fix 1: the README's `from prop_cli.api import load_bundle` raised ImportError."""
    pattern = r"from (prop_cli[\w.]*|prop_adapters[\w.]*) import (?:\(([^)]*)\)|([\w, ]+)$)"
    imports = [(m, a or b) for m, a, b in re.findall(pattern, README, flags=re.M)]
    assert any(mod == "prop_cli.api" and "load_bundle" in names for mod, names in imports)
    for mod, names in imports:
        m = importlib.import_module(mod)
        for name in (n.strip() for n in names.split(",") if n.strip()):
            assert hasattr(m, name), f"{mod}.{name}"


def test_the_python_api_example_runs(workdir, monkeypatch):
    (block,) = [b for b in _blocks() if "personalize_checkpoint(" in b and "KeyedPolicy(bundle" in b]
    quick = block.replace("steps=2000", "steps=20").replace(
        "AuditSettings(blackbox=100_000)",
        "AuditSettings(random=16, restarts=2, search_steps=5, blackbox=256, per_distance=8)",
    )
    monkeypatch.chdir(workdir)
    env: dict = {}
    exec(compile(quick, "README.md", "exec"), env)
    assert env["action"].shape == (2,) and env["y"].shape == (8, 2)
    assert env["report"]["schema"] == "prop-audit/2"


def test_the_format_table_is_the_registrys():
    from prop_cli.api import formats
    from prop_cli.cli.formats_cmd import formats_markdown

    table = README.split("<!-- formats:start -->\n")[1].split("<!-- formats:end -->")[0].strip()
    assert table == formats_markdown(formats()), "regenerate it with: prop formats --markdown"


def test_docs_are_in_the_repository_and_cited():
    for doc in ("design.md", "metrics.md", "threat-model.md", "hardening.md"):
        assert (ROOT / "docs" / doc).is_file() and f"docs/{doc}" in README
    for path in [ROOT / "README.md", *ROOT.glob("prop_cli/**/*.py"), *ROOT.glob("adapters/*.py")]:
        assert "DESIGN.md" not in path.read_text() and "../shared" not in path.read_text(), path


# ---- Extending: one file + one registry line each -----------------------------------------------


def test_extending_with_an_adapter(tmp_path, monkeypatch):
    from prop_cli.api import KeySource, load_bundle, personalize_checkpoint
    from prop_cli.config import PersonalizeConfig

    mod = _module("adapters/npz_mlp.py", "adapters.npz_mlp")
    registry = list(adapters.ADAPTERS)
    registry.insert(registry.index(next(a for a in registry if a.name == "mlp")), mod.NpzMLPAdapter())
    monkeypatch.setattr(prop_adapters, "ADAPTERS", registry)
    rng = np.random.default_rng(0)
    arrays = {
        "W0": rng.normal(size=(8, 3)),
        "b0": np.zeros(8),
        "W1": rng.normal(size=(2, 8)),
        "b1": np.zeros(2),
    }
    np.savez(tmp_path / "net.npz", **{k: v.astype(np.float32) for k, v in arrays.items()})
    x = rng.uniform(-1, 1, (60, 3)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=x[:, :2])
    loaded = adapters.load_checkpoint(tmp_path / "net.npz")
    assert loaded.spec == {"adapter": "npz-mlp", "sizes": [3, 8, 2]}
    key = KeySource(rng.integers(0, 2, 32, dtype=np.uint8), "file")
    cfg = PersonalizeConfig(steps=5)
    personalize_checkpoint(
        str(tmp_path / "net.npz"), [(tmp_path / "mine.npz", key)], tmp_path / "b.prop", cfg
    )
    assert load_bundle(tmp_path / "b.prop").manifest["model"]["adapter"] == "npz-mlp"


def test_extending_with_a_data_source(tmp_path, monkeypatch, workdir):
    from prop_cli.datasources import load_data

    mod = _module("prop_cli/datasources/csv.py", "prop_cli.datasources.csv")
    monkeypatch.setattr(sys.modules["prop_cli.datasources"], "SOURCES", [*SOURCES, mod.CsvSource()])
    rows = np.random.default_rng(0).uniform(-1, 1, (20, 6))
    np.savetxt(tmp_path / "d.csv", rows, delimiter=",", header="x0,x1,x2,x3,y0,y1", comments="")
    ds = load_data(tmp_path / "d.csv")
    assert ds.x.shape == (20, 4) and ds.y.shape == (20, 2)
    np.testing.assert_allclose(ds.y, rows[:, 4:], rtol=1e-6)


def test_extending_with_a_probe(monkeypatch, workdir):
    from prop_cli.api import KeySource, load_bundle, personalize_checkpoint
    from prop_cli.attack.audit import audit
    from prop_cli.config import AuditSettings, PersonalizeConfig
    from prop_cli.core.keys import read_key_file
    from prop_cli.datasources import load_data

    mod = _module("prop_cli/probes/complement.py", "prop_cli.probes.complement")
    monkeypatch.setattr(probes, "PROBES", [*probes.PROBES, mod.PROBE])
    key = read_key_file(workdir / "k.bin")
    users = [(workdir / "mine.npz", KeySource(key, "file"))]
    personalize_checkpoint(
        str(workdir / "model.safetensors"), users, workdir / "b.prop", PersonalizeConfig(steps=20)
    )
    rep = audit(load_bundle(workdir / "b.prop"), load_data(workdir / "mine.npz"), [key],
                AuditSettings(probes=["null", "complement"], samples=32))  # fmt: skip
    assert [g["name"] for g in rep["groups"]] == ["null", "complement"]
    g = rep["groups"][1]
    assert g["threat"] == "T0" and g["keys"] == 1 and g["gate"]["on"] == "raw"
    with pytest.raises(Exception, match="need the user's key"):
        audit(
            load_bundle(workdir / "b.prop"),
            load_data(workdir / "mine.npz"),
            [],
            AuditSettings(probes=["complement"]),
        )


def test_the_readme_probe_table_is_the_registry():
    section = README.split("## Auditing with prop attack", 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in section.splitlines() if ln.startswith("| `")]
    listed = [
        ln.split("`")[1] for ln in rows if "| T" in ln or "| structure |" in ln or "| cross-user |" in ln
    ]
    assert list(dict.fromkeys(listed)) == probes.names()
    for p in probes.PROBES:
        row = next(ln for ln in rows if ln.startswith(f"| `{p.name}`"))
        assert f"| {p.threat} | {p.kind} |" in row, p.name
