"""LeRobot pi0.5 through the policy protocol: what differs from pi0 (``pi0``).

- **The state is in the prompt**: pi0.5's preprocessor normalises the state, cuts it into 256 bins and
  writes them into the instruction (``"Task: ..., State: 12 200 ...;\\nAction: "``) before tokenizing, so
  a row's tokens already hold its state and the model takes no state tensor (``_inputs``).
- **The expert has no state token**: its suffix is the noisy actions alone, and the flow time enters
  through adaptive RMS norms (``embed_suffix(x_t, t)`` returns their condition, passed to the expert).
- **User term**: LeRobot 0.6's ``PI05Policy.forward``, drawn and reduced as pi0's (noise, then time;
  the MSE cut to the action's width, padded steps not masked).
- **Keyed layers** by default: what LeRobot's PEFT targets match on pi0.5 (the regex is pi0's): the
  expert's q/v projections and the action in/out projections. pi0.5 has no ``state_proj`` and its time
  MLP is ``time_mlp_*``, which that regex does not name.
"""

from __future__ import annotations

import torch

from .pi0 import PI0Protocol
from .smolvla import MASK, TOKENS

PI05_LAYERS = [
    r"model\.paligemma_with_expert\.gemma_expert\..*\.self_attn\.(q|v)_proj",
    r"model\.(action_in_proj|action_out_proj)",
]


class PI05Protocol(PI0Protocol):
    """pi0.5 through the policy protocol (see the module docstring)."""

    default_layers = PI05_LAYERS
    label = "pi0.5"

    def _inputs(self, batch: dict[str, torch.Tensor]) -> tuple:
        """(images, image masks, tokens, token mask) as PI05Pytorch takes them: the state is in the
        tokens."""
        images, img_masks = self.policy._preprocess_images({k: batch[k] for k in self.input_features})
        return images, img_masks, batch[TOKENS].round().long(), batch[MASK].bool()

    def _suffix(self, inputs: tuple, x_t: torch.Tensor, time: torch.Tensor) -> tuple:
        return self.model.embed_suffix(x_t, time)


__all__ = ["PI05_LAYERS", "PI05Protocol"]
