"""LeRobot SmolVLA through the policy protocol: its model's calls (``SmolVLM``), under flow matching.

SmolVLA is a VLM (SmolVLM: vision encoder + language model) with an action expert trained by flow
matching: ``x_t = t * noise + (1 - t) * actions``, the expert predicts the velocity ``noise - actions``,
and the deployed chunk integrates it from pure noise (t = 1) in ``num_steps`` Euler steps.

- **Rows** (the base's for a VLA, ``takes_instruction``): the camera frames and the state (one frame,
  SmolVLA's n_obs_steps is 1) plus the frame's instruction as tokens (``observation.language.tokens``
  and its attention mask), padded to the policy's ``tokenizer_max_length`` so every row has one width
  (padding is masked out of attention, so it changes nothing). The instruction is the dataset's task
  text for the frame; in closed loop it is ``prop eval --instruction``, or in Python
  ``KeyedPolicy(..., instruction=...)`` or the observation's ``task`` entry (as LeRobot's preprocessor
  takes it).
- **Deployed chunk, user term, fallback term**: flow matching's (``flow_matching.FlowMatching``), over
  SmolVLA's model (``SmolVLM``): its loss leaves padded steps (``action_is_pad``) out, as LeRobot 0.6's
  ``SmolVLAPolicy.forward`` computes it, and both terms share one forward (no dropout anywhere).
- **Keyed layers** by default: LeRobot's own PEFT targets for SmolVLA (``_get_default_peft_targets``):
  the action expert's q/v projections and the state/action/time projections.
- **The VLM is data, never a download** (``build``): config.json names it (``vlm_model_name``: a hub id
  or a folder) and LeRobot would read its config, tokenizer and processor from there, downloading them
  or its weights. prop builds the VLM from its config alone (``load_vlm_weights=False``;
  model.safetensors holds every weight), reads those files from a local folder (the name as a folder,
  or the hub cache, offline) and the bundle carries them in ``lerobot/vlm/``. The tokenizer step of the
  processors is pointed at that folder: it reads a tokenizer file, never code. transformers' Auto classes
  import code a file names (``auto_map``) or, as LeRobot gives no trust_remote_code, ask at the terminal:
  such a VLM file is refused (``check_vlm``; in a bundle also ``bundle.read.check_tree``), and a bundle
  reads its own ``vlm/`` only, never a folder its config.json names.
- **Bundles made under lerobot 0.4 (transformers 4)**: transformers 5 changed how SmolVLM's vision
  embeddings bucket patch positions (its ``(k / n) * (1 - 1e-6)`` became ``min(k / n, 1 - 1e-6)``), which
  moves their actions by up to 1.4e-3. Such a bundle's policy gets the 4.x position ids back on its own
  vision-embedding instance (``legacy_positions``), so it runs as it was trained, bit for bit.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import types
from collections.abc import Iterator
from pathlib import Path

import torch

from prop_adapters.folder import CONFIG, WEIGHTS
from prop_adapters.weights import load_into, safetensors_shapes
from prop_cli.constants import LEROBOT_VLM_DIR
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, shown

from .flow_matching import (
    TOKENIZER_STEP,
    Bounded,
    Expert,
    FlowMatching,
    PrefixMemo,
    code_file,
    local_folder,
    refuse_outside_file,
    unhooked,
)
from .policy import COMMON_STEPS, MASK, TOKENS, Built, LeRobotProtocol, construct, older_than

# LeRobot's SmolVLA PEFT targets (SmolVLAPolicy._get_default_peft_targets), as prop's layer regexes.
SMOLVLA_LAYERS = [
    r"model\.vlm_with_expert\.lm_expert\..*\.(q|v)_proj",
    r"model\.(state_proj|action_in_proj|action_out_proj|action_time_mlp_in|action_time_mlp_out)",
]
MEMO_BYTES = 512 << 20  # image embeddings kept by ``SmolVLM.memo`` (250 KB per 512x512 frame)
# The VLM files SmolVLA reads by name (no weights): config, tokenizer, image/video processor, template.
VLM_FILES = (
    "config.json", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json", "added_tokens.json",
    "vocab.json", "merges.txt", "preprocessor_config.json", "processor_config.json",
    "video_preprocessor_config.json", "chat_template.json", "chat_template.jinja",
)  # fmt: skip


def vlm_folder(folder: Path, name: object, where: str, contained: bool = False) -> Path:
    """The local folder of a SmolVLA's VLM files: the bundle's own ``vlm/``, the name as a folder, or the
    name's snapshot in the hub cache (offline: never a download). ``contained`` (a bundle's folder):
    its own ``vlm/`` only, never a folder or cache entry its config.json names."""
    own = folder / LEROBOT_VLM_DIR
    if (own / CONFIG).is_file():
        return check_vlm(own, where)
    if contained:
        raise PropError(
            f"{where}: the bundle has no {LEROBOT_VLM_DIR}/{CONFIG} for SmolVLA's VLM, and reads none from "
            f"outside it (config.json names {shown(repr(name))}): {TAMPERED}",
            RESTORE,
        )
    found = local_folder(name, CONFIG, list(VLM_FILES))
    if found is not None:
        return check_vlm(found, where)
    raise PropError(
        f"{where}: SmolVLA's VLM {name!r} (config.json vlm_model_name) is not on this machine",
        "download it once (hf download NAME), or set vlm_model_name to a folder with its config and "
        "tokenizer",
    )


def check_vlm(vlm: Path, where: str) -> Path:
    """``vlm`` once none of the files SmolVLA reads from it names code: an ``auto_map`` makes
    transformers import a module from the folder (or ask at the terminal whether to). SmolVLM is
    transformers' own; prop runs no VLM code, --trust-remote-code or not, and carries none."""
    bad = code_file(vlm, VLM_FILES)
    if bad is not None:
        raise PropError(
            f"{where}: SmolVLA's VLM file {bad} has an auto_map (code for transformers to import); "
            "prop runs no VLM code",
            "use SmolVLM's own files (transformers ships its code); if this is a bundle, "
            f"{TAMPERED}: {RESTORE}",
        )
    refuse_outside_file(vlm, VLM_FILES, "SmolVLA's VLM", where)  # a tokenizer_file elsewhere, ...
    return vlm


