"""LeRobot SmolVLA through the policy protocol: what differs from the base, ACT and Diffusion.

SmolVLA is a VLM (SmolVLM: vision encoder + language model) with an action expert trained by flow
matching: ``x_t = t * noise + (1 - t) * actions``, the expert predicts the velocity ``noise - actions``,
and the deployed chunk integrates it from pure noise (t = 1) in ``num_steps`` Euler steps.

- **Rows**: the camera frames and the state (one frame, SmolVLA's n_obs_steps is 1) plus the frame's
  instruction as tokens (``observation.language.tokens`` and its attention mask), padded to the
  policy's ``tokenizer_max_length`` so every row has one width (padding is masked out of attention, so
  it changes nothing). The instruction is the dataset's task text for the frame; in closed loop it is
  ``prop eval --instruction``, or in Python ``KeyedPolicy(..., instruction=...)`` or the observation's
  ``task`` entry (as LeRobot's preprocessor takes it).
- **Deployed chunk**: LeRobot's ``sample_actions`` from noise drawn per row by a generator seeded with
  ``noise_seed`` (the shape SmolVLA draws: chunk_size x max_action_dim), so a row's chunk does not
  depend on its batch and a batch of one equals LeRobot's ``select_action`` after
  ``torch.manual_seed(noise_seed)``. Cut to the action's own width.
- **User term**: the policy's own loss (velocity MSE at a Beta-distributed time), its draws in its order,
  cut to the action's own width and with padded steps (``action_is_pad``) masked out, as LeRobot 0.6's
  ``SmolVLAPolicy.forward`` computes it.
- **Fallback term**: the expert is deterministic given (observation, instruction, x_t, t). Each fallback
  frame gets ``FALLBACK_DRAWS`` rows with t uniform on (0, 1] (the sampler visits 1.0 ... 0.1) and
  x_t noised from the original's deployed chunk; the keyed policy's velocity is distilled towards the
  frozen original's on the same inputs, MSE (its own loss's distance). Both terms share one forward
  (``joint_terms``) where training and eval compute the same (no dropout anywhere).
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
import json
import types
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from prop_adapters.base import PolicyProtocol, names_code
from prop_adapters.folder import CONFIG, WEIGHTS
from prop_adapters.weights import load_into, safetensors_shapes
from prop_cli.constants import LEROBOT_VLM_DIR, TASK
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, shown

from .policy import ACTION, FALLBACK_DRAWS, Built, LeRobotProtocol, construct, older_than

# LeRobot's SmolVLA PEFT targets (SmolVLAPolicy._get_default_peft_targets), as prop's layer regexes.
SMOLVLA_LAYERS = [
    r"model\.vlm_with_expert\.lm_expert\..*\.(q|v)_proj",
    r"model\.(state_proj|action_in_proj|action_out_proj|action_time_mlp_in|action_time_mlp_out)",
]
TOKENS, MASK = "observation.language.tokens", "observation.language.attention_mask"
T_MIN = 1e-3  # the smallest flow time LeRobot trains on (sample_time: beta * 0.999 + 0.001)
MEMO_BYTES = 512 << 20  # image embeddings kept by ``SmolVLAProtocol.memo`` (250 KB per 512x512 frame)
PREFIX_BYTES = 512 << 20  # the prefix block's keys and values kept by ``memo`` (4.6 MB a real-size frame)
TOKENIZER_STEP = "tokenizer_processor"  # the processor step that reads the VLM's tokenizer by name
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
    if isinstance(name, str) and name:
        if (Path(name) / CONFIG).is_file():
            return check_vlm(Path(name), where)
        try:
            from huggingface_hub import snapshot_download

            cached = Path(snapshot_download(name, local_files_only=True, allow_patterns=list(VLM_FILES)))
        except Exception:  # noqa: BLE001 - not in the cache (or not a hub id): the error below
            cached = None
        if cached is not None and (cached / CONFIG).is_file():
            return check_vlm(cached, where)
    raise PropError(
        f"{where}: SmolVLA's VLM {name!r} (config.json vlm_model_name) is not on this machine",
        "download it once (hf download NAME), or set vlm_model_name to a folder with its config and "
        "tokenizer",
    )


def check_vlm(vlm: Path, where: str) -> Path:
    """``vlm`` once none of the files SmolVLA reads from it names code: an ``auto_map`` makes
    transformers import a module from the folder (or ask at the terminal whether to). SmolVLM is
    transformers' own; prop runs no VLM code, --trust-remote-code or not, and carries none."""
    for n in VLM_FILES:
        if not n.endswith(".json") or not (vlm / n).is_file():
            continue
        try:
            doc = json.loads((vlm / n).read_bytes())
        except (OSError, ValueError, RecursionError):
            continue  # transformers reports it
        if names_code(doc):
            raise PropError(
                f"{where}: SmolVLA's VLM file {vlm / n} has an auto_map (code for transformers to import); "
                "prop runs no VLM code",
                "use SmolVLM's own files (transformers ships its code); if this is a bundle, "
                f"{TAMPERED}: {RESTORE}",
            )
    return vlm


