"""LeRobot pi0 through the policy protocol: what differs from SmolVLA (``smolvla``), whose rows, noise,
sampler call and fallback pool it shares (both are openpi's flow-matching VLA).

pi0 is PaliGemma (SigLIP + Gemma) with a Gemma action expert trained by flow matching, SmolVLA's
convention: ``x_t = t * noise + (1 - t) * actions``, the expert predicts ``noise - actions``, and the
deployed chunk integrates it from pure noise (t = 1) in ``num_inference_steps`` Euler steps.

- **Rows**: the camera frames and the state plus the frame's instruction as tokens (PaliGemma's
  tokenizer, padded to ``tokenizer_max_length``), as SmolVLA's.
- **Deployed chunk**: LeRobot's ``sample_actions`` from noise drawn per row with ``noise_seed`` (chunk_size
  x max_action_dim), as SmolVLA's: a batch of one equals ``select_action`` after
  ``torch.manual_seed(noise_seed)``. Cut to the action's own width.
- **User term**: LeRobot 0.6's ``PI0Policy.forward``: its noise, then its time (Beta(1.5, 1) * 0.999 +
  0.001), both drawn in the policy before the model runs, the velocity MSE cut to the action's own width
  and **not** masked by ``action_is_pad`` (unlike SmolVLA's: padded steps count, as LeRobot trains them).
- **Fallback term**: the expert's velocity on (observation, instruction, x_t, t), distilled towards the
  frozen original's (SmolVLA's ``fallback_pool``): ``_velocity`` is PI0Pytorch.forward up to its loss.
- **Keyed layers** by default: LeRobot's own PEFT targets for pi0 (``_get_default_peft_targets``): the
  expert's q/v projections and the state, action and action-time projections.
- **The tokenizer is data, never a download** (``build``): LeRobot's preprocessor names PaliGemma's hub
  tokenizer (``google/paligemma-3b-pt-224``, gated). prop reads its files from a local folder (the name
  as a folder, or the hub cache, offline), carries them in the bundle's ``tokenizer/`` and points the
  tokenizer step there. A file naming code (``auto_map``) is refused (``check_tokenizer``; in a bundle
  also ``bundle.read.check_tree``), and a bundle reads its own ``tokenizer/`` only.
- **Weights** from a LeRobot folder get LeRobot's own key fixes first (``_fix_pytorch_state_dict_keys``
  and the ``model.`` prefix, as ``PI0Policy.from_pretrained`` applies them to openpi-converted
  checkpoints); then they must fit the config exactly (``construct``).
"""

from __future__ import annotations

import contextlib
import copy
import importlib
import inspect
import json
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from prop_adapters.base import names_code
from prop_adapters.folder import CONFIG, WEIGHTS
from prop_adapters.weights import load_into, read_weights, safetensors_shapes, sniff
from prop_cli.constants import LEROBOT_TOKENIZER_DIR, TASK
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, shown

from .policy import Built, construct
from .smolvla import MASK, TOKENIZER_STEP, TOKENS, PrefixMemo, SmolVLAProtocol, unhooked

NEVER = -1e30  # below it, a float attention mask blocks (LeRobot's OPENPI_ATTENTION_MASK_VALUE: -2.4e38)

# LeRobot's pi0 PEFT targets (PI0Policy._get_default_peft_targets), as prop's layer regexes.
PI0_LAYERS = [
    r"model\.paligemma_with_expert\.gemma_expert\..*\.self_attn\.(q|v)_proj",
    r"model\.(state_proj|action_in_proj|action_out_proj|action_time_mlp_in|action_time_mlp_out)",
]
PREPROCESSOR = "policy_preprocessor.json"  # adapter.PREPROCESSOR (adapter imports this module)
# The tokenizer files LeRobot's tokenizer step reads (transformers' AutoTokenizer); the folder's
# config.json is read only where tokenizer_config.json names no class, so it is checked, never carried.
TOKENIZER_CONFIG = "tokenizer_config.json"
TOKENIZER_FILES = (
    "tokenizer.json", TOKENIZER_CONFIG, "special_tokens_map.json", "added_tokens.json", "tokenizer.model",
)  # fmt: skip