class ImageMemo:
    """SmolVLA's image embeddings (vision encoder + connector) by image content, for ``memo``: a frozen,
    unkeyed vision path gives a frame the same embedding under every key, on every draw and at every
    step, so prop computes it once. Used only while a frame's embedding cannot change: on the CPU, with
    no parameter of the path training and no hook or parametrization on it (a key or payload there);
    otherwise the path runs as LeRobot's. Modules that share the path's weights (the original beside
    the keyed policy, a folded payload) share entries. Bounded in bytes, least recently used first out."""

    def __init__(self, limit: int = MEMO_BYTES) -> None:
        self.embeddings = Bounded(limit)
        self.owners: dict[int, torch.Tensor] = {}  # held, so no id is reused while the memo lives

    @staticmethod
    def frozen(vlm_with_expert) -> bool:
        model = vlm_with_expert.get_vlm_model()
        return unhooked(m for part in (model.vision_model, model.connector) for m in part.modules())

    def embed(self, compute, vlm_with_expert, image: torch.Tensor) -> torch.Tensor:
        """``compute(image)`` (B, tokens, width), each row from the memo where it was computed before."""
        if image.device.type != "cpu" or image.requires_grad or not self.frozen(vlm_with_expert):
            return compute(image)
        model = vlm_with_expert.get_vlm_model()
        weights = (next(model.vision_model.parameters()), next(model.connector.parameters()))
        self.owners.update((id(w), w) for w in weights)
        amp = torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else None
        head = (tuple(id(w) for w in weights), amp, image.dtype, tuple(image.shape[1:]))
        flat = image.detach().contiguous().view(len(image), -1)
        keys = [(*head, hashlib.blake2b(row.numpy().tobytes(), digest_size=16).digest()) for row in flat]
        todo = list(dict.fromkeys(k for k in keys if k not in self.embeddings))
        if todo:
            first = {k: i for i, k in reversed(list(enumerate(keys)))}
            new = compute(image[[first[k] for k in todo]]).detach()
            for k, e in zip(todo, new):
                self.embeddings.keep(k, e.clone())
        return torch.stack(self.embeddings.rows(keys))


