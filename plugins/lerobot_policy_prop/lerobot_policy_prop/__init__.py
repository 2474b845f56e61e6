"""``--policy.type=prop`` for LeRobot's tools: a prop bundle, run with the user's key (or none).

LeRobot imports this package by its distribution name; importing it registers the config class, and
LeRobot's factory finds the policy (``modeling_prop.PropPolicy``) and its processors
(``processor_prop.make_prop_pre_post_processors``) beside it by naming convention.
"""

from .configuration_prop import PropConfig
from .modeling_prop import PropPolicy
from .processor_prop import make_prop_pre_post_processors

__all__ = ["PropConfig", "PropPolicy", "make_prop_pre_post_processors"]