def tokenizer_name(folder: Path) -> object:
    """The tokenizer ``folder``'s preprocessor names (its tokenizer step's ``tokenizer_name``)."""
    try:
        doc = json.loads((folder / PREPROCESSOR).read_text())
    except (OSError, ValueError, RecursionError):
        return None  # LeRobot reports the file
    steps = doc.get("steps") if isinstance(doc, dict) else None
    for step in steps if isinstance(steps, list) else []:
        if isinstance(step, dict) and step.get("registry_name") == TOKENIZER_STEP:
            config = step.get("config")
            return config.get("tokenizer_name") if isinstance(config, dict) else None
    return None


def tokenizer_folder(folder: Path, kind: str, where: str, contained: bool = False) -> Path:
    """The local folder of a pi0's tokenizer files: the bundle's own ``tokenizer/``, the name its
    preprocessor gives as a folder, or that name's snapshot in the hub cache (offline: never a download).
    ``contained`` (a bundle's folder): its own ``tokenizer/`` only."""
    own = folder / LEROBOT_TOKENIZER_DIR
    name = tokenizer_name(folder)
    if (own / TOKENIZER_CONFIG).is_file():
        return check_tokenizer(own, kind, where)
    if contained:
        raise PropError(
            f"{where}: the bundle has no {LEROBOT_TOKENIZER_DIR}/{TOKENIZER_CONFIG} for {kind}'s "
            f"tokenizer, and reads none from outside it ({PREPROCESSOR} names {shown(repr(name))}): "
            f"{TAMPERED}",
            RESTORE,
        )
    if isinstance(name, str) and name:
        if (Path(name) / TOKENIZER_CONFIG).is_file():
            return check_tokenizer(Path(name), kind, where)
        try:
            from huggingface_hub import snapshot_download

            cached = Path(snapshot_download(name, local_files_only=True,
                                            allow_patterns=[*TOKENIZER_FILES, CONFIG]))  # fmt: skip
        except Exception:  # noqa: BLE001 - not in the cache (or not a hub id): the error below
            cached = None
        if cached is not None and (cached / TOKENIZER_CONFIG).is_file():
            return check_tokenizer(cached, kind, where)
    raise PropError(
        f"{where}: {kind}'s tokenizer {name!r} ({PREPROCESSOR}, step {TOKENIZER_STEP}) is not on this "
        "machine",
        "download it once (hf download google/paligemma-3b-pt-224: a gated repository, accept its licence "
        "first), or set the step's tokenizer_name to a folder with its tokenizer files",
    )


def check_tokenizer(tokenizer: Path, kind: str, where: str) -> Path:
    """``tokenizer`` once none of the files transformers reads from it names code (an ``auto_map``:
    transformers would import a module from the folder, or ask at the terminal whether to)."""
    for n in (*TOKENIZER_FILES, CONFIG):
        if not n.endswith(".json") or not (tokenizer / n).is_file():
            continue
        try:
            doc = json.loads((tokenizer / n).read_bytes())
        except (OSError, ValueError, RecursionError):
            continue  # transformers reports it
        if names_code(doc):
            raise PropError(
                f"{where}: {kind}'s tokenizer file {tokenizer / n} has an auto_map (code for transformers to "
                "import); prop runs no tokenizer code",
                f"use PaliGemma's own tokenizer files; if this is a bundle, {TAMPERED}: {RESTORE}",
            )
    return tokenizer


def meta_ready(policy_class):
    """``policy_class`` as ``construct`` takes it: built on the meta device (its shape probe), the
    config's device is "meta" too. pi0 moves its model to ``config.device``, which a meta tensor cannot
    leave: without this the probe fails and a config.json's claimed size is allocated before any check."""

    def build(config):
        if torch.get_default_device().type == "meta":
            config = copy.copy(config)
            config.device = "meta"
        return policy_class(config)

    return build


# The tensors whose width is a Gemma's (config.json's variants): the language model's, the expert's.
GEMMA_WIDTHS = (
    ("paligemma_variant", "language model", "model.paligemma_with_expert.paligemma.model.language_model."
     "embed_tokens.weight"),
    ("action_expert_variant", "action expert", "model.paligemma_with_expert.gemma_expert.model.layers.0."
     "self_attn.q_proj.weight"),
)  # fmt: skip


