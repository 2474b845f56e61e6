"""The bundle's own pre- and post-processors (normalisation with the statistics of the data the base was
trained on, the tokenizer of a VLA): LeRobot's factory calls ``make_prop_pre_post_processors`` after it
has built the policy from the same config, so the bundle is read once (``modeling_prop``)."""

from __future__ import annotations

from .configuration_prop import PropConfig
from .modeling_prop import hosted_for


def make_prop_pre_post_processors(config: PropConfig, dataset_stats=None, **_):
    """The bundle's processors; ``dataset_stats`` (a dataset the host records into) is not used: the
    statistics are the ones the bundle's base was trained with."""
    hosted = hosted_for(config)
    return hosted.pre, hosted.post
