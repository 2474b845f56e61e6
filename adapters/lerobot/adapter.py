"""A LeRobot policy folder (``save_pretrained`` of policy and processors), loaded by LeRobot's own classes.

The folder holds ``config.json`` (with ``type``), ``model.safetensors`` and the pre/post-processor files
(``policy_preprocessor.json`` ...). The module is the LeRobot policy itself, so state-dict names are
LeRobot's; the bundle carries the folder's config and processor files byte for byte plus the trained
weights, so its ``lerobot/`` folder loads back with ``from_pretrained``.

lerobot is optional (scripts/setup-lerobot.sh builds its environment) and imported only here, inside
functions. Supported: ACT (``policy.LeRobotPolicy`` is how prop trains and runs it), Diffusion
(``diffusion.DiffusionPolicy``: its denoiser is the fallback term's output, its chunks are sampled from
a seeded noise) and SmolVLA (``smolvla.SmolVLAPolicy``: the same for its flow-matching expert). Other
types (pi0, ...) are refused in one line.

SmolVLA names its VLM (``vlm_model_name``: a hub id or a folder) and LeRobot would read its config,
tokenizer and processor from there, downloading them or its weights. prop never lets it: the VLM is
built from its config alone (``load_vlm_weights=False``; model.safetensors holds every weight), the
config/tokenizer/processor files are read from a local folder (the name as a folder, or the hub cache,
offline), and the bundle carries those files in ``lerobot/vlm/`` so whoever receives it needs nothing
else. The tokenizer step of the processors is pointed at that folder: it reads a tokenizer file, never
code (transformers' Auto classes run code only with trust_remote_code, which LeRobot does not pass).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path

import torch

from prop_adapters.base import Adapter, CheckpointOptions, LoadedModel, finish
from prop_adapters.folder import CONFIG, WEIGHTS, read_config
from prop_adapters.weights import read_weights
from prop_cli.constants import LEROBOT_DIR, LEROBOT_TYPES, LEROBOT_VLM_DIR
from prop_cli.errors import PropError

from .diffusion import DiffusionPolicy
from .policy import LeRobotPolicy
from .smolvla import SmolVLAPolicy

PREPROCESSOR = "policy_preprocessor.json"
PROCESSORS = "policy_*processor*.json"  # the pipelines LeRobot reads: pre- and postprocessor
# Registered steps that load further models or tokenizers by a name their config gives: code and
# downloads a file would choose, so they need --trust-remote-code like an import path does.
LOADS_BY_NAME = ("tokenizer", "classifier", "groot", "xvla", "pi0")
# Steps accepted although they load by name: prop overrides the name with the folder's own VLM folder.
LOADS_FROM_OWN_FOLDER = {"tokenizer_processor"}
TOKENIZER_STEP = "tokenizer_processor"
# The VLM files SmolVLA reads by name (no weights): config, tokenizer, image/video processor, template.
VLM_FILES = (
    "config.json", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json", "added_tokens.json",
    "vocab.json", "merges.txt", "preprocessor_config.json", "processor_config.json",
    "video_preprocessor_config.json", "chat_template.json", "chat_template.jinja",
)  # fmt: skip
FOLDER_IN_BUNDLE = LEROBOT_DIR  # the bundle's LeRobot folder
# policy type -> how prop trains it
PROTOCOLS = {"act": LeRobotPolicy, "diffusion": DiffusionPolicy, "smolvla": SmolVLAPolicy}
SUPPORTED = LEROBOT_TYPES
assert set(PROTOCOLS) == set(SUPPORTED)
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
    name: a step is accepted only by a ``registry_name`` LeRobot itself registers (read before LeRobot
    sees the files; a ``class`` import path is what LeRobot would import)."""
    _lerobot()
    from lerobot.processor import ProcessorStepRegistry

    known = {n for n in ProcessorStepRegistry.list() if not any(w in n for w in LOADS_BY_NAME)}
    known |= LOADS_FROM_OWN_FOLDER
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


def _folder_files(folder: Path, vlm: Path | None = None) -> dict[str, bytes]:
    """The folder's config and processor files, by their path in the bundle; a SmolVLA's VLM files too."""
    names = [CONFIG] + sorted(p.name for p in folder.glob("policy_*processor*") if p.is_file())
    files = {f"{FOLDER_IN_BUNDLE}/{n}": (folder / n).read_bytes() for n in names}
    if vlm is not None:
        files |= {
            f"{FOLDER_IN_BUNDLE}/{LEROBOT_VLM_DIR}/{n}": (vlm / n).read_bytes()
            for n in VLM_FILES if (vlm / n).is_file()
        }  # fmt: skip
    return files


def _check_type(config: dict, where: str) -> str:
    kind = config.get("type")
    if kind not in SUPPORTED:
        raise PropError(
            f"{where}: policy type {kind!r} is not supported", f"prop supports {', '.join(SUPPORTED)}"
        )
    return kind


