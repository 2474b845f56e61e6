"""`prop export --lerobot OUT`: a LeRobot policy folder for the tools that load a policy only by path
(``lerobot-rollout``, LeRobot's async policy server; ``lerobot-eval`` and ``lerobot-record`` take it
too): ``--policy.path=OUT`` with the plugin ``lerobot_policy_prop`` installed.

The folder names the bundle (relative to itself, so the two move together) and holds no weights, no
statistics and no key: ``config.json`` is a ``--policy.type=prop`` config, and the two processor files
hold LeRobot's rename and device steps (which LeRobot's tools override by name) around the plugin's one
step that runs the bundle's own processors. Whatever runs comes from the bundle, verified when the policy
is built; the key is given when the folder is run (``--policy.key_file``), never written here.
"""

from __future__ import annotations

import os
from pathlib import Path

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.errors import PropError
from prop_cli.files import dump_json, staged_dir


def _pipeline(name: str, stage: str, around: bool) -> dict:
    step = {"registry_name": C.LEROBOT_BUNDLE_STEP, "config": {"stage": stage}}
    if not around:
        return {"name": name, "steps": [step]}
    rename = {"registry_name": "rename_observations_processor", "config": {"rename_map": {}}}
    device = {"registry_name": "device_processor", "config": {"device": "cpu", "float_dtype": None}}
    return {"name": name, "steps": [rename, step, device]}


def write_lerobot_folder(bundle: Bundle, out: Path, *, resize_images: bool = False) -> Path:
    """Write the folder ``out`` for ``bundle`` (a bundle of a LeRobot policy)."""
    if bundle.loaded.policy is None:
        raise PropError(
            f"{bundle.path} holds an array model, not a LeRobot policy: there is no LeRobot folder to export",
            "run it with prop run or prop eval, or export it with --onnx",
        )
    out = Path(out)
    where = os.path.relpath(Path(bundle.path).resolve(), out.resolve())
    config = {"type": C.LEROBOT_POLICY_TYPE, "bundle": where, "resize_images": bool(resize_images),
              "device": "cpu", "input_features": {}, "output_features": {}}  # fmt: skip
    with staged_dir(out, what="LeRobot policy folder", flag="--lerobot") as tmp:
        (tmp / C.LEROBOT_CONFIG).write_text(dump_json(config))
        (tmp / C.LEROBOT_PRE).write_text(dump_json(_pipeline("policy_preprocessor", "pre", True)))
        (tmp / C.LEROBOT_POST).write_text(dump_json(_pipeline("policy_postprocessor", "post", False)))
    return out
