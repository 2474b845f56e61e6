"""LeRobot pi0 through the policy protocol: its model's calls (``PaliGemma``, shared with pi0.5) under
flow matching (``flow_matching.FlowMatching``), as SmolVLA's (both are openpi's flow-matching VLA).

pi0 is PaliGemma (SigLIP + Gemma) with a Gemma action expert trained by flow matching, SmolVLA's
convention: ``x_t = t * noise + (1 - t) * actions``, the expert predicts ``noise - actions``, and the
deployed chunk integrates it from pure noise (t = 1) in ``num_inference_steps`` Euler steps.

- **Rows**: the camera frames and the state plus the frame's instruction as tokens (PaliGemma's
  tokenizer, padded to ``tokenizer_max_length``), as every VLA's.
- **Deployed chunk**: flow matching's: a batch of one equals ``select_action`` after
  ``torch.manual_seed(noise_seed)``.
- **User term**: LeRobot 0.6's ``PI0Policy.forward``: its noise, then its time (Beta(1.5, 1) * 0.999 +
  0.001), both drawn in the policy before the model runs, the velocity MSE cut to the action's own width
  and **not** masked by ``action_is_pad`` (``PaliGemma.masks_padding``: padded steps count, as LeRobot
  trains them).
- **Fallback term**: the expert's velocity on (observation, instruction, x_t, t), distilled towards the
  frozen original's: ``PaliGemma.velocity`` is PI0Pytorch.forward up to its loss.
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
import json
import logging
from collections.abc import Iterator
from pathlib import Path

import torch

from prop_adapters.folder import CONFIG, WEIGHTS
from prop_adapters.weights import load_into, read_weights, safetensors_shapes, sniff
from prop_cli.constants import LEROBOT_TOKENIZER_DIR
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, shown

from .flow_matching import (
    TOKENIZER_STEP,
    Expert,
    FlowMatching,
    PrefixMemo,
    code_file,
    local_folder,
    refuse_outside_file,
    unhooked,
)
from .policy import COMMON_STEPS, MASK, TOKENS, Built, LeRobotProtocol, construct

NEVER = -1e30  # below it, a float attention mask blocks (LeRobot's OPENPI_ATTENTION_MASK_VALUE: -2.4e38)

# LeRobot's pi0 PEFT targets (PI0Policy._get_default_peft_targets), as prop's layer regexes.
PI0_LAYERS = [
    r"model\.paligemma_with_expert\.gemma_expert\..*\.self_attn\.(q|v)_proj",
    r"model\.(state_proj|action_in_proj|action_out_proj|action_time_mlp_in|action_time_mlp_out)",
]
# pi0's and pi0.5's relative-action steps (off unless config.use_relative_actions): arithmetic on the
# state and actions, nothing loaded.
RELATIVE_ACTION_STEPS = ("relative_actions_processor", "absolute_actions_processor")
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
    found = local_folder(name, TOKENIZER_CONFIG, [*TOKENIZER_FILES, CONFIG])
    if found is not None:
        return check_tokenizer(found, kind, where)
    raise PropError(
        f"{where}: {kind}'s tokenizer {name!r} ({PREPROCESSOR}, step {TOKENIZER_STEP}) is not on this "
        "machine",
        "download it once (hf download google/paligemma-3b-pt-224: a gated repository, accept its licence "
        "first), or set the step's tokenizer_name to a folder with its tokenizer files",
    )


def check_tokenizer(tokenizer: Path, kind: str, where: str) -> Path:
    """``tokenizer`` once none of the files transformers reads from it names code (an ``auto_map``:
    transformers would import a module from the folder, or ask at the terminal whether to), nor a file
    outside it (``flow_matching.outside_file``: a ``tokenizer_file`` elsewhere decides the token ids)."""
    bad = code_file(tokenizer, (*TOKENIZER_FILES, CONFIG))
    if bad is not None:
        raise PropError(
            f"{where}: {kind}'s tokenizer file {bad} has an auto_map (code for transformers to import); "
            "prop runs no tokenizer code",
            f"use PaliGemma's own tokenizer files; if this is a bundle, {TAMPERED}: {RESTORE}",
        )
    refuse_outside_file(tokenizer, (*TOKENIZER_FILES, CONFIG), f"{kind}'s tokenizer", where)
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


def build_paligemma(
    cls, policy_class, folder: Path, weights: dict[str, torch.Tensor] | None, where: str, *,
    contained: bool = False, made_with: str | None = None, as_held: bool = False,
) -> Built:  # fmt: skip
    """Built from its config and the weights, the tokenizer's files read from a local folder
    (``tokenizer_folder``; a bundle's own ``tokenizer/`` where ``contained``) and carried in the
    bundle's ``tokenizer/``; the tokenizer step reads that folder. pi0's and pi0.5's ``build`` (``cls``:
    the protocol, its ``label`` naming the type in messages)."""
    from lerobot.configs.policies import PreTrainedConfig

    config = PreTrainedConfig.from_pretrained(str(folder))
    tokenizer = tokenizer_folder(folder, cls.label, where, contained)
    if weights is None and _file_names_fit(policy_class, config, folder / WEIGHTS):
        # LeRobot's own names: built, then filled one tensor at a time from the file (pi0 at its
        # published size: its 7 GB of weights never held beside the model).
        shapes = safetensors_shapes(folder / WEIGHTS)
        check_sizes(policy_class, config, shapes, where, cls.label)
        policy = construct(meta_ready(policy_class), config, shapes, where)
        load_into(policy, folder / WEIGHTS, as_held)
    else:
        if weights is None:
            weights = lerobot_keys(policy_class, config, read_weights(folder / WEIGHTS)[0])
        check_sizes(policy_class, config, weights, where, cls.label)
        policy = construct(meta_ready(policy_class), config, weights, where)
        policy.load_state_dict(weights, strict=True)
    files = {f"{LEROBOT_TOKENIZER_DIR}/{n}": (tokenizer / n).read_bytes()
             for n in TOKENIZER_FILES if (tokenizer / n).is_file()}  # fmt: skip
    return Built(policy, {TOKENIZER_STEP: {"tokenizer_name": str(tokenizer)}}, files)



class PaliGemma(Expert):
    """pi0's and pi0.5's model (PaliGemma + a Gemma action expert, openpi's layout) as ``FlowMatching``
    calls it. pi0.5's state is in its
    prompt (``state_in_prompt``: its preprocessor writes it into the tokens) and its expert takes no state
    token (the time enters through adaptive RMS norms)."""

    masks_padding = False  # LeRobot 0.6's PI0Policy/PI05Policy.forward count padded steps in their loss

    def __init__(self, owner: LeRobotProtocol, state_in_prompt: bool = False) -> None:
        super().__init__(owner)
        self.state_in_prompt = state_in_prompt

    def inputs(self, batch: dict[str, torch.Tensor]) -> tuple:
        """(images, image masks, tokens, token mask[, state]) as PI0Pytorch (PI05Pytorch: no state)
        takes them."""
        feats = {k: batch[k] for k in self.owner.input_features}
        images, img_masks = self.owner.policy._preprocess_images(feats)
        tokens = batch[TOKENS].round().long(), batch[MASK].bool()
        if self.state_in_prompt:
            return images, img_masks, *tokens
        return images, img_masks, *tokens, self.owner.policy.prepare_state(feats)

    def suffix(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> tuple:
        state = () if self.state_in_prompt else (inputs[4],)
        return self.owner.model.embed_suffix(*state, x_t, time)

    def velocity(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """PI0Pytorch.forward (PI05Pytorch.forward) up to its loss (prefix and suffix in one pass, no
        cache)."""
        m, c = self.owner.model, self.owner.config
        lerobot = importlib.import_module(type(m).__module__)
        prefix, prefix_pad, prefix_att = m.embed_prefix(*inputs[:4])
        suffix, suffix_pad, suffix_att, adarms_cond = self.suffix(inputs, x_t, time)
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
        pwe = self.owner.model.paligemma_with_expert
        vlm = pwe.paligemma.config
        configs = (vlm.text_config, vlm.vision_config, pwe.gemma_expert.config)
        return not any(getattr(p, "attention_dropout", 0.0) for p in configs)

    @contextlib.contextmanager
    def memo(self) -> Iterator[None]:
        """Within: PaliGemma's keys and values for each frame's prefix (images and language; pi0's state
        is in the suffix, pi0.5's in the language) computed once (``PrefixMemo``), where the prefix needs
        no gradient and PaliGemma's language model has no parameter training and no hook or
        parametrization on it (sealed, ``train_expert_only``); a forward then runs the expert only, over
        the prefix's cache, as LeRobot's denoising step runs it. Otherwise LeRobot's forward as it is."""
        from transformers import DynamicCache

        cls = type(self.owner.model.paligemma_with_expert)
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

    def describe(self) -> dict:
        c, pwe = self.owner.config, self.owner.model.paligemma_with_expert
        return {
            "chunk_size": c.chunk_size,
            "n_action_steps": c.n_action_steps,
            "flow_steps": c.num_inference_steps,
            "tokenizer_max_length": c.tokenizer_max_length,
            "vlm_layers": len(pwe.paligemma.model.language_model.layers),
            "expert_layers": len(pwe.gemma_expert.model.layers),
        }



class PI0Protocol(LeRobotProtocol):
    """pi0 through the policy protocol (see the module docstring)."""

    default_layers = PI0_LAYERS
    vetted_steps = COMMON_STEPS | {"pi0_new_line_processor", *RELATIVE_ACTION_STEPS}
    own_steps = frozenset({TOKENIZER_STEP})  # pointed at the tokenizer folder ``build`` finds
    takes_instruction = True
    label = "pi0"
    build = classmethod(build_paligemma)

    def make_denoiser(self) -> FlowMatching:
        return FlowMatching(self, PaliGemma(self))


__all__ = ["PI0_LAYERS", "PI0Protocol", "PaliGemma", "TOKENIZER_FILES", "build_paligemma", "check_tokenizer",
           "tokenizer_folder"]  # fmt: skip
