"""What a new policy type or adapter touches (issue 41, "a VLA in one file"): each LeRobot policy class
derives from the one LeRobot base, and declares its own vetted processor steps; each adapter declares
its own manifest fields, which the bundle format reads from the adapter registry; prop_cli reaches a
policy's flat view through the policy protocol, never through LeRobot's modules. No lerobot needed."""

from __future__ import annotations

import ast
import copy
from pathlib import Path

import pytest

import prop_adapters
from prop_adapters.lerobot import POLICIES, LeRobotProtocol
from prop_adapters.lerobot.policy import COMMON_STEPS
from prop_cli.bundle import manifest as schema
from prop_cli.core.rules import MODEL_CHECKS, MODEL_FIELDS
from prop_cli.errors import PropError

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("kind", sorted(POLICIES))
def test_each_policy_type_derives_from_the_lerobot_base_alone(kind):
    cls = POLICIES[kind]
    assert cls.__bases__ == (LeRobotProtocol,), cls.__mro__
    assert cls.vetted_steps >= COMMON_STEPS
    assert cls.label != LeRobotProtocol.label  # its messages name it


def test_each_policy_vets_its_own_steps():
    """A step one policy's pipeline uses is not accepted in another's folder because of it."""
    assert "smolvla_new_line_processor" in POLICIES["smolvla"].vetted_steps
    assert "smolvla_new_line_processor" not in POLICIES["pi0"].vetted_steps | POLICIES["act"].vetted_steps
    assert "relative_actions_processor" in POLICIES["pi05"].vetted_steps & POLICIES["pi0"].vetted_steps
    assert POLICIES["act"].vetted_steps == POLICIES["diffusion"].vetted_steps == COMMON_STEPS


def test_each_adapter_hands_its_own_manifest_fields_to_the_format():
    for adapter in prop_adapters.ADAPTERS:
        assert MODEL_FIELDS[adapter.name] == adapter.manifest_fields
    lerobot = MODEL_FIELDS["lerobot"]["type"]
    assert all(lerobot.ok(kind) for kind in POLICIES) and not lerobot.ok("groot")
    assert MODEL_CHECKS["mlp"]({"layers": ["a"], "sizes": [3, 2]}) is None
    assert MODEL_CHECKS["mlp"]({"layers": ["a"], "sizes": [3]})[0] == "sizes"


def _manifest(workdir_manifest: dict, **model) -> dict:
    m = copy.deepcopy(workdir_manifest)
    m["model"] = model
    return m


@pytest.fixture(scope="module")
def manifest() -> dict:
    """A stored format 5 manifest (an mlp's), its digest dropped (``validate`` checks fields only)."""
    import json

    path = sorted((ROOT / "tests" / "fixtures").rglob("manifest.json"))
    for p in path:
        m = json.loads(p.read_text())
        if m.get("model", {}).get("adapter") == "mlp" and m.get("mode", "unsealed") == "unsealed":
            return {k: v for k, v in m.items() if k != "manifest_sha256"}
    pytest.skip("no stored mlp manifest")


def test_the_format_checks_a_model_spec_by_its_adapters_fields(manifest):
    schema.validate(manifest, "b.prop")
    policy = _manifest(manifest, adapter="lerobot", type="pi05", lerobot_version="0.6.1")
    schema.validate(policy, "b.prop")
    with pytest.raises(PropError, match=r"field 'model.type' must be one of 'act'"):
        schema.validate(_manifest(manifest, adapter="lerobot", type="groot", lerobot_version="0.6.1"), "b")
    with pytest.raises(PropError, match=r"field 'model.lerobot_version' is missing"):
        schema.validate(_manifest(manifest, adapter="lerobot", type="act"), "b")
    extension = _manifest(manifest, adapter="npz-mlp", sizes=[3, 2])  # an adapter the table does not know
    assert schema.validate(extension, "b.prop") is extension


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_prop_cli_reaches_lerobot_through_the_protocol_only():
    """train/, attack/ and fit take a policy's flat view from the protocol (``PolicyProtocol.flat``), and
    the manifest's schema takes the policy types from the adapter registry: nothing in prop_cli imports
    a module of prop_adapters.lerobot."""
    found = {
        str(p.relative_to(ROOT)): sorted(m for m in _imports(p) if m.startswith("prop_adapters.lerobot"))
        for p in (ROOT / "prop_cli").rglob("*.py")
    }
    assert {k: v for k, v in found.items() if v} == {}
    manifest = _imports(ROOT / "prop_cli" / "bundle" / "manifest.py")
    assert not {m for m in manifest if m.split(".")[0] in ("torch", "prop_adapters")}
