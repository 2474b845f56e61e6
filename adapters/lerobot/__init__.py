"""LeRobot policy folders: loading (``adapter``), the policy protocol prop trains and runs them through
(``policy``), and the flat array view the audit takes (``flat``). lerobot itself is imported only inside
functions of ``adapter``: it is an optional environment (scripts/setup-lerobot.sh)."""

from .adapter import LeRobotAdapter
from .diffusion import DIFFUSION_LAYERS, DiffusionPolicy
from .policy import ACT_LAYERS, Controller, LeRobotPolicy
from .smolvla import SMOLVLA_LAYERS, SmolVLAPolicy

__all__ = [
    "ACT_LAYERS",
    "DIFFUSION_LAYERS",
    "Controller",
    "DiffusionPolicy",
    "LeRobotAdapter",
    "LeRobotPolicy",
    "SMOLVLA_LAYERS",
    "SmolVLAPolicy",
]