def check_sizes(policy_class, config, weights: dict, where: str, label: str) -> None:
    """Refuse, in a line that says so, weights at a width config.json's Gemma variants do not build
    (LeRobot builds pi0 and pi0.5 at PaliGemma's sizes only: a tiny one from examples/pi_tiny.py loads
    only under its patch), rather than as a bundle or folder whose files do not belong together."""
    gemma = getattr(importlib.import_module(policy_class.__module__), "get_gemma_config", None)
    for field, part, name in GEMMA_WIDTHS:
        tensor = weights.get(name)
        variant = getattr(config, field, None)
        if tensor is None or gemma is None or not isinstance(variant, str):
            continue
        shape = tuple(tensor.shape) if isinstance(tensor, torch.Tensor) else tuple(tensor)
        try:
            want, sizes = gemma(variant).width, {v: gemma(v).width for v in ("gemma_300m", "gemma_2b")}
        except (ValueError, TypeError, AttributeError):  # a variant LeRobot does not know: construct says
            continue
        if len(shape) != 2 or shape[1] == want:
            continue
        fit = [v for v, w in sizes.items() if w == shape[1]]
        raise PropError(
            f"{where}: the {label}'s {part} is {shape[1]} wide, config.json's {field} {variant} {want} wide: "
            f"LeRobot builds {label} at PaliGemma's sizes only "
            f"({', '.join(f'{v}: {w}' for v, w in sizes.items())}); nothing was built",
            f"set {field} to {fit[0]} in config.json" if fit else
            f"a tiny {label} made by examples/pi_tiny.py loads only under its patch: python -m "
            "examples.pi_tiny ARGS is prop ARGS with it",
        )  # fmt: skip


