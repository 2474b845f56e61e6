"""A bundle run by another program's control loop: LeRobot's own tools (``lerobot-eval``,
``lerobot-record``, ``lerobot-rollout``) through the ``lerobot_policy_prop`` plugin.

The host owns the loop, the environment or robot, and its pre- and post-processing calls; prop hands it
the bundle's LeRobot policy under the user's key and the bundle's own processors. Every check ``prop run``
makes happens here, before the host takes a first action: the bundle's files and manifest (changed, code in
it, rollback), the key (enrolled in nothing: refused unless allowed) and the features the host gives
against those the bundle's policy takes.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from torch import nn

from prop_cli.bundle import load_bundle
from prop_cli.core.key_files import key_for_bundle
from prop_cli.errors import PropError

from .policy import WrongKeyWarning, module_for_key, require_enrolled


@dataclass
class Hosted:
    """What a host runs: ``module`` is the bundle's LeRobot policy under the key (a copy with the key's
    behaviour folded in, in memory only) or its base; ``pre`` and ``post`` the bundle's own processors."""

    path: str
    module: nn.Module
    pre: object
    post: object
    keyed: bool  # the key opened its holder's behaviour (False: no key, or an allowed unenrolled key)
    input_features: dict[str, tuple[int, ...]]
    output_features: dict[str, tuple[int, ...]]


def host_policy(
    bundle_path: Path,
    *,
    key_file: Path | None = None,
    passphrase: str | None = None,
    allow_unenrolled_key: bool = False,
    allow_rollback: bool = False,
    trust_remote_code: bool = False,
    through_encoder: bool = False,
) -> Hosted:
    """The bundle's LeRobot policy for a host's loop, checked as ``prop run`` checks it. The key bits live
    only in this call: what comes back holds the behaviour they open, never the key.
    ``through_encoder``: any key runs as the method answers it, unchecked (an unsealed bundle's encoder,
    what anyone holding the files can run, as ``prop attack``'s key rows do; a sealed bundle's records,
    where a wrong key opens nothing and the base runs): for measuring wrong keys in a closed loop."""
    bundle = load_bundle(
        Path(bundle_path), trust_remote_code=trust_remote_code, allow_rollback=allow_rollback
    )
    policy = bundle.loaded.policy
    if policy is None:
        raise PropError(
            f"{bundle_path} holds an array model ({bundle.loaded.kind}), not a LeRobot policy",
            "run it with prop run or prop eval; LeRobot's tools run bundles of LeRobot policies",
        )
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    if through_encoder and key is None:
        raise PropError("--policy.through_encoder runs a key, and none was given", "pass --policy.key_file")
    if through_encoder:
        module, keyed = module_for_key(bundle, key, method=True), False
    else:
        keyed = key is not None and require_enrolled(bundle, key, allow_unenrolled_key)
        with warnings.catch_warnings():
            # require_enrolled has refused an unenrolled key, or the caller allowed it: said once, below.
            warnings.simplefilter("ignore", WrongKeyWarning)
            module = module_for_key(bundle, key, allow_unenrolled=allow_unenrolled_key)
        if not keyed and key is not None:
            warnings.warn(f"{bundle_path}: the key is enrolled in nothing; running the bundle's base "
                          "(--policy.allow_unenrolled_key)", WrongKeyWarning, stacklevel=2)  # fmt: skip
    del key
    config = policy.config
    return Hosted(
        str(bundle_path), module.eval(), policy.pre, policy.post, keyed,
        {k: tuple(f.shape) for k, f in config.input_features.items()},
        {k: tuple(f.shape) for k, f in config.output_features.items()},
    )  # fmt: skip

def match_features(
    hosted: Hosted,
    given: Mapping[str, tuple[int, ...]],
    given_actions: Mapping[str, tuple[int, ...]],
    where: str,
    *,
    resize_images: bool = False,
) -> dict[str, tuple[int, ...]]:
    """Check the features a host gives (``where``: "the environment", "the robot's dataset") against the
    bundle's; return the camera features to resize (name -> the bundle's (C, H, W)). Extra features the
    host gives are left unused, as LeRobot does. A mismatch is one line naming both sides."""

    def show(features: Mapping[str, tuple[int, ...]]) -> str:
        return ", ".join(f"{k} {tuple(s)}" for k, s in features.items()) or "none"

    resize = {}
    for name, shape in hosted.input_features.items():
        have = given.get(name)
        if have is None:
            raise PropError(
                f"the bundle's policy takes {name!r}, which {where} does not give (the bundle takes "
                f"{show(hosted.input_features)}; {where} gives {show(given)})",
                "record the bundle's data with the same feature names, or map them with --rename_map",
            )
        have = tuple(have)
        if have == shape:
            continue
        camera = len(shape) == 3 and len(have) == 3 and have[0] == shape[0]
        if camera and resize_images:
            resize[name] = shape
            continue
        fix = ("pass --policy.resize_images=true to resize its frames to the bundle's size"
               if camera else "personalize from a policy trained on this environment or robot")  # fmt: skip
        raise PropError(f"{name!r} is {have} in {where} and {shape} in the bundle {hosted.path}", fix)
    for name, shape in hosted.output_features.items():
        have = given_actions.get(name)
        if have is not None and tuple(have) != shape:
            raise PropError(
                f"{name!r} is {tuple(have)} in {where} and {shape} in the bundle {hosted.path}",
                "personalize from a policy trained on this environment or robot",
            )
    return resize
