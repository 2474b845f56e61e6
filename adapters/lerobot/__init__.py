"""LeRobot policy folders: loading (``adapter``), the policies prop drives (``registry.POLICIES``: one
file each, ``act``, ``diffusion``, ``smolvla``, ``pi0``, ``pi05``, over the shared
``policy.LeRobotProtocol`` and its closed-loop ``Controller``), and the flat array view the audit takes
(``flat``). lerobot itself is imported only inside functions: it is an optional environment
(scripts/setup-lerobot.sh)."""

from .act import ACT_LAYERS, ACTProtocol
from .adapter import LeRobotAdapter
from .diffusion import DIFFUSION_LAYERS, DiffusionProtocol
from .pi0 import PI0_LAYERS, PI0Protocol
from .pi05 import PI05_LAYERS, PI05Protocol
from .policy import Controller, LeRobotProtocol
from .registry import POLICIES
from .smolvla import SMOLVLA_LAYERS, SmolVLAProtocol

__all__ = [
    "ACT_LAYERS",
    "ACTProtocol",
    "Controller",
    "DIFFUSION_LAYERS",
    "DiffusionProtocol",
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
