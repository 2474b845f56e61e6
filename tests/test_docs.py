"""The README and docs/ say what the code does: API names, module paths, links, the format and probe
tables, the layout map, the Extending sketches. The README holds what a user needs first; the rest
lives in docs/ (README "Documentation")."""

from __future__ import annotations

import ast
import importlib
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import prop_adapters as adapters
from prop_cli.attack import probes
from prop_cli.datasources import SOURCES

ROOT = Path(__file__).resolve().parents[1]
README_PATH = ROOT / "README.md"
README = README_PATH.read_text()
DOCS = sorted((ROOT / "docs").glob("*.md"))
# The files the README and docs/ are made of: the README and every docs/*.md.
OWN = [README_PATH, *DOCS]
# The Extending sketches' files: shown in docs/extending.md, not shipped.
SKETCHES = (
    "adapters/npz_mlp.py",
    "prop_cli/datasources/csv.py",
    "prop_cli/attack/probes/complement.py",
    "adapters/lerobot/myvla.py",
)


def _doc(name: str) -> str:
    return (ROOT / "docs" / name).read_text()


def _prose(text: str) -> str:
    """Markdown without its fenced code blocks (their `#` lines are comments, not headings)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)


def _links(text: str) -> list[str]:
    """Targets of the Markdown links outside code blocks."""
    return re.findall(r"\]\(([^)\s]+)\)", _prose(text))


def _relative_md_links(path: Path) -> list[Path]:
    out = []
    for target in _links(path.read_text()):
        file = target.split("#", 1)[0]
        if file.endswith(".md") and "://" not in file:
            out.append((path.parent / file).resolve())
    return out


# Every Markdown file a reader reaches from the README: the README, docs/, and what they link to.
LINKED = sorted({*OWN, *(p for f in OWN for p in _relative_md_links(f) if p.is_file())})


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(text: str) -> set[str]:
    return {_slug(h) for h in re.findall(r"^#{1,6} (.+)$", _prose(text), flags=re.M)}


def _section(text: str, heading: str) -> str:
    """From the line ``heading`` to the next heading of the same or a higher level (code blocks skipped)."""
    level = len(heading.split(" ", 1)[0])
    lines = text.splitlines()
    start = lines.index(heading) + 1
    code = False
    for i in range(start, len(lines)):
        code ^= lines[i].startswith("```")
        found = re.match(r"(#+) ", lines[i])
        if not code and found and len(found.group(1)) <= level:
            return "\n".join(lines[start:i])
    return "\n".join(lines[start:])


def _blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def _file_block(path: str) -> str:
    (block,) = [b for b in _blocks(_doc("extending.md")) if b.startswith(f"# file: {path}\n")]
    return block


def _module(path: str, name: str, monkeypatch) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__file__ = path
    monkeypatch.setitem(sys.modules, name, mod)
    exec(compile(_file_block(path), path, "exec"), mod.__dict__)
    return mod


def _is_module_file(module: str) -> bool:
    """A module of the current layout: a file of prop_cli/, or of adapters/ (installed as prop_adapters)."""
    parts = module.split(".")
    if parts[0] == "prop_adapters":
        parts[0] = "adapters"
    base = ROOT.joinpath(*parts)
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


IMPORT = r"from (prop_cli[\w.]*|prop_adapters[\w.]*) import (?:\(([^)]*)\)|([\w, ]+)$)"


def _imports(text: str) -> list[tuple[str, list[str]]]:
    found = re.findall(IMPORT, text, flags=re.M)
    return [(m, [n.strip() for n in (a or b).split(",") if n.strip()]) for m, a, b in found]


# ---- the README: short, and the two commands first -------------------------------------------------


def test_the_readme_is_short():
    """Issue 19: the reference, the privacy tables and the extension guide live in docs/."""
    assert len(README.splitlines()) < 250


def test_the_readme_quick_start_is_two_commands_that_exist():
    section = _section(README, "## Quick start (two commands)")
    block = re.search(r"```\n(.*?)```", section, flags=re.S).group(1)
    commands = [ln.split("#", 1)[0].strip() for ln in block.splitlines() if ln.strip()]
    assert commands == ["bash scripts/demo.sh", "bash scripts/test.sh"]
    for command in commands:
        assert (ROOT / command.split()[1]).is_file(), command


def test_the_readmes_first_block_reads_as_typed():
    """Issue 28: it wrote --out mine.prop twice (the second with --force). Typed in order, each command
    uses files made above it (or the user's own inputs), writes each output once, without --force, and
    add-user takes the sealed bundle."""
    block = re.search(r"```\n(.*?)```", README, flags=re.S).group(1)
    lines = [ln.split("#", 1)[0].split() for ln in block.splitlines() if ln.startswith("prop ")]
    made: dict[str, list[str]] = {}  # path -> the command line that wrote it
    for words in lines:
        cmd, args = words[1], words[2:]
        assert "--force" not in args, words
        outs = [args[i + 1] for i, w in enumerate(args) if w in ("--out", "--output")]
        outs += [args[0]] if cmd == "keygen" else []
        for path in outs:
            assert path not in made, f"{path} is written twice: {words}"
            made[path] = words
        for i, w in enumerate(args):
            if w == "--key-file":
                assert args[i + 1] in made, f"{args[i + 1]} is used before prop keygen makes it"
        if cmd in ("run", "add-user", "attack", "export"):
            assert args[0] in made and made[args[0]][1] == "personalize", words
        if cmd == "add-user":
            assert "--seal" in made[args[0]], "add-user takes a sealed bundle"


def test_docs_are_in_the_repository_and_cited():
    expected = (
        "audit.md", "bundle-format.md", "cli.md", "deploy.md", "design.md", "extending.md",
        "formats.md", "hardening.md", "metrics.md", "privacy.md", "sealed.md", "speed.md",
        "threat-model.md",
    )  # fmt: skip
    for doc in expected:
        assert (ROOT / "docs" / doc).is_file(), doc
    for doc in DOCS:  # every page of docs/ is reachable from the README
        assert f"](docs/{doc.name}" in README, doc.name
    for path in [*OWN, *ROOT.glob("prop_cli/**/*.py"), *ROOT.glob("adapters/**/*.py")]:
        assert "DESIGN.md" not in path.read_text() and "../shared" not in path.read_text(), path


# ---- names, module paths and links -------------------------------------------------------------------


@pytest.mark.parametrize("path", LINKED, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_name_the_docs_import_exists(path):
    """Issue 10, fix 1: the README's `from prop_cli.api import load_bundle` raised ImportError."""
    for mod, names in _imports(path.read_text()):
        m = importlib.import_module(mod)
        for name in names:
            assert hasattr(m, name), f"{path.name}: {mod}.{name}"


def test_the_readme_imports_the_api():
    assert any(m == "prop_cli.api" and "load_bundle" in n for m, n in _imports(README))


# What a module of the layout may import that the test environment lacks: the `ray` extra's (prop serve-ray).
OPTIONAL_IMPORTS = {"ray", "fastapi", "starlette"}


@pytest.mark.parametrize("path", OWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_docs_name_modules_by_their_current_paths(path):
    """Imports, dotted names (`prop_cli.core.key_files.user_keys`) and file paths (`prop_cli/bundle/...py`)
    in the README and docs/ are those of the current layout, not the deprecated 0.1 paths."""
    text = path.read_text()
    for mod, _ in _imports(text):
        assert _is_module_file(mod), f"{path.name}: `from {mod} import` is an old path"
    assert "prop_cli.adapters" not in text, f"{path.name}: prop_cli.adapters is prop_adapters since 0.2"
    for dotted in sorted(set(re.findall(r"\b(?:prop_cli|prop_adapters)(?:\.\w+)+", text))):
        parts = dotted.split(".")
        n = max(i for i in range(1, len(parts) + 1) if _is_module_file(".".join(parts[:i])))
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ModuleNotFoundError as e:  # a module of an extra not installed here (ray_app: `ray`): read it
            assert e.name.split(".")[0] in OPTIONAL_IMPORTS, f"{path.name}: {dotted} ({e.name})"
            assert _dotted_exists(dotted), f"{path.name}: {dotted}"
            continue
        for attr in parts[n:]:
            obj = getattr(obj, attr, None)
            # a module here would be a name that is no file of the layout
            assert obj is not None and not isinstance(obj, types.ModuleType), f"{path.name}: {dotted}"
    for span in re.findall(r"`([\w./-]+\.py)`", text):
        if span in SKETCHES or "/" not in span:
            continue
        assert (ROOT / span).is_file() or (ROOT / "prop_cli" / span).is_file(), f"{path.name}: {span}"


def _top_level_names(path: Path) -> set[str]:
    """What a module defines or imports at its top level (read, not imported: examples pull heavy code)."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names}
    return names


def _dotted_exists(dotted: str) -> bool:
    """`prop_cli.core.key_files.passphrase_bits`: a module of the layout, then a name it defines."""
    parts = dotted.split(".")
    base = ROOT / ("adapters" if parts[0] == "prop_adapters" else parts[0])
    for i, part in enumerate(parts[1:], 1):
        if (base / part).is_dir():
            base = base / part
        elif (base / f"{part}.py").is_file():
            return i + 1 == len(parts) or parts[i + 1] in _top_level_names(base / f"{part}.py")
        else:  # a name a package's __init__ defines
            return (base / "__init__.py").is_file() and part in _top_level_names(base / "__init__.py")
    return True


# Texts beside the README and docs/ that name modules and files: pyproject.toml's comments, the examples'
# results. (CHANGELOG.md is history: it keeps the names of its time.)
NAMING = [*OWN, ROOT / "pyproject.toml", *sorted((ROOT / "examples").rglob("*.md"))]


@pytest.mark.parametrize("path", NAMING, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_files_and_modules_named_exist(path):
    """Issue 41: pyproject.toml named prop_cli/seal.py and tests/test_sb3.py, examples/RESULTS.md
    prop_cli.keys.passphrase_bits, each long gone."""
    text = "\n".join(line for line in path.read_text().splitlines() if not line.startswith("# file: "))
    paths = r"(?<![\w./-])((?:prop_cli|adapters|tests|examples|scripts|docs)/[\w./-]*\.\w+)"
    for named in re.findall(paths, text):
        if named not in SKETCHES:
            assert (ROOT / named).exists(), f"{path.relative_to(ROOT)}: {named}"
    for dotted in re.findall(r"(?<![\w.])((?:prop_cli|prop_adapters|examples)(?:\.\w+)+)", text):
        assert _dotted_exists(dotted), f"{path.relative_to(ROOT)}: {dotted}"


@pytest.mark.parametrize("path", OWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_to_a_file(path):
    text = path.read_text()
    for target in _links(text):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        assert dest.exists(), f"{path.name}: ({target}) points to a missing file"
        if anchor and dest.suffix == ".md":
            assert anchor in _anchors(dest.read_text()), f"{path.name}: ({target}) no such heading"
    # paths named in the text, from the repository root: "docs/sealed.md", "examples/RESULTS.md"
    for named in re.findall(r"\b((?:docs|examples)/[\w.-]+\.md)\b", _prose(text)):
        assert (ROOT / named).is_file(), f"{path.name}: {named}"


def test_the_changelog_says_each_change_in_one_line():
    """Issue 41: the Unreleased section read as research notes (228 lines). Keep a Changelog: one line per
    user-visible change under its kind; the figures stay in the docs the line links, and the links hold."""
    text = (ROOT / "CHANGELOG.md").read_text()
    unreleased = _section(text, "## [Unreleased]")
    kinds = re.findall(r"^### (.+)$", unreleased, flags=re.M)
    assert kinds and set(kinds) <= {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}, kinds
    for line in unreleased.splitlines():
        assert not line or line.startswith(("### ", "- ")), f"CHANGELOG.md: not one line per change: {line!r}"
    for target in _links(unreleased):
        if re.match(r"[a-z]+:", target):
            continue
        file, _, anchor = target.partition("#")
        assert (ROOT / file).is_file(), f"CHANGELOG.md: ({target}) points to a missing file"
        if anchor:
            assert anchor in _anchors((ROOT / file).read_text()), f"CHANGELOG.md: ({target}) no such heading"


def test_design_maps_the_layout():
    """docs/design.md's "Layout" names every module and package of prop_cli and adapters/, and only those."""
    section = _section(_doc("design.md"), "## Layout")
    tree = re.search(r"```\n(.*?)```", section, flags=re.S).group(1)
    roots = (ROOT / "prop_cli", ROOT / "adapters")
    paths = [p for root in roots for p in root.rglob("*.py")]
    files = {p.name for p in paths}
    for path in paths:
        if path.name == "__init__.py" or (path.name.endswith("_cmd.py") and "<command>_cmd.py" in tree):
            continue
        assert re.search(rf"(?<![\w<>]){re.escape(path.name)}", tree), path.relative_to(ROOT)
    for folder in (p.parent for p in paths if p.name == "__init__.py" and p.parent not in roots):
        assert f"{folder.name}/" in tree, folder.relative_to(ROOT)
    for named in re.findall(r"(?<![\w<>])(\w+\.py)", tree):
        assert named in files, f"design.md Layout names {named}, which the layout does not have"
    assert "adapters/" in tree and not (ROOT / "prop_cli" / "adapters").exists()


# ---- the tables the registries make ------------------------------------------------------------------


def test_the_python_api_example_runs(workdir, monkeypatch):
    (block,) = [b for b in _blocks(README) if "personalize_checkpoint(" in b and "KeyedPolicy(bundle" in b]
    quick = block.replace("steps=2000", "steps=20").replace(
        "AuditSettings(blackbox=100_000)",
        "AuditSettings(random=16, restarts=2, search_steps=5, blackbox=256, per_distance=8, "
        "fewshot_restarts=2, fewshot_steps=5)",
    )
    monkeypatch.chdir(workdir)
    env: dict = {}
    exec(compile(quick, "README.md", "exec"), env)
    assert env["action"].shape == (2,) and env["y"].shape == (8, 2)
    assert env["report"]["schema"] == "prop-audit/3"


def test_the_format_table_is_the_registrys():
    from prop_cli.api import formats
    from prop_cli.cli.formats_cmd import formats_markdown

    text = _doc("formats.md")
    table = text.split("<!-- formats:start -->\n")[1].split("<!-- formats:end -->")[0].strip()
    assert table == formats_markdown(formats()), "regenerate it with: prop formats --markdown"


def test_the_audit_docs_probe_table_is_the_registry():
    section = _doc("audit.md").split("\n## ", 1)[0]  # the probes, before the report's schema
    rows = [ln for ln in section.splitlines() if ln.startswith("| `")]
    listed = [
        ln.split("`")[1] for ln in rows if "| T" in ln or "| structure |" in ln or "| cross-user |" in ln
    ]
    assert list(dict.fromkeys(listed)) == probes.names()
    for p in probes.PROBES:
        row = next(ln for ln in rows if ln.startswith(f"| `{p.name}`"))
        assert f"| {p.threat} | {p.kind} |" in row, p.name


def _cli_defaults() -> dict[str, dict[str, object]]:
    """Each command's options and their defaults, as the CLI parses them."""
    import typer.main

    from prop_cli.cli.main import app

    group = typer.main.get_command(app)
    return {
        name: {flag: p.default for p in cmd.params if p.param_type_name == "option" for flag in p.opts}
        for name, cmd in group.commands.items()
    }


def _documented_defaults(text: str) -> list[tuple[list[str], str, str]]:
    """(the section's commands, flag, value) for every default a reference page states: each
    `--flag VALUE` of a bullet "with the defaults:" (the first of `a|b`; placeholders such as N
    skipped), and `--flag ...` followed by "(default VALUE" or "(...; default VALUE"."""
    found = []
    for section in re.split(r"^## ", text, flags=re.M)[1:]:
        heading, body = section.split("\n", 1)
        commands = re.findall(r"prop ([a-z-]+)", heading)
        for bullet in re.findall(r"^- [^\n]*with the defaults:.*?(?=^- |^$)", body, flags=re.S | re.M):
            for flag, value in re.findall(r"`(--[\w-]+) ([^`\s]+)`", bullet):
                if not value.isupper():
                    found.append((commands, flag, value.split("|")[0]))
        for flag, value in re.findall(r"`(--[\w-]+)[^`]*` \((?:[^()]*?; )?default:? ([^\s,;)]+)", body):
            found.append((commands, flag, value))
    return found


def _same(documented: str, default: object) -> bool:
    try:
        return float(documented) == float(default)  # 1e-3 and 0.001, 1 and 1.0
    except (TypeError, ValueError):
        return documented == str(default)


def test_the_cli_reference_states_the_clis_defaults():
    """docs/cli.md said --fallback-noise defaults to 0.5 when it was 1.0: every default it states is
    the one the command parses (personalize's come from PersonalizeConfig)."""
    defaults = _cli_defaults()
    stated = _documented_defaults(_doc("cli.md"))
    flags = {flag for _, flag, _ in stated}
    assert len(stated) >= 12 and {"--fallback-noise", "--steps", "--precision", "--threads"} <= flags
    for commands, flag, value in stated:
        mine = [defaults[c][flag] for c in commands if flag in defaults.get(c, {})]
        assert mine, f"docs/cli.md states a default for {flag}, an option of none of {commands}"
        assert _same(value, mine[0]), f"docs/cli.md: {flag} defaults to {mine[0]!r}, not {value}"


def test_the_docs_list_every_payload_kind():
    from prop_cli.config import PAYLOAD_KINDS

    synopsis = re.findall(r"--payload ([\w|-]+)", _section(_doc("cli.md"), "## prop personalize --seal"))
    assert synopsis and all(sorted(s.split("|")) == sorted(PAYLOAD_KINDS) for s in synopsis), synopsis
    kinds = _doc("sealed.md").split("A **payload** is", 1)[1].split("\n\n", 1)[0]
    for kind in PAYLOAD_KINDS:
        assert f"`{kind}`" in kinds, f"docs/sealed.md's payload paragraph omits {kind}"


# ---- Extending (docs/extending.md): one file + one registry line each ---------------------------------


def test_extending_with_an_adapter(tmp_path, monkeypatch):
    from prop_cli.api import KeySource, load_bundle, personalize_checkpoint
    from prop_cli.config import PersonalizeConfig

    mod = _module("adapters/npz_mlp.py", "prop_adapters.npz_mlp", monkeypatch)
    registry = list(adapters.ADAPTERS)
    registry.insert(registry.index(next(a for a in registry if a.name == "mlp")), mod.NpzMLPAdapter())
    monkeypatch.setattr(adapters, "ADAPTERS", registry)
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
    cfg = PersonalizeConfig.of(steps=5)
    personalize_checkpoint(
        str(tmp_path / "net.npz"), [(tmp_path / "mine.npz", key)], tmp_path / "b.prop", cfg
    )
    assert load_bundle(tmp_path / "b.prop").manifest["model"]["adapter"] == "npz-mlp"


def test_extending_with_a_data_source(tmp_path, monkeypatch, workdir):
    from prop_cli.datasources import load_data

    mod = _module("prop_cli/datasources/csv.py", "prop_cli.datasources.csv", monkeypatch)
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
    from prop_cli.core.key_files import read_key_file
    from prop_cli.datasources import load_data

    mod = _module("prop_cli/attack/probes/complement.py", "prop_cli.attack.probes.complement", monkeypatch)
    monkeypatch.setattr(probes, "PROBES", [*probes.PROBES, mod.PROBE])
    key = read_key_file(workdir / "k.bin")
    users = [(workdir / "mine.npz", KeySource(key, "file"))]
    personalize_checkpoint(
        str(workdir / "model.safetensors"), users, workdir / "b.prop", PersonalizeConfig.of(steps=20)
    )
    rep = audit(load_bundle(workdir / "b.prop"), load_data(workdir / "mine.npz"), [key],
                AuditSettings(probes=["null", "complement"], samples=32))  # fmt: skip
    assert [g["name"] for g in rep["groups"]] == ["null", "complement"]
    g = rep["groups"][1]
    assert g["threat"] == "T0" and g["keys"] == 1 and g["gate"]["on"] == "beyond-control"
    assert g["control"]["available"] and g["control"]["leakage"]["worst"] == 0  # no user enrolled
    with pytest.raises(Exception, match="need the user's key"):
        audit(
            load_bundle(workdir / "b.prop"),
            load_data(workdir / "mine.npz"),
            [],
            AuditSettings(probes=["complement"]),
        )


def test_the_cli_references_settings_table_is_read_from_the_fields():
    """docs/cli.md's table of personalize's settings is generated from the fields' help text and
    defaults (prop_cli.config.settings_table), as `prop personalize --help` is; regenerate it on a
    change."""
    from prop_cli.config import settings_table

    text = _doc("cli.md")
    start = "<!-- settings: prop_cli.config.settings_table() -->\n"
    block = text.split(start, 1)[1].split("\n<!-- /settings -->")[0]
    assert block == settings_table(), (
        "docs/cli.md's settings table is stale: paste the output of "
        "python -c 'from prop_cli.config import settings_table; print(settings_table())'"
    )


def _registry_entry(path: str, mod: types.ModuleType) -> tuple[str, type]:
    """The registry line shown after ``path``'s block, as the entry it adds (evaluated in the module)."""
    blocks = _blocks(_doc("extending.md"))
    line = blocks[blocks.index(_file_block(path)) + 1]
    assert line.startswith("# registry line")
    ((name, cls),) = eval("{" + line + "}", mod.__dict__).items()  # noqa: S307 - the docs' own line
    return name, cls


@pytest.mark.lerobot
def test_extending_with_a_vla(tmp_path, monkeypatch):
    """The new VLA is one file deriving from the LeRobot base only, and one registry line; its file, run
    on a tiny SmolVLA, computes what SmolVLAProtocol does: the chunk, the fallback pool and both terms."""
    pytest.importorskip("lerobot")
    pytest.importorskip("num2words")  # SmolVLM's processor
    import torch

    from examples import lerobot_reach_task as task
    from examples import smolvla_tiny
    from prop_adapters.lerobot import POLICIES, LeRobotProtocol, SmolVLAProtocol
    from prop_adapters.lerobot.policy import PAD

    mod = _module("adapters/lerobot/myvla.py", "prop_adapters.lerobot.myvla", monkeypatch)
    name, cls = _registry_entry("adapters/lerobot/myvla.py", mod)
    assert cls.__bases__ == (LeRobotProtocol,) and name not in POLICIES
    monkeypatch.setitem(POLICIES, name, cls)
    torch.manual_seed(0)
    policy, pre, post = smolvla_tiny.build_smolvla(smolvla_tiny.build_vlm(tmp_path / "vlm"))
    ours, theirs = cls(policy, pre, post, noise_seed=3), SmolVLAProtocol(policy, pre, post, noise_seed=3)
    obs = {task.STATE: torch.rand(3, 6), task.CAMERA: torch.rand(3, 3, task.IMAGE, task.IMAGE),
           "task": ["reach the target"] * 3}  # fmt: skip
    batch = {k: v for k, v in pre(obs).items() if k in ours.row_shapes}
    assert set(batch) == set(ours.row_shapes) == set(theirs.row_shapes)
    with torch.no_grad():
        chunk = ours.chunk(batch)
        assert chunk.shape == (3, 10, 3) and torch.equal(chunk, theirs.chunk(batch))
        g = [torch.Generator().manual_seed(0) for _ in range(2)]
        pools = [p.fallback_pool(batch, chunk, theirs, gen) for p, gen in zip((ours, theirs), g)]
        assert all(torch.equal(pools[0][0][k], pools[1][0][k]) for k in pools[1][0])
        assert torch.equal(pools[0][1], pools[1][1])
        user = batch | {"action": torch.rand(3, 10, 3), PAD: torch.zeros(3, 10, dtype=torch.bool)}
        user[PAD][0, 7:] = True
        fallback = {k: v[:4] for k, v in pools[0][0].items()}
        terms = []
        for p in (ours, theirs):
            torch.manual_seed(1)
            terms.append(p.joint_terms(user, fallback))
    assert torch.equal(terms[0][0], terms[1][0]) and torch.equal(terms[0][1], terms[1][1])
    assert torch.equal(ours.row_weights(user), theirs.row_weights(user))