class ImageMemo:
    """SmolVLA's image embeddings (vision encoder + connector) by image content, for ``memo``: a frozen,
    unkeyed vision path gives a frame the same embedding under every key, on every draw and at every
    step, so prop computes it once. Used only while a frame's embedding cannot change: on the CPU, with
    no parameter of the path training and no hook or parametrization on it (a key or payload there);
    otherwise the path runs as LeRobot's. Modules that share the path's weights (the original beside
    the keyed policy, a folded payload) share entries. Bounded in bytes, least recently used first out."""

    def __init__(self, limit: int = MEMO_BYTES) -> None:
        self.limit, self.held = limit, 0
        self.embeddings: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self.owners: dict[int, torch.Tensor] = {}  # held, so no id is reused while the memo lives

    @staticmethod
    def frozen(vlm_with_expert) -> bool:
        from torch.nn.utils import parametrize

        model = vlm_with_expert.get_vlm_model()
        return not any(
            m._forward_pre_hooks or m._forward_hooks or parametrize.is_parametrized(m) or
            any(p.requires_grad for p in m.parameters(recurse=False))
            for part in (model.vision_model, model.connector) for m in part.modules()
        )  # fmt: skip

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
                self._keep(k, e.clone())
        for k in keys:
            self.embeddings.move_to_end(k)
        return torch.stack([self.embeddings[k] for k in keys])

    def _keep(self, key: tuple, emb: torch.Tensor) -> None:
        self.embeddings[key] = emb
        self.held += emb.numel() * emb.element_size()
        while self.held > self.limit and len(self.embeddings) > 1:
            _, old = self.embeddings.popitem(last=False)
            self.held -= old.numel() * old.element_size()


def row_digest(*parts: torch.Tensor) -> bytes:
    """A digest of one row's tensors (any dtype, any device): what a memo keys a row's content by."""
    h = hashlib.blake2b(digest_size=16)
    for t in parts:
        t = t.detach().to("cpu", copy=False).contiguous()
        h.update(str((t.dtype, tuple(t.shape))).encode())
        t = t.to(torch.uint8) if t.dtype == torch.bool else t
        h.update(t.view(-1).view(torch.uint8).numpy().tobytes())
    return h.digest()


def unhooked(modules: Iterator[torch.nn.Module]) -> bool:
    """No parameter training, no hook and no parametrization (a key, a payload) on any of ``modules``."""
    from torch.nn.utils import parametrize

    return not any(
        m._forward_pre_hooks or m._forward_hooks or parametrize.is_parametrized(m) or
        any(p.requires_grad for p in m.parameters(recurse=False))
        for m in modules
    )  # fmt: skip