def after_block(vwe, kv: list, attention_mask, position_ids, inputs_embeds: list, use_cache: bool) -> tuple:
    """LeRobot 0.6's ``SmolVLMWithExpertModel.forward`` (with ``forward_attn_layer`` and
    ``forward_cross_attn_layer``, no cache passed in) over the tokens after the prefix's first block,
    that block's post-RoPE keys and values at every layer given (``kv``, (B, n, heads, head dim) each,
    as that module holds them): ``inputs_embeds`` = [the rest
    of the prefix, the suffix or None], ``attention_mask`` their rows over [block, rest, suffix],
    ``position_ids`` theirs. The same modules in the same order on the same inputs, so keys and payloads
    on them act as in LeRobot's forward. Returns ([None, the suffix's output], the filled cache over the
    whole prefix where ``use_cache``, else None); the prefix's output is not computed (no caller reads
    it)."""
    mod = importlib.import_module(type(vwe).__module__)
    models = [vwe.get_vlm_model().text_model, vwe.lm_expert]
    layers = vwe.get_model_layers(models)
    rest, suffix = inputs_embeds
    b, r, n = rest.shape[0], rest.shape[1], kv[0][0].shape[1]
    head_dim = vwe.vlm.config.text_config.head_dim
    attend = vwe.get_attention_interface()
    every = vwe.self_attn_every_n_layers
    cache = mod.DynamicCache() if use_cache else None

    def qkv(layer, h: torch.Tensor) -> tuple:
        h = layer.input_layernorm(h)
        shape = (*h.shape[:-1], -1, layer.self_attn.head_dim)
        h = h.to(dtype=layer.self_attn.q_proj.weight.dtype)
        a = layer.self_attn
        return a.q_proj(h).view(shape), a.k_proj(h).view(shape), a.v_proj(h).view(shape)

    for i in range(vwe.num_vlm_layers):
        ka, va = kv[i]
        if use_cache or "cross" not in vwe.attention_mode or (every > 0 and i % every == 0):
            both = zip((layers[0][i], layers[1][i]), (rest, suffix))
            parts = [qkv(layer, h) for layer, h in both if h is not None and layer is not None]
            q, k, v = (torch.cat(x, dim=1) for x in zip(*parts))
            t = q.shape[1]
            q, k = mod.apply_rope(q, position_ids[:, :t]), mod.apply_rope(k, position_ids[:, :t])
            k, v = torch.cat([ka, k], dim=1), torch.cat([va, v], dim=1)
            if cache is not None:
                cache.update(k.transpose(1, 2), v.transpose(1, 2), i)
            outs = [attend(attention_mask[:, :t, : n + t], b, head_dim, q, k, v)]
        else:
            q, k, v = qkv(layers[0][i], rest)
            q, k = mod.apply_rope(q, position_ids[:, :r]), mod.apply_rope(k, position_ids[:, :r])
            k, v = torch.cat([ka, k], dim=1), torch.cat([va, v], dim=1)
            outs = [attend(attention_mask[:, :r, : n + r], b, head_dim, q, k, v)]
            expert = layers[1][i]
            if expert is None:
                outs.append(None)
            else:
                a = expert.self_attn
                h = expert.input_layernorm(suffix)
                eq = a.q_proj(h.to(dtype=a.q_proj.weight.dtype)).view(*h.shape[:-1], -1, a.head_dim)
                ek_in = k.to(dtype=a.k_proj.weight.dtype).reshape(*k.shape[:2], -1)
                ek = a.k_proj(ek_in).view(*ek_in.shape[:-1], -1, a.head_dim)
                ev_in = v.to(dtype=a.v_proj.weight.dtype).reshape(*v.shape[:2], -1)
                ev = a.v_proj(ev_in).view(*ev_in.shape[:-1], -1, a.head_dim)
                pos = position_ids[:, r:]
                pos = pos - torch.min(pos, dim=1, keepdim=True).values
                mask = attention_mask[:, -suffix.shape[1] :, : ek.shape[1]]
                outs.append(attend(mask, b, head_dim, mod.apply_rope(eq, pos), ek, ev))
        new, start = [], 0
        for j, h in enumerate((rest, suffix)):
            layer = layers[j][i]
            out = outs[j] if j < len(outs) else outs[0]
            if h is None or layer is None:
                new.append(h)
                continue
            end = start + h.shape[1]
            if out.dtype != layer.self_attn.o_proj.weight.dtype:
                out = out.to(layer.self_attn.o_proj.weight.dtype)
            emb = layer.self_attn.o_proj(out[:, start:end])
            emb += h
            residual = emb.clone()
            emb = layer.mlp(layer.post_attention_layernorm(emb))
            emb += residual
            new.append(emb)
            start = end if len(outs) == 1 else 0
        rest, suffix = new
    return [None, None if suffix is None else models[1].norm(suffix)], cache


