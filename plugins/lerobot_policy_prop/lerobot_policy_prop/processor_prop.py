"""The bundle's own pre- and post-processors (normalisation with the statistics the base was trained
with, a VLA's tokenizer), as prop vetted and built them when it read the bundle.

``--policy.type=prop --policy.bundle=B``: LeRobot's factory calls ``make_prop_pre_post_processors`` after
it has built the policy from the same config. ``--policy.path=FOLDER`` (what ``prop export --lerobot``
writes, for tools that load only by path: lerobot-rollout, the async policy server): LeRobot reads the
folder's processor files itself, and those hold one step of prop's, ``BundleProcessorStep``, between
LeRobot's own rename and device steps (which LeRobot's tools override); it runs the bundle's processors.
The folder holds no copy of the bundle's files, so nothing in it can drift from what the bundle verifies.
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.processor import ProcessorStep, ProcessorStepRegistry

from prop_cli.errors import PropError

from .configuration_prop import PropConfig, refuse
from .modeling_prop import hosted_for, last_hosted

STEP = "prop_bundle_processor"  # the registry name the folder's processor files give (prop export --lerobot)


def make_prop_pre_post_processors(config: PropConfig, dataset_stats=None, **_):
    """The bundle's processors; ``dataset_stats`` (a dataset the host records into) is not used: the
    statistics are the ones the bundle's base was trained with."""
    hosted = hosted_for(config)
    return hosted.pre, hosted.post


@ProcessorStepRegistry.register(name=STEP)
@dataclass
class BundleProcessorStep(ProcessorStep):
    """The steps of the bundle's own preprocessor (``stage="pre"``) or postprocessor (``"post"``), run on
    LeRobot's transition in order. LeRobot's tools build the policy first: its bundle is the one run."""

    stage: str = "pre"

    def _pipeline(self):
        hosted = last_hosted()
        if hosted is None:
            refuse(PropError("a prop policy folder's processors were loaded before its policy",
                             "load the policy first (LeRobot's tools do); in Python: make_policy, then "
                             "make_pre_post_processors"))  # fmt: skip
        if self.stage not in ("pre", "post"):
            refuse(PropError(f"{STEP}: stage {self.stage!r}", "stage is pre or post (prop export --lerobot)"))
        return hosted.pre if self.stage == "pre" else hosted.post

    def __call__(self, transition):
        for step in self._pipeline().steps:
            transition = step(transition)
        return transition

    def get_config(self) -> dict:
        return {"stage": self.stage}

    def transform_features(self, features):
        hosted = last_hosted()
        if hosted is None:
            return features
        for step in self._pipeline().steps:
            features = step.transform_features(features)
        return features
