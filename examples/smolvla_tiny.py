"""A tiny SmolVLA built on this machine: nothing is downloaded.

SmolVLA's VLM backbone is named by ``vlm_model_name`` and read with transformers' Auto classes (config,
tokenizer, image processor). ``build_vlm`` writes such a folder for a SmolVLM of 2 text layers (hidden 64)
and 2 vision layers (hidden 32, 32x32 images in 8x8 patches), its tokenizer built with the
``tokenizers`` library (a word-level vocabulary over lower-case words and digits, with SmolVLM's special
image tokens), and SmolVLM's image processor. No weights: SmolVLA builds the VLM from the config
(``load_vlm_weights=False``) and its own model.safetensors holds every weight.

``build_smolvla`` is a SmolVLAConfig on that folder (chunk 10, 10 flow-matching steps, images resized
to 32x32) with its processors. Used by the tests (pytest -m lerobot) and examples/lerobot_reach.py.
"""

from __future__ import annotations

import json
from pathlib import Path

IMAGE = 32
WORDS = (
    "reach the goal red block pick place up down left right move arm to a of and with on in at "
    "slowly quickly higher lower".split()
)
SPECIAL = {
    "fake_image_token": "<fake_token_around_image>",
    "image_token": "<image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
}
INSTRUCTION = "reach the goal"


def _tokenizer(folder: Path) -> None:
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    vocab = {w: i for i, w in enumerate(["<pad>", "<unk>", "<|im_start|>", *SPECIAL.values()])}
    for w in [*WORDS, *"0123456789", "\n"]:
        vocab.setdefault(w, len(vocab))
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.normalizer = normalizers.Lowercase()
    # "\n" is a token of its own: SmolVLA's processor ends every instruction with one.
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [pre_tokenizers.Split("\n", "isolated"), pre_tokenizers.WhitespaceSplit()]
    )
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tok, pad_token="<pad>", unk_token="<unk>", bos_token="<|im_start|>",
        additional_special_tokens=list(SPECIAL.values()), extra_special_tokens=SPECIAL,
    )  # fmt: skip
    fast.save_pretrained(folder)


def build_vlm(folder: Path, text_layers: int = 2, hidden: int = 64, config: dict | None = None) -> Path:
    """Write a SmolVLM folder (config, tokenizer, processor; no weights) and return it: the tiny one, or
    ``config`` (SmolVLMConfig's arguments: text_config, vision_config, scale_factor, ...; e.g. a
    published SmolVLM's numbers) with the same tiny tokenizer and a processor for its image size."""
    from transformers import (
        AutoTokenizer,
        SmolVLMConfig,
        SmolVLMImageProcessor,
        SmolVLMProcessor,
        SmolVLMVideoProcessor,
    )

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _tokenizer(folder)
    tokenizer = AutoTokenizer.from_pretrained(folder)
    tiny = dict(
        text_config=dict(
            model_type="llama", vocab_size=len(tokenizer), hidden_size=hidden, intermediate_size=2 * hidden,
            num_hidden_layers=text_layers, num_attention_heads=4, num_key_value_heads=2, head_dim=hidden // 4,
            max_position_embeddings=512, rms_norm_eps=1e-5, tie_word_embeddings=False,
            pad_token_id=tokenizer.pad_token_id,
        ),
        vision_config=dict(
            hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
            image_size=IMAGE, patch_size=8,
        ),
        image_token_id=tokenizer.convert_tokens_to_ids(SPECIAL["image_token"]), scale_factor=2,
        pad_token_id=tokenizer.pad_token_id,
    )  # fmt: skip
    config = SmolVLMConfig(**(config or tiny))
    config.save_pretrained(folder)
    side = config.vision_config.image_size
    image = SmolVLMImageProcessor(
        do_resize=False, do_image_splitting=False, max_image_size={"longest_edge": side},
        size={"longest_edge": side},
    )  # fmt: skip
    # image_seq_len: one image's patches, pixel-shuffled by scale_factor (tiny: 32x32 in 8x8 -> 4 tokens).
    seq = (side // config.vision_config.patch_size) ** 2 // config.scale_factor**2
    video = SmolVLMVideoProcessor(max_image_size={"longest_edge": side}, size={"longest_edge": side})
    processor = SmolVLMProcessor(
        image_processor=image, tokenizer=tokenizer, video_processor=video, image_seq_len=seq
    )
    processor.save_pretrained(folder)
    (folder / "README.md").write_text("A SmolVLM folder from prop's examples/smolvla_tiny.py (no weights).\n")
    return folder


def build_smolvla(vlm: Path, stats: dict | None = None, features: dict | None = None, **overrides):
    """A small SmolVLA on the tiny VLM at ``vlm``: (policy, preprocessor, postprocessor)."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from examples.lerobot_reach_task import vla_features

    settings = vla_features(features) | dict(
        vlm_model_name=str(vlm), load_vlm_weights=False, chunk_size=10, n_action_steps=5,
        num_steps=10, resize_imgs_with_padding=(IMAGE, IMAGE), tokenizer_max_length=16, num_vlm_layers=2,
        max_state_dim=16, max_action_dim=4, expert_width_multiplier=0.5, freeze_vision_encoder=False,
        train_expert_only=False,
    )  # fmt: skip
    cfg = SmolVLAConfig(**(settings | overrides))
    policy = SmolVLAPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    return policy, pre, post


def describe(folder: Path) -> dict:
    return json.loads((Path(folder) / "config.json").read_text())


def record_and_build(work: Path, kind: str, general_episodes: int, user_episodes: int, **overrides) -> Path:
    """The benchmarks' set-up for any small policy: record general and user data (with the camera for
    SmolVLA, pi0 and pi0.5, which need an image), build the policy and save it after one LeRobot step;
    its folder. A tiny pi0 / pi0.5 (examples/pi_tiny.py) loads back only under ``pi_tiny.tiny()``."""
    import numpy as np

    from examples import lerobot_reach_task as task
    from examples import pi_tiny

    camera = kind in ("smolvla", *pi_tiny.KINDS)
    task.record(work / "general", general_episodes, 0, np.zeros(3, np.float32), camera=camera)
    task.record(work / "user", user_episodes, 50_000, task.USER_OFFSET, camera=camera)
    stats = task.dataset_stats(work / "general")
    if kind in pi_tiny.KINDS:
        built = pi_tiny.build_pi(kind, pi_tiny.build_tokenizer(work / "tokenizer"), stats, **overrides)
    elif camera:
        built = build_smolvla(build_vlm(work / "vlm"), stats, **overrides)
    else:
        built = task.BUILDERS[kind](stats, **overrides)
    task.train_base(work / "general", work / kind, steps=1, built=built)
    return work / kind


KINDS = ("act", "diffusion", "smolvla", "pi0", "pi05")  # what record_and_build builds
