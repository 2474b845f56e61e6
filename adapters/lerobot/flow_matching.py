"""What SmolVLA, pi0 and pi0.5 share, as parts each VLA's protocol holds (none derives from another).

- ``FlowMatching``: the ``policy.Denoiser`` of a flow-matching VLA (openpi's convention): ``x_t = t *
  noise + (1 - t) * actions``, the expert predicts the velocity ``noise - actions``, and the deployed
  chunk integrates it from pure noise (t = 1) in the model's Euler steps. What differs between the VLAs
  is their model (``Expert``: its inputs, its velocity, what it may compute once, its dropout).

  - **Deployed chunk**: LeRobot's ``sample_actions`` from noise drawn per row by a generator seeded
    with the policy's ``noise_seed`` (the shape the VLA draws: chunk_size x max_action_dim), so a row's
    chunk does not depend on its batch and a batch of one equals LeRobot's ``select_action`` after
    ``torch.manual_seed(noise_seed)``. Cut to the action's own width.
  - **User term**: the policy's own loss (velocity MSE at its own draw of time, its noise then its time,
    as its ``forward`` draws them), cut to the action's own width; padded steps (``action_is_pad``)
    masked out where LeRobot masks them (``Expert.masks_padding``: SmolVLA; pi0 and pi0.5 count them).
  - **Fallback term**: the expert is deterministic given (observation, instruction, x_t, t). Each
    fallback frame gets ``FALLBACK_DRAWS`` rows with t uniform on (T_MIN, 1] (the sampler visits 1.0
    ... 0.1; ``--fallback-times sampler``: only those) and x_t noised from the original's deployed
    chunk; the keyed policy's velocity is distilled towards the frozen original's on the same inputs,
    MSE. Both terms share one forward (``joint_terms``) where training and eval compute the same
    (``Expert.joins_terms``: no dropout).
- ``PrefixMemo``: the VLM's keys and values for each frame's prefix, computed once (``memo``), kept in a
  store bounded in bytes (``Bounded``, SmolVLA's image memo's too).
- ``local_folder`` and ``code_file``: the files a VLA's processors read by name (a tokenizer, a
  VLM's config) from a local folder, never a download, and none that names code.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
from abc import ABC, abstractmethod
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import torch

from prop_adapters.base import names_code
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, shown

from .policy import PAD, TOKENS, Denoiser, LeRobotProtocol

T_MIN = 1e-3  # the smallest flow time LeRobot trains on (sample_time: beta * 0.999 + 0.001)
PREFIX_BYTES = 512 << 20  # the prefix block's keys and values kept by ``memo`` (4.6 MB a real-size frame)
TOKENIZER_STEP = "tokenizer_processor"  # the processor step that reads a VLA's tokenizer by name


class Expert(ABC):
    """A flow-matching VLA's model as ``FlowMatching`` calls it: one class in the VLA's file, over the
    VLA's protocol (``owner``: its LeRobot policy, model and config). It implements ``inputs`` and
    ``velocity``; the rest has defaults."""

    masks_padding: ClassVar[bool] = False  # the policy's own loss leaves padded chunk steps out
    # Training and eval compute the same (no dropout): one forward may serve both terms (a property
    # where the model's config decides).
    joins_terms: bool = False

    def __init__(self, owner: LeRobotProtocol) -> None:
        self.owner = owner

    @abstractmethod
    def inputs(self, batch: dict[str, torch.Tensor]) -> tuple:
        """The rows as the model's ``sample_actions`` takes them (images, masks, tokens, ...); tokens may
        come as floats (the flat view)."""

    @abstractmethod
    def velocity(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """The expert's velocity on (inputs, x_t, t): the model's forward up to its loss, differentiable."""

    def memo(self) -> contextlib.AbstractContextManager:
        """``PolicyProtocol.memo``: what the model computes the same for every key, kept within."""
        return contextlib.nullcontext()

    def describe(self) -> dict:
        """What `prop inspect` shows of the model."""
        c = self.owner.config
        return {"chunk_size": c.chunk_size, "n_action_steps": c.n_action_steps}


class FlowMatching(Denoiser):
    """The denoiser of a flow-matching VLA (see the module docstring): ``owner`` is the VLA's protocol
    (its LeRobot policy, config and noise seed), ``expert`` its model."""

    def __init__(self, owner: LeRobotProtocol, expert: Expert) -> None:
        self.owner, self.expert = owner, expert

    @property
    def joins_terms(self) -> bool:
        return self.expert.joins_terms

    @property
    def width(self) -> int:
        return self.owner.config.action_feature.shape[0]

    def noise(self, rows: int, device: torch.device) -> torch.Tensor:
        """Each row's initial noise, drawn by a generator seeded with the policy's noise seed."""
        shape = (1, self.owner.config.chunk_size, self.owner.config.max_action_dim)
        g = torch.Generator(device)
        return torch.cat([torch.randn(shape, generator=g.manual_seed(self.owner.noise_seed), device=device)
                          for _ in range(rows)])  # fmt: skip

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        # LeRobot decorates pi0's and pi0.5's sample_actions with @torch.no_grad(); the audit's gradient
        # searches need the chunk's graph, so the undecorated function runs (the same chunk: callers that
        # want no graph run it under no_grad themselves). SmolVLA's is not decorated.
        self.owner.policy.eval()
        inputs = self.expert.inputs(batch)
        noise = self.noise(batch[TOKENS].shape[0], batch[TOKENS].device)
        model = self.owner.model
        actions = inspect.unwrap(type(model).sample_actions)(model, *inputs, noise=noise)
        return actions[:, :, : self.width]

    def sampler_times(self) -> torch.Tensor:
        """The times LeRobot's Euler sampler visits: 1, 1 - 1/n, ..., 1/n (n: its steps)."""
        c = self.owner.config
        n = int(getattr(c, "num_steps", None) or c.num_inference_steps)
        return 1 - torch.arange(n, dtype=torch.float32) / n

    def draws(self, rows: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        if self.owner.fallback_times == "sampler":  # only the times the closed loop runs
            visited = self.sampler_times()
            t = visited[torch.randint(0, len(visited), (rows,), generator=generator)]
        else:
            t = T_MIN + (1 - T_MIN) * torch.rand(rows, generator=generator)  # t, then the noise (one draw)
        c = self.owner.config
        return {"t": t, "eps": torch.randn((rows, c.chunk_size, c.max_action_dim), generator=generator)}

    def noised(self, x0: torch.Tensor, draws: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x0 = torch.nn.functional.pad(x0, (0, self.owner.config.max_action_dim - x0.shape[-1]))
        t = draws["t"].to(x0.device)
        tt = t[:, None, None].to(x0)
        return {"x_t": tt * draws["eps"].to(x0) + (1 - tt) * x0, "t": t}

    def output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.owner.policy.eval()
        return self.expert.velocity(self.expert.inputs(batch), batch["x_t"], batch["t"])

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The policy's own loss on the user rows (its noise, then its time, drawn as its ``forward``
        draws them) and the expert's velocity on the fallback rows, as one forward."""
        owner = self.owner
        owner.policy.eval()
        model = owner.model
        actions = owner.policy.prepare_action(user)
        n = len(actions)
        noise = model.sample_noise(actions.shape, actions.device)
        time = model.sample_time(n, actions.device)
        tt = time[:, None, None]
        x_t = tt * noise + (1 - tt) * actions
        both = {k: torch.cat([user[k], fallback[k]]) for k in owner.row_shapes}
        v = self.expert.velocity(self.expert.inputs(both), torch.cat([x_t, fallback["x_t"]]),
                                 torch.cat([time, fallback["t"].to(time)]))  # fmt: skip
        target, width = noise - actions, self.width
        if not self.expert.masks_padding:  # every step counts (pi0, pi0.5: LeRobot's own reduction)
            losses = torch.nn.functional.mse_loss(target, v[:n], reduction="none")
            return losses[:, :, :width].mean(), v[n:]
        losses = (v[:n, :, :width] - target[:, :, :width]) ** 2
        pad = user.get(PAD)
        if pad is None:
            return losses.mean(), v[n:]
        keep = (~pad.bool()).unsqueeze(-1).to(losses)
        return (losses * keep).sum() / (keep.sum() * width).clamp_min(1), v[n:]

    def row_weights(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        # A masked loss is a mean over the chunk steps that are not padding; an unmasked one over rows.
        pad = batch.get(PAD)
        return None if pad is None or not self.expert.masks_padding else (~pad.bool()).sum(1).float()

    def memo(self) -> contextlib.AbstractContextManager:
        return self.expert.memo()

    def describe(self) -> dict:
        return self.expert.describe()


# ---- the files a VLA's processors read by name -------------------------------------------------------


def local_folder(name: object, marker: str, patterns: list[str]) -> Path | None:
    """The local folder ``name`` gives (a config's or a processor's hub id or folder): the name as a
    folder holding ``marker``, or the name's snapshot in the hub cache (offline: never a download; only
    ``patterns`` read); None where neither is on this machine."""
    if not isinstance(name, str) or not name:
        return None
    if (Path(name) / marker).is_file():
        return Path(name)
    try:
        from huggingface_hub import snapshot_download

        cached = Path(snapshot_download(name, local_files_only=True, allow_patterns=patterns))
    except Exception:  # noqa: BLE001 - not in the cache (or not a hub id)
        return None
    return cached if (cached / marker).is_file() else None


def code_file(folder: Path, names: tuple[str, ...]) -> Path | None:
    """The first JSON file of ``names`` in ``folder`` that names code (an ``auto_map``: transformers would
    import a module from the folder, or ask at the terminal whether to); None if none does."""
    for n in names:
        if not n.endswith(".json") or not (folder / n).is_file():
            continue
        try:
            doc = json.loads((folder / n).read_bytes())
        except (OSError, ValueError, RecursionError):
            continue  # transformers reports it
        if names_code(doc):
            return folder / n
    return None


# JSON files transformers reads by name whose keys are words of the vocabulary, not settings.
VOCABULARIES = ("tokenizer.json", "added_tokens.json", "vocab.json")


def _file_fields(doc: object) -> Iterator[tuple[str, object]]:
    """Every field of a parsed JSON document, at any depth, whose name ends in ``_file`` or ``_files``
    (transformers opens a tokenizer's ``*_file`` arguments as paths), with its value."""
    stack = [doc]
    while stack:
        node = stack.pop()
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for k, v in items:
            if isinstance(k, str) and k.endswith(("_file", "_files")):
                yield k, v
            if isinstance(v, (dict, list)):
                stack.append(v)


def _sibling(folder: Path, name: object) -> bool:
    """``name`` is a plain file name of a regular file in ``folder`` (no folder, no link)."""
    plain = isinstance(name, str) and name not in ("", ".", "..") and not {"/", "\\", "\0"} & set(name)
    return plain and not (folder / name).is_symlink() and (folder / name).is_file()


def outside_file(folder: Path, names: tuple[str, ...]) -> tuple[str, str, object] | None:
    """The first field of a settings file of ``names`` in ``folder`` (a tokenizer's or processor's JSON)
    that makes transformers read a file from outside ``folder``: (file, field, value), or None.

    A ``*_file`` field with any value but null: transformers opens it as a path, an absolute one
    anywhere, a relative one or a plain name from the working folder (measured: ``"tokenizer_file":
    "tokenizer.json"`` read the working folder's, not the tokenizer's); left null or out, it reads the
    folder's own file. A ``*_files`` list: each entry must name a file in ``folder`` (transformers looks
    it up there). In a bundle, every file in the folder is one the manifest lists."""
    for n in names:
        if not n.endswith(".json") or n in VOCABULARIES or not (folder / n).is_file():
            continue
        try:
            doc = json.loads((folder / n).read_bytes())
        except (OSError, ValueError, RecursionError):
            continue  # transformers reports it
        for field, value in _file_fields(doc):
            listed = field.endswith("_files") and isinstance(value, list)
            if value is not None and not (listed and all(_sibling(folder, v) for v in value)):
                return n, field, value
    return None


def refuse_outside_file(folder: Path, names: tuple[str, ...], what: str, where: str) -> None:
    """``outside_file`` as the one-line refusal, naming the file, the field and its value."""
    found = outside_file(folder, names)
    if found is not None:
        n, field, value = found
        raise PropError(
            f"{where}: {what} file {folder / n} names {field} {shown(repr(value))}: transformers would read "
            f"it from outside {folder.name}/ (a plain name: from the working folder), a file no hash covers",
            f"leave {field} out (or null): transformers then reads the folder's own file; if this is a "
            f"bundle, {TAMPERED}: {RESTORE}",
        )


# ---- what a VLA computes once per frame ----------------------------------------------------------------


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


class Bounded(OrderedDict):
    """A memo's tensors by key, bounded in bytes: least recently used first out."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit, self.held = limit, 0

    def keep(self, key: tuple, t: torch.Tensor) -> None:
        self[key] = t
        self.held += t.numel() * t.element_size()
        while self.held > self.limit and len(self) > 1:
            _, old = self.popitem(last=False)
            self.held -= old.numel() * old.element_size()

    def rows(self, keys: list[tuple]) -> list[torch.Tensor]:
        """The tensors of ``keys`` (each held), now the most recently used."""
        for k in keys:
            self.move_to_end(k)
        return [self[k] for k in keys]


class PrefixMemo:
    """The VLM's keys and values for the first block of a VLA's prefix, per frame, for ``memo`` (pi0's
    and pi0.5's whole prefix; SmolVLA's image + language block). SmolVLA's prefix is [image tokens,
    language tokens, state token]; the image and language tokens attend only to each other (the state
    token opens a block of its own: ``embed_prefix``'s att_masks), so with the VLM frozen and unkeyed
    (``train_expert_only``; prop's keyed layers are the expert's and the state/action projections) their
    keys and values at every layer are the same under every key, for the original and the keyed policy,
    at every step and every denoising step. They are computed once per frame by LeRobot's own forward
    over the block (its prefix fill), and each forward runs the rest (SmolVLA: the state token and the
    action expert, ``smolvla.after_block``). Used only while the block cannot change: its embeddings need
    no gradient and the VLM's text model has no parameter training and no hook or parametrization on
    it; otherwise the forward runs as LeRobot's. Bounded in bytes, least recently used first out."""

    def __init__(self, limit: int = PREFIX_BYTES) -> None:
        self.kv = Bounded(limit)  # (layers, 2, tokens, heads, head dim) per frame
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
                self.kv.keep(k, new[:, :, j].clone())
        rows = torch.stack(self.kv.rows(keys), dim=2)  # (layers, 2, B, heads, n, dim)
        return [(layer[0], layer[1]) for layer in rows]


