"""The LeRobot policies prop supports: policy type -> the class that drives it (``policy.LeRobotProtocol``).

The type is LeRobot's (config.json ``type``) and is stored in a bundle's manifest as ``model.type``:
never rename one. A new policy is one file beside these (its class, deriving from ``LeRobotProtocol``
only) and one line here; the types the adapter loads, the manifest accepts (``LeRobotAdapter.
manifest_fields``) and ``prop formats`` lists all come from this table.
"""

from __future__ import annotations

from .act import ACTProtocol
from .diffusion import DiffusionProtocol
from .pi0 import PI0Protocol
from .pi05 import PI05Protocol
from .policy import LeRobotProtocol
from .smolvla import SmolVLAProtocol

POLICIES: dict[str, type[LeRobotProtocol]] = {
    "act": ACTProtocol,
    "diffusion": DiffusionProtocol,
    "smolvla": SmolVLAProtocol,
    "pi0": PI0Protocol,
    "pi05": PI05Protocol,
}