def legacy_positions(embeddings: torch.nn.Module) -> None:
    """Give one SmolVLM vision-embedding module transformers 4.x's patch position ids (bound on the
    instance: other policies in the process keep transformers' own)."""

    def forward(self, pixel_values: torch.Tensor, patch_attention_mask: torch.Tensor) -> torch.Tensor:
        b, _, height, width = pixel_values.shape
        out = self.patch_embedding(pixel_values).flatten(2).transpose(1, 2)
        side = self.num_patches_per_side
        dev = pixel_values.device
        bounds = torch.arange(1 / side, 1.0, 1 / side, device=dev)
        ids = torch.zeros((b, (height // self.patch_size) * (width // self.patch_size)), dtype=torch.long,
                          device=dev)  # fmt: skip
        for i, mask in enumerate(patch_attention_mask):
            rows, cols = mask[:, 0].sum(), mask[0].sum()
            fh = torch.arange(rows, device=dev, dtype=pixel_values.dtype) / rows * (1 - 1e-6)
            fw = torch.arange(cols, device=dev, dtype=pixel_values.dtype) / cols * (1 - 1e-6)
            bh = torch.bucketize(fh, bounds, right=True)
            bw = torch.bucketize(fw, bounds, right=True)
            ids[i][mask.view(-1)] = (bh[:, None] * side + bw).flatten()
        return out + self.position_embedding(ids)

    embeddings.forward = types.MethodType(forward, embeddings)


class SmolVLM(Expert):
    """SmolVLA's model (SmolVLM + its action expert) as ``FlowMatching`` calls it."""

    masks_padding = True  # LeRobot 0.6's SmolVLAPolicy.forward leaves padded steps out of its loss

    def inputs(self, batch: dict[str, torch.Tensor]) -> tuple:
        """(images, image masks, tokens, token mask, state) as SmolVLA's model takes them."""
        policy = self.owner.policy
        feats = {k: batch[k] for k in self.owner.input_features}
        images, img_masks = policy.prepare_images(feats)
        state = policy.prepare_state(feats)
        return images, img_masks, batch[TOKENS].round().long(), batch[MASK].bool(), state

    def velocity(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """VLAFlowMatching.forward up to its loss (prefix and suffix in one pass, no cache)."""
        m, c = self.owner.model, self.owner.config
        images, img_masks, tokens, masks, state = inputs
        make_att_2d_masks = importlib.import_module(type(m).__module__).make_att_2d_masks
        prefix, prefix_pad, prefix_att = m.embed_prefix(images, img_masks, tokens, masks, state=state)
        suffix, suffix_pad, suffix_att = m.embed_suffix(x_t, time)
        pad = torch.cat([prefix_pad, suffix_pad], dim=1)
        att = make_att_2d_masks(pad, torch.cat([prefix_att, suffix_att], dim=1))
        (_, out), _ = m.vlm_with_expert.forward(
            attention_mask=att, position_ids=torch.cumsum(pad, dim=1) - 1, past_key_values=None,
            inputs_embeds=[prefix, suffix], use_cache=False,
        )  # fmt: skip
        return m.action_out_proj(out[:, -c.chunk_size :].to(torch.float32))

    @property
    def joins_terms(self) -> bool:
        # Training and eval differ only by dropout; SmolVLM's configs have none by default.
        cfg = self.owner.model.vlm_with_expert.config
        return not any(getattr(p, "attention_dropout", 0.0) for p in (cfg.text_config, cfg.vision_config))

    @contextlib.contextmanager
    def memo(self) -> Iterator[None]:
        """Within: what SmolVLA computes the same for every key, computed once per frame and shared by
        every SmolVLA with the same frozen weights (this policy, the original beside it, a folded
        payload): each frame's image embedding (``ImageMemo``) and the VLM's keys and values for its
        image + language block (``PrefixMemo``), so a forward runs the state token and the expert only."""
        model = self.owner.model
        vwe_cls, model_cls = type(model.vlm_with_expert), type(model)
        own_image, own_prefix, own_forward = vwe_cls.embed_image, model_cls.embed_prefix, vwe_cls.forward
        images, prefixes = ImageMemo(), PrefixMemo()

        def embed_image(vwe, image: torch.Tensor) -> torch.Tensor:
            return images.embed(lambda im: own_image(vwe, im), vwe, image)

        def embed_prefix(model, imgs, img_masks, lang_tokens, lang_masks, state=None):
            out = own_prefix(model, imgs, img_masks, lang_tokens, lang_masks, state=state)
            prefixes.note(model.vlm_with_expert, out, imgs)
            return out

        def forward(vwe, attention_mask=None, position_ids=None, past_key_values=None, inputs_embeds=None,
                    use_cache=None):  # fmt: skip
            n = prefixes.block(vwe, inputs_embeds, attention_mask, past_key_values)
            if n is None:
                return own_forward(vwe, attention_mask=attention_mask, position_ids=position_ids,
                                   past_key_values=past_key_values, inputs_embeds=inputs_embeds,
                                   use_cache=use_cache)  # fmt: skip
            block, mask, pos = inputs_embeds[0][:, :n], attention_mask[:, :n, :n], position_ids[:, :n]

            def fill(rows: list[int]):  # LeRobot's prefix fill over the block alone
                return own_forward(vwe, attention_mask=mask[rows], position_ids=pos[rows],
                                   past_key_values=None, inputs_embeds=[block[rows].detach(), None],
                                   use_cache=True)[1]  # fmt: skip

            weights = list(vwe.get_vlm_model().text_model.parameters())
            held = prefixes.block_kv(fill, block, mask, pos, weights)
            kv = [(k.transpose(1, 2), v.transpose(1, 2)) for k, v in held]  # as forward_attn_layer holds them
            return after_block(vwe, kv, attention_mask[:, n:], position_ids[:, n:],
                               [inputs_embeds[0][:, n:], inputs_embeds[1]], bool(use_cache))  # fmt: skip

        vwe_cls.embed_image, model_cls.embed_prefix, vwe_cls.forward = embed_image, embed_prefix, forward
        try:
            yield
        finally:
            vwe_cls.embed_image, model_cls.embed_prefix, vwe_cls.forward = own_image, own_prefix, own_forward

    def describe(self) -> dict:
        c = self.owner.config
        return {
            "chunk_size": c.chunk_size,
            "n_action_steps": c.n_action_steps,
            "flow_steps": c.num_steps,
            "tokenizer_max_length": c.tokenizer_max_length,
            "vlm_layers": self.owner.model.vlm_with_expert.num_vlm_layers,
        }


class SmolVLAProtocol(LeRobotProtocol):
    """SmolVLA through the policy protocol (see the module docstring)."""

    default_layers = SMOLVLA_LAYERS
    vetted_steps = COMMON_STEPS | {"smolvla_new_line_processor"}
    own_steps = frozenset({TOKENIZER_STEP})  # pointed at the VLM folder ``build`` finds
    takes_instruction = True
    label = "SmolVLA"

    @classmethod
    def build(
        cls, policy_class, folder: Path, weights: dict[str, torch.Tensor] | None, where: str, *,
        contained: bool = False, made_with: str | None = None, as_held: bool = False,
    ) -> Built:  # fmt: skip
        """Built from its config and the weights (``load_vlm_weights=False``: model.safetensors holds
        every weight), the VLM's files read from a local folder (``vlm_folder``; a bundle's own
        ``vlm/`` where ``contained``) and carried in the bundle's ``vlm/``; the tokenizer step reads
        that folder. ``made_with``: the lerobot version a bundle was made under (its manifest)."""
        from lerobot.configs.policies import PreTrainedConfig

        config = PreTrainedConfig.from_pretrained(str(folder))
        vlm = vlm_folder(folder, config.vlm_model_name, where, contained)
        config.vlm_model_name, config.load_vlm_weights = str(vlm), False
        if weights is None:  # the folder's own file, copied in tensor by tensor (load_into)
            path = folder / WEIGHTS
            policy = construct(policy_class, config, safetensors_shapes(path), where)
            load_into(policy, path, as_held)
        else:
            policy = construct(policy_class, config, weights, where)
            policy.load_state_dict(weights)
        if made_with is not None and older_than(made_with, "0.5"):
            legacy_positions(policy.model.vlm_with_expert.get_vlm_model().vision_model.embeddings)
        files = {f"{LEROBOT_VLM_DIR}/{n}": (vlm / n).read_bytes() for n in VLM_FILES if (vlm / n).is_file()}
        return Built(policy, {TOKENIZER_STEP: {"tokenizer_name": str(vlm)}}, files)

    def make_denoiser(self) -> FlowMatching:
        return FlowMatching(self, SmolVLM(self))


__all__ = ["SMOLVLA_LAYERS", "SmolVLAProtocol"]
