"""``--policy.type=prop``: which bundle, and how the user's key is given.

What LeRobot logs and dumps of a policy config (lerobot-eval prints it whole, lerobot-record keeps it) is
this dataclass: it names the bundle and the key's file, never the key. A passphrase is never an option's
value (it would be printed): ``--policy.passphrase=true`` asks for it on the terminal, or reads
PROP_PASSPHRASE where there is none.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from prop_cli.constants import ENV_DEBUG
from prop_cli.errors import PropError


def refuse(error: PropError) -> None:
    """A PropError inside LeRobot's tools: one line and exit 1, as prop's own CLI does (a traceback only
    with PROP_DEBUG set). LeRobot's scripts catch no SystemExit, so this is the whole output."""
    if os.environ.get(ENV_DEBUG):
        raise error
    print(f"prop: error: {error.line()}", file=sys.stderr)
    raise SystemExit(1)


@PreTrainedConfig.register_subclass("prop")
@dataclass
class PropConfig(PreTrainedConfig):
    # The bundle folder `prop personalize` wrote (sealed or not, personalized from a LeRobot policy).
    bundle: str | None = None
    # The user's key file (prop keygen); none and no passphrase: the original's behaviour.
    key_file: str | None = None
    # Ask for the user's passphrase on the terminal (PROP_PASSPHRASE where there is no terminal).
    passphrase: bool = False
    # Run the bundle's base with a key enrolled in nothing (scripts that measure wrong keys), with a warning.
    allow_unenrolled_key: bool = False
    # Run this copy even where it is older than one this machine has seen (prop's rollback check).
    allow_rollback: bool = False
    # Run the key through an unsealed bundle's encoder, unchecked: what anyone holding the files can run
    # with any key (prop attack's key rows). For measuring wrong keys in a closed loop, never deployment.
    through_encoder: bool = False
    # Import code the bundle names (a processor step LeRobot does not register): the user's consent.
    trust_remote_code: bool = False
    # Resize camera frames of another size to the bundle's (bilinear, antialiased), e.g. a simulator that
    # renders 480x480 for a policy trained on 96x96 frames of the same camera.
    resize_images: bool = False
    # prop runs bundles on the CPU by default (LeRobot's own default is the first accelerator it finds);
    # --policy.device=cuda moves the policy and the processors' device step there.
    device: str | None = "cpu"

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.bundle:
            refuse(PropError("--policy.type=prop needs the bundle", "pass --policy.bundle=PATH/TO/BUNDLE"))
        if self.key_file and self.passphrase:
            refuse(PropError("--policy.key_file and --policy.passphrase both given", "use one of them"))

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self):
        # lerobot-train asks for this first (TrainPipelineConfig.validate): refuse before any data loads.
        refuse(PropError(
            "lerobot-train cannot train a prop bundle (its payload is trained by prop, sealed or keyed)",
            "personalize with prop personalize CHECKPOINT --data DATA --key-file KEY; train the base policy "
            "with lerobot-train's own --policy.type",
        ))  # fmt: skip

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        """The bundle's features are matched against the host's when the policy is built (PropPolicy)."""
