"""A LeRobot policy folder (``save_pretrained`` of policy and processors), loaded by LeRobot's own classes.

The folder holds ``config.json`` (with ``type``), ``model.safetensors`` and the pre/post-processor files
(``policy_preprocessor.json`` ...). The module is the LeRobot policy itself, so state-dict names are
LeRobot's; the bundle carries the folder's config and processor files byte for byte plus the trained
weights, so its ``lerobot/`` folder loads back with ``from_pretrained``.

lerobot is optional (scripts/setup-lerobot.sh builds its environment) and imported only inside
functions. Supported: the types of ``registry.POLICIES``, each built by its class's ``build`` (the VLAs:
their VLM's or tokenizer's files from a local folder, never a download); other types are refused in one
line.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path

import torch

from prop_adapters.base import Adapter, CheckpointOptions, LoadedModel, finish, no_prompt
from prop_adapters.folder import CONFIG, WEIGHTS, read_config
from prop_adapters.weights import read_weights, safetensors_dtypes, safetensors_shapes, sniff
from prop_cli.constants import LEROBOT_DIR
from prop_cli.core.rules import choice, text
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, shown

from .policy import LeRobotProtocol
from .registry import POLICIES

PREPROCESSOR = "policy_preprocessor.json"
PROCESSORS = "policy_*processor*.json"  # the pipelines LeRobot reads: pre- and postprocessor
FOLDER_IN_BUNDLE = LEROBOT_DIR  # the bundle's LeRobot folder
_TYPES = " or ".join([", ".join(list(POLICIES)[:-1]), list(POLICIES)[-1]])  # "act, ... or pi05"
SETUP_HINT = "set up the LeRobot environment: bash scripts/setup-lerobot.sh (then use .venv-lerobot)"


def _lerobot():
    try:
        import lerobot
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    except ImportError:
        raise PropError("this is a LeRobot policy folder, but lerobot is not installed", SETUP_HINT) from None
    # Everything prop reads is local; a missing file must fail, never download.
    os.environ["HF_HUB_OFFLINE"] = "1"
    return lerobot.__version__, get_policy_class, make_pre_post_processors


def processor_code(folder: Path) -> list[str]:
    """The processor steps of ``folder``'s pipelines that LeRobot would import or that load models by
    name: a step is accepted only by a ``registry_name`` LeRobot itself registers and the folder's policy
    vets (``LeRobotProtocol.vetted_steps``: steps that neither import code nor load anything by a name
    their config gives; ``own_steps``: those its ``build`` points at the folder's own files). Any other
    step needs --trust-remote-code like an import path does. Read before LeRobot sees the files; a
    ``class`` import path is what LeRobot would import."""
    _lerobot()
    from lerobot.processor import ProcessorStepRegistry

    protocol = _protocol_of(folder)
    known = (protocol.vetted_steps | protocol.own_steps) & set(ProcessorStepRegistry.list())
    named = []
    for f in sorted(folder.glob(PROCESSORS)):
        try:
            doc = json.loads(f.read_text())
        except (OSError, ValueError, RecursionError):
            named.append(f"{f.name} (not readable JSON: LeRobot would have to interpret it)")
            continue
        steps = doc.get("steps") if isinstance(doc, dict) else None
        if not isinstance(steps, list):
            named.append(f"{f.name} (no list of steps)")
            continue
        for i, step in enumerate(steps):
            name = step.get("registry_name") if isinstance(step, dict) else None
            if isinstance(name, str) and name in known and "class" not in step:
                continue
            what = step.get("class", name) if isinstance(step, dict) else step
            named.append(f"{f.name} step {i}: {str(what)[:80]!r}")
    return named


def _protocol_of(folder: Path) -> type[LeRobotProtocol]:
    """The class of ``folder``'s policy type; the base (the common steps only) where the type is unknown
    or config.json unreadable (loading it then says why)."""
    try:
        kind = read_config(folder).get("type")
    except PropError:
        kind = None
    return POLICIES.get(kind, LeRobotProtocol) if isinstance(kind, str) else LeRobotProtocol


def _folder_files(folder: Path, extra: dict[str, bytes]) -> dict[str, bytes]:
    """The folder's config and processor files (with every state file they name), and the policy's
    ``extra`` files, by their bundle path."""
    names = {CONFIG, *(p.name for p in folder.glob("policy_*processor*") if p.is_file())}
    names |= set(state_files(folder, str(folder)))
    files = {n: (folder / n).read_bytes() for n in sorted(names)} | extra
    return {f"{FOLDER_IN_BUNDLE}/{n}": b for n, b in files.items()}


def state_files(folder: Path, where: str) -> list[str]:
    """The files ``folder``'s processor steps load their state from (``state_file``: the normaliser's
    statistics, which decide what the policy does with no key), each a plain file inside ``folder``.
    LeRobot would read a path outside it, or download a name it does not find: refused in one line,
    before LeRobot sees the folder. In a bundle, every file in its LeRobot folder is listed with its
    sha256 (``bundle.read.check_tree``), so each state file is one the manifest covers."""
    found = []
    for f in sorted(folder.glob(PROCESSORS)):
        try:
            doc = json.loads(f.read_text())
        except (OSError, ValueError, RecursionError):
            continue  # processor_code names it; LeRobot would refuse it too
        steps = doc.get("steps") if isinstance(doc, dict) else None
        for i, step in enumerate(steps if isinstance(steps, list) else []):
            if not isinstance(step, dict) or "state_file" not in step:
                continue
            name = step["state_file"]
            parts = name.split("/") if isinstance(name, str) else []
            inside = bool(parts) and all(p and p not in (".", "..") and "\\" not in p for p in parts)
            if not inside or not _plain_file(folder, name):
                what = "outside the policy folder" if not inside else "not a file in the policy folder"
                raise PropError(
                    f"{where}: {f.name} step {i} loads its state from {shown(repr(name))}, {what}: "
                    f"{TAMPERED}",
                    "a processor's state is a file beside it, as LeRobot's save_pretrained writes it; "
                    + RESTORE,
                )
            found.append(name)
    return found


def _plain_file(folder: Path, name: str) -> bool:
    """``folder / name`` is a regular file reached through no symbolic link."""
    here = folder
    for part in name.split("/"):
        here = here / part
        if here.is_symlink():
            return False
    return here.is_file()


def _check_type(config: dict, where: str) -> str:
    kind = config.get("type")
    if not isinstance(kind, str) or kind not in POLICIES:
        raise PropError(
            f"{where}: policy type {kind!r} is not supported", f"prop supports {', '.join(POLICIES)}"
        )
    return kind


def _load(
    folder: Path, weights: dict[str, torch.Tensor] | None, where: str, contained: bool = False,
    made_with: str | None = None, as_held: bool = False,
):  # fmt: skip
    """LeRobot's policy and processors from ``folder``. ``contained``: the folder is a bundle's, and
    nothing outside it is read (SmolVLA's VLM files included). ``made_with``: the lerobot version the
    bundle was made under (its manifest). ``as_held``: the weights file's tensors taken in its dtypes
    (``CheckpointOptions.keep_dtypes``)."""
    version, get_policy_class, make_pre_post_processors = _lerobot()
    kind = _check_type(read_config(folder), where)
    state_files(folder, where)
    try:
        # LeRobot prints progress (stdout is for results); nothing it calls may ask at the terminal.
        with contextlib.redirect_stdout(sys.stderr), no_prompt():
            built = POLICIES[kind].build(
                get_policy_class(kind), folder, weights, where, contained=contained, made_with=made_with,
                as_held=as_held,
            )  # fmt: skip
            pre, post = make_pre_post_processors(
                built.policy.config, pretrained_path=str(folder), preprocessor_overrides=built.overrides
            )
    except PropError:
        raise
    except Exception as e:  # noqa: BLE001 - LeRobot's errors on a damaged or foreign folder
        raise PropError(
            f"{where}: LeRobot could not load the policy "
            f"({type(e).__name__}: {str(e).splitlines()[0][:160]})",
            "check that config.json, model.safetensors and the processor files belong together",
        ) from None
    return version, built.policy, pre, post, _folder_files(folder, built.files)


def weight_names(path: Path) -> list[str]:
    """The tensor names of a policy's weights file: from the header of a safetensors file (nothing else
    read: a real-size VLA's 1.8 GB stay on disk), else from the file itself."""
    return list(safetensors_shapes(path) if sniff(path) == "safetensors" else read_weights(path)[0])


class LeRobotAdapter(Adapter):
    name = "lerobot"
    manifest_fields = {"type": choice(tuple(POLICIES)), "lerobot_version": text()}
    summary = (
        f"a LeRobot policy folder: config.json (type {_TYPES}) + model.safetensors + "
        "policy_preprocessor.json and the other processor files, loaded by LeRobot (scripts/setup-lerobot.sh)"
    )

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return path.is_dir() and all((path / n).is_file() for n in (CONFIG, WEIGHTS, PREPROCESSOR))

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        names = weight_names(path / WEIGHTS)
        old = sorted(n for n in names if n.startswith(("normalize_inputs.", "normalize_targets.")))
        if old:
            raise PropError(
                f"{path}: the normalisation statistics are inside model.safetensors (LeRobot < 0.4 layout)",
                "migrate it with lerobot's processor/migrate_policy_normalization.py",
            )
        version, policy, pre, post, files = _load(path, None, str(path), as_held=options.keep_dtypes)
        held = safetensors_dtypes(path / WEIGHTS) if sniff(path / WEIGHTS) == "safetensors" else {}
        return self._loaded(policy, pre, post, version, str(path), files, held, options.keep_dtypes)

    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        folder, contained = Path(source) / FOLDER_IN_BUNDLE, True
        if not (folder / CONFIG).is_file() and (Path(source) / PREPROCESSOR).is_file():
            folder, contained = Path(source), False  # the original LeRobot folder itself (--original)
        if not (folder / CONFIG).is_file():
            raise PropError(f"bundle {source} has no {FOLDER_IN_BUNDLE}/{CONFIG}", "write the bundle again")
        made_with = spec.get("lerobot_version") if isinstance(spec.get("lerobot_version"), str) else None
        version, policy, pre, post, files = _load(folder, weights, source, contained, made_with)
        # The version the weights were trained under stays the bundle's (add-user rewrites the manifest).
        held = {k: v.dtype for k, v in weights.items()}
        return self._loaded(policy, pre, post, made_with or version, source, files, held)

    def _loaded(
        self, policy, pre, post, version: str, source: str, files: dict[str, bytes],
        held: dict[str, torch.dtype], keep: bool = False,
    ) -> LoadedModel:  # fmt: skip
        """``held``: the dtype the checkpoint holds each tensor in (the module computes in fp32, ``finish``;
        ``keep``: in ``held``, as ``--precision bf16`` loads it); the bundle's base is written back in it
        (a bf16 pi0 gives a bf16 base, not one of twice its size)."""
        module = finish(policy, held if keep else None)
        spec = {"adapter": self.name, "type": policy.config.type, "lerobot_version": version}
        return LoadedModel(
            module=module,
            spec=spec,
            dtypes={k: held.get(k, v.dtype) for k, v in module.state_dict().items()},
            input_shape=None,
            source=source,
            continuous=True,
            policy=POLICIES[policy.config.type](module, pre, post),
            files=files,
            base_alias=f"{FOLDER_IN_BUNDLE}/{WEIGHTS}",
        )

    def remote_code(self, spec: dict, source: str) -> list[str]:
        folder = Path(source) / FOLDER_IN_BUNDLE
        return processor_code(folder if folder.is_dir() else Path(source))

    def remote_code_at(self, path: Path, options: CheckpointOptions) -> list[str]:
        return processor_code(path)

    def weights(self, path: Path) -> dict[str, torch.Tensor]:
        return read_weights(path / WEIGHTS if path.is_dir() else path)[0]

    def describe(self, loaded: LoadedModel) -> dict:
        info = super().describe(loaded)
        info.update(type=loaded.module.config.type, lerobot_version=loaded.spec.get("lerobot_version"))
        info.update(loaded.policy.describe())
        info["inputs"] = {k: list(v) for k, v in loaded.policy.input_features.items()}
        return info
