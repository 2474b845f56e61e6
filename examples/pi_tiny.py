"""A tiny pi0 and pi0.5 built on this machine: nothing is downloaded.

LeRobot 0.6 builds pi0 and pi0.5 at PaliGemma's sizes only: their configs accept the Gemma variants
``gemma_300m`` and ``gemma_2b`` by name, and the SigLIP tower, vocabulary (257,152) and image projection
are hard-coded. ``tiny()`` shrinks them while it is active, by replacing three module-level names of
LeRobot's pi0 and pi0.5 modelling modules (restored on exit):

- ``get_gemma_config``: one small Gemma (width 64, 2 layers, 8 heads of 8: LeRobot's joint attention
  reshapes to 8 heads) for both the PaliGemma language model and the action expert;
- ``PaliGemmaForConditionalGenerationWithPiGemma``: first gets a 2-layer SigLIP (width 32, 32 x 32 images
  in 8 x 8 patches), the projection to the text width and a ``VOCAB``-word vocabulary;
- ``PiGemmaForCausalLM`` (the expert): the same vocabulary (its unused lm_head is otherwise 257,152 wide).

The config.json a tiny policy saves still names ``gemma_300m``: it loads back as the tiny model only
inside ``tiny()``. Outside it, LeRobot builds PaliGemma-300m's shapes and prop refuses the weights
("the weights do not fit the policy config.json describes"). So everything that loads a tiny pi runs in
this process under ``tiny()``: the tests (an autouse fixture), or ``python -m examples.pi_tiny ARGS``,
which is ``prop ARGS`` with the patch applied.

The tokenizer (``build_tokenizer``) stands in for PaliGemma's: a word-level vocabulary over lower-case
words, punctuation and the numbers 0..255 (pi0.5 writes its state into the prompt as 256 bins), built with
the ``tokenizers`` library, with PaliGemma's pad/eos/bos ids. ``build_pi`` makes a policy and its
processors, the tokenizer step pointed at that folder. Used by tests/adapters/test_lerobot_pi0.py.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
from collections.abc import Iterator
from pathlib import Path

IMAGE = 32
VOCAB = 320  # the tiny PaliGemma's vocabulary; the tokenizer's words fit below it (the last id is <image>)
WIDTH, DEPTH, MLP, HEADS, HEAD_DIM = 64, 2, 128, 8, 8
VISION_WIDTH, VISION_LAYERS, PATCH = 32, 2, 8
WORDS = (
    "reach the target goal red block pick place up down left right move arm to a of and with on in at "
    "task state action".split()
)
KINDS = {"pi0": ("pi0", "PI0Config", "PI0Policy"), "pi05": ("pi05", "PI05Config", "PI05Policy")}
INSTRUCTION = "reach the target"


def build_tokenizer(folder: Path) -> Path:
    """Write a PaliGemma-like word-level tokenizer to ``folder`` (tokenizer.json and its config)."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {w: i for i, w in enumerate(["<pad>", "<eos>", "<bos>", "<unk>"])}  # PaliGemma's ids 0..2
    for w in [*WORDS, *map(str, range(256)), "\n", ":", ",", ";", "-", "_", "."]:
        vocab.setdefault(w, len(vocab))
    assert len(vocab) < VOCAB
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.normalizer = normalizers.Lowercase()
    # "\n" a token of its own (pi0 ends every instruction with one), punctuation split off the words.
    split = pre_tokenizers.Split
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [split("\n", "isolated"), pre_tokenizers.Punctuation(), split(" ", "removed")]
    )
    tok.post_processor = processors.TemplateProcessing(single="<bos> $A", special_tokens=[("<bos>", 2)])
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tok, pad_token="<pad>", unk_token="<unk>", bos_token="<bos>", eos_token="<eos>"
    )
    folder = Path(folder)
    fast.save_pretrained(folder)
    return folder


def _modules() -> list:
    return [importlib.import_module(f"lerobot.policies.{k}.modeling_{k}") for k in KINDS]