def vlm_folder(folder: Path, name: object, where: str) -> Path:
    """The local folder of a SmolVLA's VLM files: the bundle's own ``vlm/``, the name as a folder, or the
    name's snapshot in the hub cache (offline: never a download)."""
    own = folder / LEROBOT_VLM_DIR
    if (own / CONFIG).is_file():
        return own
    if isinstance(name, str) and name:
        if (Path(name) / CONFIG).is_file():
            return Path(name)
        try:
            from huggingface_hub import snapshot_download

            cached = Path(snapshot_download(name, local_files_only=True, allow_patterns=list(VLM_FILES)))
            if (cached / CONFIG).is_file():
                return cached
        except Exception:  # noqa: BLE001, S110 - not in the cache (or not a hub id): the error below
            pass
    raise PropError(
        f"{where}: SmolVLA's VLM {name!r} (config.json vlm_model_name) is not on this machine",
        "download it once (hf download NAME), or set vlm_model_name to a folder with its config and "
        "tokenizer",
    )


def _load(folder: Path, weights: dict[str, torch.Tensor] | None, where: str):
    version, get_policy_class, make_pre_post_processors = _lerobot()
    kind = _check_type(read_config(folder), where)
    vlm = None
    try:
        from lerobot.configs.policies import PreTrainedConfig

        cls = get_policy_class(kind)
        with contextlib.redirect_stdout(sys.stderr):  # LeRobot prints progress: stdout is for results
            overrides = {}
            if kind == "smolvla":  # built from its config and our weights; VLM files from a local folder
                config = PreTrainedConfig.from_pretrained(str(folder))
                vlm = vlm_folder(folder, config.vlm_model_name, where)
                config.vlm_model_name, config.load_vlm_weights = str(vlm), False
                policy = cls(config)
                policy.load_state_dict(read_weights(folder / WEIGHTS)[0] if weights is None else weights)
                overrides = {TOKENIZER_STEP: {"tokenizer_name": str(vlm)}}
            elif weights is None:
                policy = cls.from_pretrained(str(folder))
            else:
                policy = cls(PreTrainedConfig.from_pretrained(str(folder)))
                policy.load_state_dict(weights, strict=True)
            pre, post = make_pre_post_processors(
                policy.config, pretrained_path=str(folder), preprocessor_overrides=overrides
            )
    except PropError:
        raise
    except Exception as e:  # noqa: BLE001 - LeRobot's errors on a damaged or foreign folder
        raise PropError(
            f"{where}: LeRobot could not load the policy "
            f"({type(e).__name__}: {str(e).splitlines()[0][:160]})",
            "check that config.json, model.safetensors and the processor files belong together",
        ) from None
    return version, policy, pre, post, vlm


class LeRobotAdapter(Adapter):
    name = "lerobot"
    summary = (
        "a LeRobot policy folder: config.json (type act, diffusion or smolvla) + model.safetensors + "
        "policy_preprocessor.json and the other processor files, loaded by LeRobot (scripts/setup-lerobot.sh)"
    )

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return path.is_dir() and all((path / n).is_file() for n in (CONFIG, WEIGHTS, PREPROCESSOR))

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        names = read_weights(path / WEIGHTS)[0]
        old = sorted(n for n in names if n.startswith(("normalize_inputs.", "normalize_targets.")))
        if old:
            raise PropError(
                f"{path}: the normalisation statistics are inside model.safetensors (LeRobot < 0.4 layout)",
                "migrate it with lerobot's processor/migrate_policy_normalization.py",
            )
        version, policy, pre, post, vlm = _load(path, None, str(path))
        return self._loaded(policy, pre, post, version, str(path), _folder_files(path, vlm))

    def rebuild(self, spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
        folder = Path(source) / FOLDER_IN_BUNDLE
        if not (folder / CONFIG).is_file() and (Path(source) / PREPROCESSOR).is_file():
            folder = Path(source)  # the original LeRobot folder itself (prop attack --original)
        if not (folder / CONFIG).is_file():
            raise PropError(f"bundle {source} has no {FOLDER_IN_BUNDLE}/{CONFIG}", "write the bundle again")
        version, policy, pre, post, vlm = _load(folder, weights, source)
        return self._loaded(policy, pre, post, version, source, _folder_files(folder, vlm))

    def _loaded(self, policy, pre, post, version: str, source: str, files: dict[str, bytes]) -> LoadedModel:
        module = finish(policy)
        spec = {"adapter": self.name, "type": policy.config.type, "lerobot_version": version}
        return LoadedModel(
            module=module,
            spec=spec,
            dtypes={k: v.dtype for k, v in module.state_dict().items()},
            input_shape=None,
            source=source,
            continuous=True,
            policy=PROTOCOLS[policy.config.type](module, pre, post),
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
