"""The environment `prop eval` rolls out in (``--env``): a gymnasium id, or the user's own factory.

- ``Pendulum-v1``: a registered gymnasium id, made by ``gymnasium.make``;
- ``package:Id``: the package is imported first, so that it registers ``Id`` (``panda_gym:PandaReach-v3``);
- ``package.module:make`` or ``path/to/file.py:make``: the user's factory, called with no arguments
  (``render_mode="rgb_array"`` with ``--video``, gymnasium's own convention), which returns the
  environment. Naming it on the command line is the user's consent to run it, as with ``--arch`` and
  ``--metric``; a bundle never names one.

When the module both registers ``Id`` with gymnasium and has an attribute ``Id``, the registered id wins
(``gymnasium.make`` adds the registration's time limit), as before factories were accepted.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable

import numpy as np

from prop_adapters.module import code_attribute, import_code
from prop_cli.errors import PropError, brief

from .streams import stdout_to_stderr

ENV_FORMS = (
    "give a registered gymnasium id (package:Id imports the package first: panda_gym:PandaReach-v3) or your "
    "factory (package.module:make or path/to/file.py:make)"
)
RENDER_MODE = "rgb_array"


def make_env(env_id: str, render: bool = False, seed: int = 0):
    """The environment ``--env`` names (module docstring). ``render``: frames from ``env.render()``
    (render_mode rgb_array), for --video; checked here with one frame after ``reset(seed=seed)``, so a
    missing renderer (pygame) is reported before any rollout."""
    try:
        import gymnasium as gym
    except ImportError:
        raise PropError(
            "prop eval needs gymnasium", "pip install gymnasium (and the environment's package)"
        ) from None
    # Simulators print banners from C (pybullet's argv lines): keep stdout for results (--json).
    with stdout_to_stderr():
        factory = env_factory(env_id, gym.registry)
        env = _call(env_id, factory, render) if factory is not None else _gym_make(gym, env_id, render)
        if render:
            _check_render(env, env_id, seed)
    return env


def env_factory(env_id: str, registry) -> Callable | None:
    """The user's factory ``env_id`` names, or None where it is a gymnasium id (after importing the
    module of a ``package:Id``, which registers it)."""
    mod_name, sep, attr = env_id.rpartition(":")
    if not sep or not mod_name or not attr:
        if env_id.endswith(".py"):
            raise PropError(f"--env '{env_id}' names a file but no factory in it", "write it as file.py:make")
        return None  # a plain id
    what = f"--env '{env_id}'"
    module = import_code(mod_name, what)
    if not mod_name.endswith(".py") and attr in registry:
        return None  # the module registered it: gymnasium.make, with the registration's wrappers
    factory = code_attribute(module, attr)
    if factory is None:
        near = _near(attr, module, registry)
        if near is not None:  # a typo: name the module's own names, not gymnasium's registry
            ids = "" if mod_name.endswith(".py") else f" and registers no gymnasium id {attr!r}"
            raise PropError(
                f"{what}: {mod_name} has no {attr!r}{ids}", f"did you mean --env {mod_name}:{near}?"
            )
        if mod_name.endswith(".py"):
            raise PropError(f"{what}: {mod_name} has no attribute '{attr}'", "check the name after the ':'")
        return None  # not an attribute: gymnasium.make says what is wrong with the id
    if not callable(factory):
        raise PropError(f"{what}: '{attr}' is a {type(factory).__name__}, not callable", ENV_FORMS)
    return factory


def _near(attr: str, module, registry) -> str | None:
    """The module's public callable or the registered id closest to ``attr`` (difflib), if any is
    close: what a mistyped ``module:attr`` most likely meant."""
    import difflib

    names = [n for n in dir(module) if not n.startswith("_") and callable(getattr(module, n, None))]
    close = difflib.get_close_matches(attr, [*names, *registry], n=1, cutoff=0.7)
    return close[0] if close else None


def _gym_make(gym, env_id: str, render: bool):
    try:
        return gym.make(env_id, render_mode=RENDER_MODE) if render else gym.make(env_id)
    except Exception as e:  # noqa: BLE001 - unknown id, missing package, bad arguments
        raise PropError(f"--env {env_id!r}: gymnasium cannot make it ({brief(e)})", ENV_FORMS) from None


def _takes_render_mode(factory: Callable) -> bool:
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):  # a builtin without a signature: let the call say
        return True
    return any(p.name == "render_mode" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def _call(env_id: str, factory: Callable, render: bool):
    name = env_id.rpartition(":")[2]
    if render and not _takes_render_mode(factory):
        raise PropError(
            f"--video: --env '{env_id}' is called as {name}(render_mode='rgb_array'), and {name} takes no "
            "render_mode",
            "give it a render_mode=None parameter passed on to the environment, or drop --video",
        )
    call = f"{name}(render_mode='rgb_array')" if render else f"{name}()"
    try:
        env = factory(render_mode=RENDER_MODE) if render else factory()
    except Exception as e:  # noqa: BLE001 - anything the user's factory raises
        raise PropError(
            f"--env '{env_id}': {call} raised {brief(e)}",
            "fix the factory (prop calls it with no arguments, and render_mode='rgb_array' for --video)",
        ) from None
    if not all(callable(getattr(env, m, None)) for m in ("reset", "step")):
        raise PropError(
            f"--env '{env_id}': {call} returned a {type(env).__name__}, not an environment (no reset/step)",
            "return the environment (a gymnasium.Env)",
        )
    return env


def frame(env) -> np.ndarray:
    """One rendered frame, checked: an (H, W, 3) array."""
    image = env.render()
    if not isinstance(image, np.ndarray) or image.ndim != 3:
        raise PropError("--video: the environment renders no rgb_array frames", "drop --video")
    return image


def _check_render(env, env_id: str, seed: int) -> None:
    try:
        env.reset(seed=seed)
        frame(env)
    except PropError:
        raise
    except Exception as e:  # noqa: BLE001 - gymnasium's DependencyNotInstalled, an ImportError, a GL error
        missing = _missing_module(e)
        if missing is None:
            raise PropError(f"--video: {env_id} cannot render ({brief(e)})", "drop --video") from None
        hint = re.search(r"`(pip install [^`]+)`", str(e))
        extra = f" (or, as the environment suggests, {hint.group(1)})" if hint else ""
        raise PropError(
            f"--video: {env_id} renders with {missing}, which is not installed",
            f"pip install {missing}{extra}, or drop --video",
        ) from None


def _missing_module(e: BaseException | None) -> str | None:
    """The top-level package an ImportError in ``e``'s chain could not import (gymnasium wraps it in
    DependencyNotInstalled), else the one its message names ("pygame is not installed")."""
    first = e
    while e is not None:
        if isinstance(e, ImportError) and e.name:
            return e.name.split(".")[0]
        e = e.__cause__ or e.__context__
    named = re.match(r"([\w.-]+) is not installed", str(first))
    return named.group(1) if named else None