@contextlib.contextmanager
def tiny() -> Iterator[None]:
    """While active, LeRobot's pi0 and pi0.5 are built at the tiny sizes above (see the docstring)."""
    from transformers import SiglipVisionConfig

    saved = []
    for module in _modules():
        gemma, paligemma, expert = (
            module.GemmaConfig, module.PaliGemmaForConditionalGenerationWithPiGemma, module.PiGemmaForCausalLM
        )  # fmt: skip

        def get_gemma_config(variant: str, gemma=gemma):
            return gemma(width=WIDTH, depth=DEPTH, mlp_dim=MLP, num_heads=HEADS, num_kv_heads=1,
                         head_dim=HEAD_DIM)  # fmt: skip

        def tiny_paligemma(config, paligemma=paligemma):
            config.vision_config = SiglipVisionConfig(
                hidden_size=VISION_WIDTH, intermediate_size=2 * VISION_WIDTH, num_hidden_layers=VISION_LAYERS,
                num_attention_heads=2, patch_size=PATCH, image_size=config.vision_config.image_size,
                vision_use_head=False, projection_dim=WIDTH, projector_hidden_act="gelu_fast",
                dtype="float32",
            )  # fmt: skip
            config.projection_dim = WIDTH
            config.text_config.vocab_size = config._vocab_size = VOCAB
            config.image_token_index = VOCAB - 1
            return paligemma(config=config)

        def tiny_expert(config, expert=expert):
            config.vocab_size = VOCAB
            return expert(config=config)

        saved.append((module, gemma, module.get_gemma_config, paligemma, expert))
        module.get_gemma_config = get_gemma_config
        module.PaliGemmaForConditionalGenerationWithPiGemma = tiny_paligemma
        module.PiGemmaForCausalLM = tiny_expert
    try:
        yield
    finally:
        for module, _, get, paligemma, expert in saved:
            module.get_gemma_config = get
            module.PaliGemmaForConditionalGenerationWithPiGemma = paligemma
            module.PiGemmaForCausalLM = expert


def build_pi(
    kind: str, tokenizer: Path, stats: dict | None = None, features: dict | None = None, **overrides
):
    """A tiny ``kind`` (pi0 or pi05) with its processors, the tokenizer step reading ``tokenizer`` (a
    folder ``build_tokenizer`` wrote): (policy, preprocessor, postprocessor)."""
    from lerobot.configs.types import NormalizationMode

    from examples.lerobot_reach_task import vla_features

    package, config_name, policy_name = KINDS[kind]
    lerobot = f"lerobot.policies.{package}"
    config_class = getattr(importlib.import_module(f"{lerobot}.configuration_{package}"), config_name)
    policy_class = getattr(importlib.import_module(f"{lerobot}.modeling_{package}"), policy_name)
    settings = vla_features(features) | dict(
        chunk_size=10, n_action_steps=5, num_inference_steps=10, max_state_dim=8,
        max_action_dim=4, image_resolution=(IMAGE, IMAGE),
        # pi0: "<bos> reach the target \n"; pi0.5: "Task: ..., State: <6 bins>;\nAction: " (19 tokens)
        tokenizer_max_length=16 if kind == "pi0" else 24,
    )  # fmt: skip
    if kind == "pi05":  # quantile statistics are not in every dataset's stats: the state's range instead
        settings["normalization_mapping"] = {
            "VISUAL": NormalizationMode.IDENTITY, "STATE": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MEAN_STD,
        }  # fmt: skip
    cfg = config_class(**(settings | overrides))
    with tiny():
        policy = policy_class(cfg)
    return (policy, *local_processors(kind, cfg, tokenizer, stats))


def local_processors(kind: str, cfg, tokenizer: Path, stats: dict | None) -> tuple:
    """LeRobot's (preprocessor, postprocessor) for a ``kind`` config, the tokenizer step reading the
    folder ``tokenizer``: LeRobot's processors name PaliGemma's hub tokenizer, this one's folder is saved
    in the preprocessor's JSON instead (where prop reads it from)."""
    from lerobot.policies.factory import make_pre_post_processors

    package = KINDS[kind][0]
    processors = importlib.import_module(f"lerobot.policies.{package}.processor_{package}")
    step = processors.TokenizerProcessorStep
    processors.TokenizerProcessorStep = lambda **kw: step(**(kw | {"tokenizer_name": str(tokenizer)}))
    try:
        return make_pre_post_processors(cfg, dataset_stats=stats)
    finally:
        processors.TokenizerProcessorStep = step


def main(argv: list[str] | None = None) -> None:
    """``prop ARGS`` with ``tiny()`` applied: a tiny pi0 folder or bundle loads only that way."""
    from prop_cli.cli.main import main as prop

    sys.argv = ["prop", *(sys.argv[1:] if argv is None else argv)]
    with tiny():
        prop()


if __name__ == "__main__":
    main()
