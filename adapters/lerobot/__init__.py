"""LeRobot policy folders: loading (``adapter``), the policies prop drives (``registry.POLICIES``: one
file each, its class deriving from ``policy.LeRobotProtocol`` only; a sampling policy holds its
``policy.Denoiser``, a VLA ``flow_matching.FlowMatching``), the closed-loop ``Controller``, and the flat
array view the audit takes (``flat``). lerobot itself is imported only inside functions: it is an
optional environment (scripts/setup-lerobot.sh)."""

from .act import ACT_LAYERS, ACTProtocol
from .adapter import LeRobotAdapter
from .diffusion import DIFFUSION_LAYERS, DiffusionProtocol
from .flow_matching import Expert, FlowMatching
from .pi0 import PI0_LAYERS, PI0Protocol
from .pi05 import PI05_LAYERS, PI05Protocol
from .policy import Controller, Denoiser, LeRobotProtocol
from .registry import POLICIES
from .smolvla import SMOLVLA_LAYERS, SmolVLAProtocol

__all__ = [
    "ACT_LAYERS",
    "ACTProtocol",
    "Controller",
    "DIFFUSION_LAYERS",
    "Denoiser",
    "DiffusionProtocol",
    "Expert",
    "FlowMatching",
    "LeRobotAdapter",
    "LeRobotProtocol",
    "PI05_LAYERS",
    "PI05Protocol",
    "PI0_LAYERS",
    "PI0Protocol",
    "POLICIES",
    "SMOLVLA_LAYERS",
    "SmolVLAProtocol",
]