def lerobot_keys(policy_class, config, weights: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``weights`` with the key fixes ``from_pretrained`` applies (openpi's old names, the ``model.``
    prefix), computed on a policy built on the meta device (shapes only)."""
    try:
        with torch.device("meta"):
            probe = meta_ready(policy_class)(config)
    except Exception:  # noqa: BLE001 - the weights as they are; construct() says what does not fit
        return weights
    logger = logging.getLogger()
    level = logger.level
    logger.setLevel(logging.ERROR)  # its per-key notes on the vision embedding are not for prop's users
    try:
        fixed = probe._fix_pytorch_state_dict_keys(weights, config)
    finally:
        logger.setLevel(level)
    return {k if k.startswith("model.") else f"model.{k}": v for k, v in fixed.items()}


def _file_names_fit(policy_class, config, path: Path) -> bool:
    """Whether the safetensors file at ``path`` already has the names LeRobot's key fixes give."""
    if not path.is_file() or sniff(path) != "safetensors":
        return False
    shapes = {k: torch.empty(v, device="meta") for k, v in safetensors_shapes(path).items()}
    return set(lerobot_keys(policy_class, config, shapes)) == set(shapes)


class PI0Protocol(SmolVLAProtocol):
    """pi0 through the policy protocol (see the module docstring)."""

    default_layers = PI0_LAYERS
    own_steps = frozenset({TOKENIZER_STEP})  # pointed at the tokenizer folder ``build`` finds
    label = "pi0"

    @classmethod
    def build(
        cls, policy_class, folder: Path, weights: dict[str, torch.Tensor] | None, where: str, *,
        contained: bool = False, made_with: str | None = None,
    ) -> Built:  # fmt: skip
        """Built from its config and the weights, the tokenizer's files read from a local folder
        (``tokenizer_folder``; a bundle's own ``tokenizer/`` where ``contained``) and carried in the
        bundle's ``tokenizer/``; the tokenizer step reads that folder."""
        from lerobot.configs.policies import PreTrainedConfig

        config = PreTrainedConfig.from_pretrained(str(folder))
        tokenizer = tokenizer_folder(folder, cls.label, where, contained)
        if weights is None and _file_names_fit(policy_class, config, folder / WEIGHTS):
            # LeRobot's own names: built, then filled one tensor at a time from the file (pi0 at its
            # published size: its 7 GB of weights never held beside the model).
            shapes = safetensors_shapes(folder / WEIGHTS)
            check_sizes(policy_class, config, shapes, where, cls.label)
            policy = construct(meta_ready(policy_class), config, shapes, where)
            load_into(policy, folder / WEIGHTS)
        else:
            if weights is None:
                weights = lerobot_keys(policy_class, config, read_weights(folder / WEIGHTS)[0])
            check_sizes(policy_class, config, weights, where, cls.label)
            policy = construct(meta_ready(policy_class), config, weights, where)
            policy.load_state_dict(weights, strict=True)
        files = {f"{LEROBOT_TOKENIZER_DIR}/{n}": (tokenizer / n).read_bytes()
                 for n in TOKENIZER_FILES if (tokenizer / n).is_file()}  # fmt: skip
        return Built(policy, {TOKENIZER_STEP: {"tokenizer_name": str(tokenizer)}}, files)

    def _complementary(self, x: dict, order: np.ndarray, flag: str, path: str) -> dict:
        if TASK not in x:
            raise PropError(
                f"{flag} {path}: no task text per frame, which {self.label} takes as its instruction",
                "record the dataset with a task for every frame (LeRobotDataset.add_frame(..., task=...))",
            )
        return {"task": [str(t) for t in x[TASK][order]]}

    def _inputs(self, batch: dict[str, torch.Tensor]) -> tuple:
        """(images, image masks, tokens, token mask, state) as PI0Pytorch takes them; tokens may come as
        floats (the flat view)."""
        feats = {k: batch[k] for k in self.input_features}
        images, img_masks = self.policy._preprocess_images(feats)
        state = self.policy.prepare_state(feats)
        return images, img_masks, batch[TOKENS].round().long(), batch[MASK].bool(), state

    def _suffix(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> tuple:
        return self.model.embed_suffix(inputs[4], x_t, time)

    def _velocity(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """The expert's velocity on (observation, instruction, x_t, t): PI0Pytorch.forward up to its loss
        (prefix and suffix in one pass, no cache)."""
        m, c = self.model, self.config
        lerobot = importlib.import_module(type(m).__module__)
        prefix, prefix_pad, prefix_att = m.embed_prefix(*inputs[:4])
        suffix, suffix_pad, suffix_att, adarms_cond = self._suffix(inputs, x_t, time)
        pwe = m.paligemma_with_expert
        if pwe.paligemma.model.language_model.layers[0].self_attn.q_proj.weight.dtype == torch.bfloat16:
            prefix, suffix = prefix.to(torch.bfloat16), suffix.to(torch.bfloat16)
        pad = torch.cat([prefix_pad, suffix_pad], dim=1)
        att = lerobot.make_att_2d_masks(pad, torch.cat([prefix_att, suffix_att], dim=1))
        (_, out), _ = pwe.forward(
            attention_mask=lerobot.prepare_attention_masks_4d(att), position_ids=torch.cumsum(pad, dim=1) - 1,
            past_key_values=None, inputs_embeds=[prefix, suffix], use_cache=False,
            adarms_cond=[None, adarms_cond],
        )  # fmt: skip
        return m.action_out_proj(out[:, -c.chunk_size :].to(torch.float32))

    @property
    def joins_terms(self) -> bool:
        # Training and eval differ only by dropout; PaliGemma's and Gemma's configs have none by default.
        pwe = self.model.paligemma_with_expert
        vlm = pwe.paligemma.config
        configs = (vlm.text_config, vlm.vision_config, pwe.gemma_expert.config)
        return not any(getattr(p, "attention_dropout", 0.0) for p in configs)

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The policy's own loss on the user rows (its noise, then its time, as its ``forward`` draws
        them; padded steps not masked) and the expert's velocity on the fallback rows, as one forward."""
        target, v = self._joint_forward(user, fallback)
        n = len(target)
        losses = torch.nn.functional.mse_loss(target, v[:n], reduction="none")
        return losses[:, :, : self.config.action_feature.shape[0]].mean(), v[n:]

    @contextlib.contextmanager
    def memo(self) -> Iterator[None]:
        """Within: PaliGemma's keys and values for each frame's prefix (images and language; pi0's state
        is in the suffix, pi0.5's in the language) computed once (``PrefixMemo``), where the prefix needs
        no gradient and PaliGemma's language model has no parameter training and no hook or
        parametrization on it (sealed, ``train_expert_only``); a forward then runs the expert only, over
        the prefix's cache, as LeRobot's denoising step runs it. Otherwise LeRobot's forward as it is."""
        from transformers import DynamicCache

        cls = type(self.model.paligemma_with_expert)
        own = cls.forward
        prefixes = PrefixMemo()

        def forward(pwe, attention_mask=None, position_ids=None, past_key_values=None, inputs_embeds=None,
                    use_cache=None, adarms_cond=None):  # fmt: skip
            args = dict(attention_mask=attention_mask, position_ids=position_ids,
                        past_key_values=past_key_values, inputs_embeds=inputs_embeds, use_cache=use_cache,
                        adarms_cond=adarms_cond)  # fmt: skip
            prefix, suffix = inputs_embeds if inputs_embeds else (None, None)
            lm = pwe.paligemma.model.language_model
            if (past_key_values is not None or prefix is None or prefix.requires_grad or
                    (suffix is None and not use_cache) or not unhooked(lm.modules())):  # fmt: skip
                return own(pwe, **args)
            n = prefix.shape[1]
            later = attention_mask[..., :n, n:]
            if (later if later.dtype == torch.bool else later > NEVER).any():  # the prefix attends beyond
                return own(pwe, **args)
            mask, pos = attention_mask[..., :n, :n], position_ids[:, :n]

            def fill(rows: list[int]):  # LeRobot's prefix fill over the prefix's rows
                # Without grad, so nothing to recompute: a model checkpointing in training mode would
                # drop the cache (transformers sets use_cache=False then), which is what is kept here.
                ckpt = [m for m in lm.modules() if getattr(m, "gradient_checkpointing", False) is True]
                for m in ckpt:
                    m.gradient_checkpointing = False
                try:
                    return own(pwe, attention_mask=mask[rows], position_ids=pos[rows], past_key_values=None,
                               inputs_embeds=[prefix[rows], None], use_cache=True)[1]  # fmt: skip
                finally:
                    for m in ckpt:
                        m.gradient_checkpointing = True

            cache = DynamicCache()
            for i, (k, v) in enumerate(prefixes.block_kv(fill, prefix, mask, pos, list(lm.parameters()))):
                cache.update(k, v, i)
            if suffix is None:  # sample_actions' prefix fill
                return [None, None], cache
            return own(pwe, attention_mask=attention_mask[..., n:, :], position_ids=position_ids[:, n:],
                       past_key_values=cache, inputs_embeds=[None, suffix], use_cache=False,
                       adarms_cond=[None, adarms_cond[1] if adarms_cond else None])  # fmt: skip

        cls.forward = forward
        try:
            yield
        finally:
            cls.forward = own

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        # LeRobot decorates pi0's and pi0.5's sample_actions with @torch.no_grad(); the audit's gradient
        # searches need the chunk's graph, so the undecorated function runs (the same chunk: callers that
        # want no graph run it under no_grad themselves).
        self.policy.eval()
        inputs = self._inputs(batch)
        noise = self._noise(batch[TOKENS].shape[0], batch[TOKENS].device)
        actions = inspect.unwrap(type(self.model).sample_actions)(self.model, *inputs, noise=noise)
        return actions[:, :, : self.config.action_feature.shape[0]]

    def describe(self) -> dict:
        c, pwe = self.config, self.model.paligemma_with_expert
        return {
            "chunk_size": c.chunk_size,
            "n_action_steps": c.n_action_steps,
            "flow_steps": c.num_inference_steps,
            "tokenizer_max_length": c.tokenizer_max_length,
            "vlm_layers": len(pwe.paligemma.model.language_model.layers),
            "expert_layers": len(pwe.gemma_expert.model.layers),
        }


__all__ = ["PI0_LAYERS", "PI0Protocol", "TOKENIZER_FILES", "check_tokenizer", "tokenizer_folder"]
