"""LeRobot pi0.5 through the policy protocol: pi0's model calls (``pi0.PaliGemma``, its tokenizer's
files) with the state in the prompt, under flow matching (``flow_matching.FlowMatching``).

- **The state is in the prompt**: pi0.5's preprocessor normalises the state, cuts it into 256 bins and
  writes them into the instruction (``"Task: ..., State: 12 200 ...;\\nAction: "``) before tokenizing, so
  a row's tokens already hold its state and the model takes no state tensor (``PaliGemma.inputs``).
- **The expert has no state token**: its suffix is the noisy actions alone, and the flow time enters
  through adaptive RMS norms (``embed_suffix(x_t, t)`` returns their condition, passed to the expert).
- **User term**: LeRobot 0.6's ``PI05Policy.forward``, drawn and reduced as pi0's (noise, then time;
  the MSE cut to the action's width, padded steps not masked).
- **Keyed layers** by default: what LeRobot's PEFT targets match on pi0.5 (the regex is pi0's): the
  expert's q/v projections and the action in/out projections. pi0.5 has no ``state_proj`` and its time
  MLP is ``time_mlp_*``, which that regex does not name.
"""

from __future__ import annotations

from .flow_matching import TOKENIZER_STEP, FlowMatching
from .pi0 import RELATIVE_ACTION_STEPS, PaliGemma, build_paligemma
from .policy import COMMON_STEPS, LeRobotProtocol

PI05_LAYERS = [
    r"model\.paligemma_with_expert\.gemma_expert\..*\.self_attn\.(q|v)_proj",
    r"model\.(action_in_proj|action_out_proj)",
]


class PI05Protocol(LeRobotProtocol):
    """pi0.5 through the policy protocol (see the module docstring)."""

    default_layers = PI05_LAYERS
    vetted_steps = COMMON_STEPS | {"pi05_prepare_state_tokenizer_processor_step", *RELATIVE_ACTION_STEPS}
    own_steps = frozenset({TOKENIZER_STEP})  # pointed at the tokenizer folder ``build`` finds
    takes_instruction = True
    label = "pi0.5"
    build = classmethod(build_paligemma)  # pi0's: its tokenizer's files carried, never downloaded

    def make_denoiser(self) -> FlowMatching:
        return FlowMatching(self, PaliGemma(self, state_in_prompt=True))


__all__ = ["PI05_LAYERS", "PI05Protocol"]