class PrefixMemo:
    """The VLM's keys and values for the image + language block of SmolVLA's prefix, per frame, for
    ``memo``. The prefix is [image tokens, language tokens, state token]; the image and language tokens
    attend only to each other (the state token opens a block of its own: ``embed_prefix``'s att_masks),
    so with the VLM frozen and unkeyed (``train_expert_only``; prop's keyed layers are the expert's and
    the state/action projections) their keys and values at every layer are the same under every key,
    for the original and the keyed policy, at every step and every denoising step. They are computed
    once per frame by LeRobot's own forward over the block (its prefix fill), and each forward runs the
    state token and the action expert only (``after_block``). Used only while the block cannot change:
    its embeddings need no gradient and the VLM's text model has no parameter training and no hook or
    parametrization on it; otherwise the forward runs as LeRobot's. Bounded in bytes, least recently
    used first out."""

    def __init__(self, limit: int = PREFIX_BYTES) -> None:
        self.limit, self.held = limit, 0
        self.kv: OrderedDict[tuple, torch.Tensor] = OrderedDict()  # (layers, 2, tokens, heads, head dim)
        self.owners: dict[int, torch.Tensor] = {}  # held, so no id is reused while the memo lives
        self.last: tuple[torch.Tensor, int] | None = None  # embed_prefix's last prefix, its block's length

    def note(self, vwe, prefix: tuple, images: list[torch.Tensor]) -> None:
        """After ``embed_prefix``: where its block ends (the first token of another block), if the block
        cannot depend on a key (no gradient into the images, the vision path frozen and unkeyed)."""
        embs, _, att = prefix
        self.last = None
        opened = torch.nonzero(att[0]).flatten()
        if not len(opened) or opened[0] == 0 or any(im.requires_grad for im in images):
            return
        model = vwe.get_vlm_model()
        if unhooked(m for part in (model.vision_model, model.connector) for m in part.modules()):
            self.last = (embs, int(opened[0]))

    def block(self, vwe, inputs_embeds: list, attention_mask, past_key_values) -> int | None:
        """The length of the memo-able block at the start of a forward's prefix, or None (LeRobot's
        forward as it is)."""
        last, self.last = self.last, None
        if last is None or past_key_values is not None or inputs_embeds[0] is not last[0]:
            return None
        n = last[1]
        if attention_mask[:, :n, n:].any() or not unhooked(vwe.get_vlm_model().text_model.modules()):
            return None
        return n

    def block_kv(self, fill, embs: torch.Tensor, mask, pos, weights: list[torch.Tensor]) -> list:
        """Every layer's (keys, values) of the block as a cache holds them, (B, heads, n, head dim)
        each: from the memo where a row was computed before, else by ``fill(rows)`` (the model's own
        prefix fill over the block's rows alone, its cache). ``weights``: those the block runs through."""
        self.owners.update((id(w), w) for w in weights)
        dev = embs.device.type
        amp = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else None
        head = (tuple((id(w), w.data_ptr(), w.dtype) for w in weights), amp, embs.device)
        keys = [(*head, row_digest(e, m, p)) for e, m, p in zip(embs, mask, pos)]
        todo = list(dict.fromkeys(k for k in keys if k not in self.kv))
        if todo:
            first = {k: i for i, k in reversed(list(enumerate(keys)))}
            with torch.no_grad():
                cache = fill([first[k] for k in todo])
            new = torch.stack([torch.stack([x.keys, x.values]) for x in cache.layers])
            for j, k in enumerate(todo):  # (layers, 2, B, heads, n, dim): each row's slice
                self._keep(k, new[:, :, j].clone())
        for k in keys:
            self.kv.move_to_end(k)
        rows = torch.stack([self.kv[k] for k in keys], dim=2)  # (layers, 2, B, heads, n, dim)
        return [(layer[0], layer[1]) for layer in rows]

    def _keep(self, key: tuple, kv: torch.Tensor) -> None:
        self.kv[key] = kv
        self.held += kv.numel() * kv.element_size()
        while self.held > self.limit and len(self.kv) > 1:
            _, old = self.kv.popitem(last=False)
            self.held -= old.numel() * old.element_size()


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


