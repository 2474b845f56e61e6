"""Stable-Baselines3 model zips: the adapter (``adapter``), the zip reader that unpickles nothing
(``archive``), and VecNormalize observation statistics read inertly (``vecnormalize``)."""

from .adapter import SB3Adapter, observation_array

__all__ = ["SB3Adapter", "observation_array"]