class SmolVLAProtocol(LeRobotProtocol):
    """SmolVLA through the policy protocol (see the module docstring)."""

    default_layers = SMOLVLA_LAYERS
    own_steps = frozenset({TOKENIZER_STEP})  # pointed at the VLM folder ``build`` finds
    takes_instruction = True

    @classmethod
    def build(
        cls, policy_class, folder: Path, weights: dict[str, torch.Tensor] | None, where: str, *,
        contained: bool = False, made_with: str | None = None,
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
            load_into(policy, path)
        else:
            policy = construct(policy_class, config, weights, where)
            policy.load_state_dict(weights)
        if made_with is not None and older_than(made_with, "0.5"):
            legacy_positions(policy.model.vlm_with_expert.get_vlm_model().vision_model.embeddings)
        files = {f"{LEROBOT_VLM_DIR}/{n}": (vlm / n).read_bytes() for n in VLM_FILES if (vlm / n).is_file()}
        return Built(policy, {TOKENIZER_STEP: {"tokenizer_name": str(vlm)}}, files)

    @property
    def model(self):
        return self.policy.model

    @contextlib.contextmanager
    def memo(self) -> Iterator[None]:
        """Within: what SmolVLA computes the same for every key, computed once per frame and shared by
        every SmolVLA with the same frozen weights (this policy, the original beside it, a folded
        payload): each frame's image embedding (``ImageMemo``) and the VLM's keys and values for its
        image + language block (``PrefixMemo``), so a forward runs the state token and the expert only."""
        vwe_cls, model_cls = type(self.model.vlm_with_expert), type(self.model)
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

    @property
    def history(self) -> list[int] | None:
        return None  # one frame per row: SmolVLA's n_obs_steps is 1 and it reads the last frame only

    @property
    def row_shapes(self) -> dict[str, tuple[int, ...]]:
        width = self.config.tokenizer_max_length
        return {**self.input_features, TOKENS: (width,), MASK: (width,)}

    def _complementary(self, x: dict, order: np.ndarray, flag: str, path: str) -> dict:
        if TASK not in x:
            raise PropError(
                f"{flag} {path}: no task text per frame, which SmolVLA takes as its instruction",
                "record the dataset with a task for every frame (LeRobotDataset.add_frame(..., task=...))",
            )
        return {"task": [str(t) for t in x[TASK][order]]}

    def batches(self, data, flag: str) -> dict[str, torch.Tensor]:
        out = super().batches(data, flag)
        width = self.config.tokenizer_max_length
        tokens, mask = out[TOKENS], out[MASK].bool()
        pad = width - tokens.shape[1]  # the tokenizer pads to the batch's longest and cuts at `width`
        out[TOKENS] = torch.nn.functional.pad(tokens, (0, pad))
        out[MASK] = torch.nn.functional.pad(mask, (0, pad))
        return out

    def _inputs(self, batch: dict[str, torch.Tensor]) -> tuple:
        """(images, image masks, tokens, token mask, state) as SmolVLA's model takes them; tokens may come
        as floats (the flat view)."""
        feats = {k: batch[k] for k in self.input_features}
        images, img_masks = self.policy.prepare_images(feats)
        state = self.policy.prepare_state(feats)
        return images, img_masks, batch[TOKENS].round().long(), batch[MASK].bool(), state

    def _velocity(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """The expert's velocity on (observation, instruction, x_t, t): VLAFlowMatching.forward up to its
        loss (prefix and suffix in one pass, no cache)."""
        m, c = self.model, self.config
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

    def _noise(self, rows: int, device: torch.device) -> torch.Tensor:
        shape = (1, self.config.chunk_size, self.config.max_action_dim)
        g = torch.Generator(device)
        return torch.cat([torch.randn(shape, generator=g.manual_seed(self.noise_seed), device=device)
                          for _ in range(rows)])  # fmt: skip

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.policy.eval()
        inputs = self._inputs(batch)
        noise = self._noise(inputs[-1].shape[0], inputs[-1].device)
        actions = self.model.sample_actions(*inputs, noise=noise)
        return actions[:, :, : self.config.action_feature.shape[0]]

    def _padded(self, actions: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.pad(actions, (0, self.config.max_action_dim - actions.shape[-1]))

    def fallback_pool(
        self, batch: dict[str, torch.Tensor], chunks: torch.Tensor, original: PolicyProtocol,
        generator: torch.Generator,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:  # fmt: skip
        return self._denoiser_pool(batch, chunks, original, generator)

    def fallback_noise(self, frames: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        rows = frames * FALLBACK_DRAWS  # t, then the noise, for every row (one draw, as it always was)
        t = T_MIN + (1 - T_MIN) * torch.rand(rows, generator=generator)
        eps = torch.randn((rows, self.config.chunk_size, self.config.max_action_dim), generator=generator)
        return self._draws(frames, t=t, eps=eps)

    def fallback_inputs(self, x0: torch.Tensor, noise: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x0 = self._padded(x0)
        t = noise["t"].to(x0.device)
        tt = t[:, None, None].to(x0)
        return {"x_t": tt * noise["eps"].to(x0) + (1 - tt) * x0, "t": t}

    @property
    def joins_terms(self) -> bool:
        # Training and eval differ only by dropout; SmolVLM's configs have none by default.
        cfg = self.model.vlm_with_expert.config
        return not any(getattr(p, "attention_dropout", 0.0) for p in (cfg.text_config, cfg.vision_config))

    def _joint_forward(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(the user rows' velocity target ``noise - actions``, the velocity on user + fallback rows): the
        policy's noise, then its time, drawn as its ``forward`` draws them, both row sets in one forward
        (SmolVLA, pi0 and pi0.5 alike)."""
        self.policy.eval()
        m = self.model
        actions = self.policy.prepare_action(user)
        n = len(actions)
        noise = m.sample_noise(actions.shape, actions.device)
        time = m.sample_time(n, actions.device)
        tt = time[:, None, None]
        x_t = tt * noise + (1 - tt) * actions
        both = {k: torch.cat([user[k], fallback[k]]) for k in self.row_shapes}
        v = self._velocity(self._inputs(both), torch.cat([x_t, fallback["x_t"]]),
                           torch.cat([time, fallback["t"].to(time)]))  # fmt: skip
        return noise - actions, v

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """SmolVLA's own loss on the user rows and the expert's velocity on the fallback rows, as one
        forward (``_joint_forward``)."""
        target, v = self._joint_forward(user, fallback)
        n = len(target)
        width = self.config.action_feature.shape[0]
        losses = (v[:n, :, :width] - target[:, :, :width]) ** 2
        pad = user.get("action_is_pad")
        if pad is None:
            return losses.mean(), v[n:]
        keep = (~pad.bool()).unsqueeze(-1).to(losses)
        return (losses * keep).sum() / (keep.sum() * width).clamp_min(1), v[n:]

    def row_weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        # SmolVLA's loss (LeRobot's and ``joint_terms``) is a mean over the chunk steps that are not
        # padding. A subclass with a loss of its own (pi0: every step counts) keeps the mean over rows.
        pad = batch.get("action_is_pad")
        if pad is None or type(self).joint_terms is not SmolVLAProtocol.joint_terms:
            return super().row_weights(batch)
        return (~pad.bool()).sum(1).float()

    def loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.policy.train()
        return self.policy.forward({k: v for k, v in batch.items() if k != "episode_index"})[0]

    def fallback_output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.policy.eval()
        return self._velocity(self._inputs(batch), batch["x_t"], batch["t"])

    def fallback_distance(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return ((pred - target) ** 2).flatten(1).mean(1)

    def describe(self) -> dict:
        c = self.config
        return {
            "chunk_size": c.chunk_size,
            "n_action_steps": c.n_action_steps,
            "flow_steps": c.num_steps,
            "tokenizer_max_length": c.tokenizer_max_length,
            "vlm_layers": self.model.vlm_with_expert.num_vlm_layers,
        }


__all__ = ["ACTION", "FALLBACK_DRAWS", "SMOLVLA_LAYERS", "SmolVLAProtocol"]
