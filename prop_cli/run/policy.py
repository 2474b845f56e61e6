"""Running a bundle: the key is turned into behaviour once (folded into a copy of the weights), then
each step is a base step.

``KeyedPolicy(bundle, key)`` is the closed-loop API for every bundle. An array model's ``predict(obs)``
is Stable-Baselines3's ``predict(observation, state=None, episode_start=None, deterministic=True)``:
numpy in, ``(action, state)`` out, one observation or a batch, continuous actions clipped to the bounds
the checkpoint records, the argmax for discrete actions. A policy with named observation features
(LeRobot) takes LeRobot's observation dict in ``select_action(obs)`` (``predict`` too) and returns
what LeRobot's ``select_action`` returns between the bundle's own pre- and postprocessor, with its
queues (``reset()`` between episodes): the controller ``prop eval`` drives. ``run_policy`` runs such
a policy over a dataset. The counterpart for an ONNX export is ``prop_cli.run.onnx``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from prop_adapters import LoadedModel
from prop_adapters.sb3 import observation_array
from prop_adapters.sb3.vecnormalize import ObsNormalizer
from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.datasources import Dataset, load_data
from prop_cli.errors import PropError

from .inputs import load_inputs

ROWS = 256  # frames per forward when running a whole dataset through a policy


class WrongKeyWarning(UserWarning):
    """A key enrolled in nothing of the bundle, run anyway (``allow_unenrolled``): the bundle's base runs
    (which is the original only if the bundle is what its publisher made: ``prop verify``)."""


BASE_RUNS = "running the bundle's base, not a keyed behaviour"
ALLOW_UNENROLLED = "--allow-unenrolled-key"
UNENROLLED_FIX = (
    "get the bundle again from whoever you trust, or run it without your key; to run its base with this "
    f"key anyway (scripts that test wrong keys): {ALLOW_UNENROLLED} (allow_unenrolled=True in Python)"
)


def key_opens_nothing(why: str, allow: bool, runs: str = BASE_RUNS, stacklevel: int = 3) -> None:
    """The one decision for a key that opens nothing where it is given (``why``: which bundle or export,
    and why). By default a PropError: the user meant their key to run something, and a bundle replaced,
    or one whose user was removed (which needs no key), must not quietly run someone else's base. With
    ``allow`` (``--allow-unenrolled-key``, for scripts that measure wrong keys) the base runs, with a
    WrongKeyWarning saying so."""
    if not allow:
        raise PropError(why, UNENROLLED_FIX)
    warnings.warn(f"{why}: {runs}", WrongKeyWarning, stacklevel=stacklevel)


def require_enrolled(bundle: Bundle, key: np.ndarray | None, allow: bool) -> bool:
    """Before a command's work: whether ``key`` is enrolled in the bundle as it is now (None: no key,
    True). A key enrolled in nothing is refused here unless ``allow`` (``key_opens_nothing``; the run
    itself then warns); a bundle changed since the key was enrolled is a PropError either way."""
    if key is None:
        return True
    if bundle.mode.enrolled(bundle.check_key(key)):
        return True
    if not allow:
        key_opens_nothing(bundle.mode.not_enrolled(str(bundle.path)), allow)
    return False


def module_for_key(
    bundle: Bundle, key: np.ndarray | None, *, method: bool = False, allow_unenrolled: bool = False
) -> nn.Module:
    """The bundle's module under ``key``: the base without a key; with one, a copy showing what the key
    unlocks (never written anywhere: it is the personalized policy in the clear). Checked (``modes``):
    a key enrolled in nothing is a PropError, or with ``allow_unenrolled`` gives the base with a
    warning; a bundle changed since the key was enrolled is a PropError. ``method``: the method's
    response to any key, unchecked (an unsealed key always goes through the encoder): for audits and the
    paper's wrong-key measurements only."""
    base = bundle.loaded.module.eval()
    if key is None:
        return base
    bits = bundle.check_key(key)
    if method:
        return bundle.mode.respond(base, bits) or base
    unlocked = bundle.mode.unlock(base, bits)
    if unlocked is None:
        key_opens_nothing(bundle.mode.not_enrolled(str(bundle.path)), allow_unenrolled, stacklevel=4)
        return base
    return unlocked


class KeyedPolicy:
    """The bundle's module with one key's behaviour folded into a copy of its weights (in memory only):
    what that key's holder enrolled, checked (``module_for_key``: a key enrolled in nothing is a
    PropError unless ``allow_unenrolled``; ``method=True``: unchecked).

    A LeRobot policy acts through its processors and queues (``select_action``, ``reset``); keep one
    KeyedPolicy per control loop (without a key it drives the bundle's own base module, whose queues a
    second one would share). ``instruction``: a language-conditioned policy's task text (SmolVLA; an
    observation's ``task`` entry overrides it); ``noise_seed``: a sampling policy's noise (Diffusion,
    SmolVLA; default the bundle's, 0), as ``prop eval --instruction/--noise-seed``. Both are unused by
    the others."""

    def __init__(
        self, bundle: Bundle, key: np.ndarray | None = None, *, method: bool = False,
        allow_unenrolled: bool = False, instruction: str | None = None, noise_seed: int | None = None,
    ) -> None:  # fmt: skip
        self.module = module_for_key(bundle, key, method=method, allow_unenrolled=allow_unenrolled)
        self.path = str(bundle.path)
        self.input_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
        loaded = bundle.loaded
        self.discrete = loaded.continuous is False
        self.low = None if loaded.action_low is None else np.asarray(loaded.action_low, np.float32)
        self.high = None if loaded.action_high is None else np.asarray(loaded.action_high, np.float32)
        self.controller = None  # an array model: one array in, one out
        if loaded.policy is not None:  # named observation features (LeRobot): processors and queues
            policy = loaded.policy.on(self.module)  # a copy: the bundle's own settings stay as they are
            if instruction is not None:
                policy.instruction = instruction
            if noise_seed is not None:
                policy.noise_seed = int(noise_seed)
            self.controller = policy.controller(self.module)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Raw outputs for a batch (N, *input_shape): what ``prop run`` writes."""
        if self.controller is not None:
            raise PropError(
                f"{self.path} is a policy with named observation features: it has no array forward",
                "drive it with KeyedPolicy.select_action({feature: array}), or get action chunks for a "
                "dataset with prop run --input",
            )
        if isinstance(x, Mapping):
            raise PropError(
                f"{self.path} takes one array per observation, shape {self.input_shape}, not a dict "
                f"(keys {', '.join(map(str, x))})",
                "pass the array the model takes (an SB3 Dict observation: "
                "prop_adapters.sb3.observation_array(bundle.loaded.spec, obs))",
            )
        with torch.inference_mode():
            return self.module(torch.from_numpy(np.ascontiguousarray(x, np.float32))).numpy()

    def reset(self, seed: int | None = None) -> None:
        """Between episodes: a policy's action (and observation) queues emptied; ``seed``, the episode's,
        seeds a sampling policy's noise. An array model is feed-forward: nothing to reset."""
        if self.controller is not None:
            self.controller.reset(seed)

    def select_action(self, observation) -> np.ndarray:
        """The action for one observation (or a batch). A LeRobot policy: ``observation`` is its dict
        (feature name -> array or tensor, in the units its preprocessor takes), and the action is
        LeRobot's ``select_action`` between the bundle's processors, in the dataset's action units
        (Diffusion: its first is ``chunk[n_obs_steps - 1]``). An array model: ``predict``'s action."""
        if self.controller is None:
            return self.predict(observation)[0]
        return self.controller.select_action(observation)

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """SB3's ``predict``: ``(action, state)`` for one observation (``input_shape``) or a batch of them.
        The policies prop keys are feed-forward, so ``state`` comes back as given; the action is the
        deterministic one (the mean, or the argmax): the key changes the policy's output, not its noise.
        A LeRobot policy: ``(select_action(observation), state)``."""
        if not deterministic:
            raise PropError(
                "KeyedPolicy.predict(deterministic=False): prop runs the deterministic policy",
                "pass deterministic=True (the mean action, or the argmax)",
            )
        if self.controller is not None:
            return self.controller.select_action(observation), state
        if isinstance(observation, Mapping):
            return self(observation), state  # refused there, in one line
        obs = np.asarray(observation, np.float32)
        single = obs.shape == self.input_shape
        y = self(obs[None] if single else obs)
        if self.discrete:
            y = y.argmax(-1)
        elif self.low is not None and self.high is not None:
            y = np.clip(y, self.low, self.high)
        return (y[0] if single else y), state


def run_bundle(
    bundle: Bundle, x: np.ndarray, key: np.ndarray | None, *, allow_unenrolled: bool = False
) -> np.ndarray:
    """The bundle's raw outputs on ``x``: with a key, that key's behaviour; without, the base's. A key
    enrolled in nothing is a PropError (``allow_unenrolled``: the base's outputs, with a warning).

    One call folds the key once; in a control loop keep a ``KeyedPolicy(bundle, key)`` instead.
    """
    return KeyedPolicy(bundle, key, allow_unenrolled=allow_unenrolled)(x)


def run_array(
    bundle: Bundle, x: np.ndarray, key: np.ndarray | None, flag: str, allow_unenrolled: bool = False
) -> np.ndarray:
    """``run_bundle``, with inputs of another image size refused in one line where the model fixes it."""
    try:
        return run_bundle(bundle, x, key, allow_unenrolled=allow_unenrolled)
    except RuntimeError as e:
        want = tuple(bundle.manifest[C.M_IO]["input_shape"])
        if x.shape[1:] == want:
            raise
        raise PropError(
            f"{flag}: the model does not run on samples of shape {x.shape[1:]} (personalized on {want}: "
            f"{str(e).splitlines()[0][:120]})",
            "give samples of shape " + str(want),
        ) from None


def run_inputs(
    bundle: Bundle, input_path: Path, key: np.ndarray | None, *, allow_unenrolled: bool = False,
    onnx: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:  # fmt: skip
    """`prop run`'s outputs for the inputs in a file: a policy's action chunks for every frame of a
    dataset (``run_policy``), or an array model's outputs (``inputs.load_inputs``), in torch or through
    ``onnx(x)`` (an ONNX export's runner; a policy has none yet)."""
    if bundle.loaded.policy is not None:
        if onnx is not None:
            raise PropError(f"--onnx: {bundle.path} is a policy, which has no ONNX export yet", "drop --onnx")
        data = load_data(input_path, require_y=False, min_samples=1, flag="--input")
        return run_policy(bundle, data, key, allow_unenrolled=allow_unenrolled)
    x = load_inputs(input_path, bundle)
    return onnx(x) if onnx is not None else run_array(bundle, x, key, "--input", allow_unenrolled)


@torch.no_grad()
def run_policy(
    bundle: Bundle, data: Dataset, key: np.ndarray | None, flag: str = "--input", *,
    allow_unenrolled: bool = False,
) -> np.ndarray:  # fmt: skip
    """A policy bundle's action chunks (N, chunk, action_dim) for every frame of ``data``, in the dataset's
    action units (the policy's postprocessor applied); with a key, that key's behaviour (checked as
    ``run_bundle`` checks it)."""
    policy = bundle.loaded.policy
    module = module_for_key(bundle, key, allow_unenrolled=allow_unenrolled)
    if module is not bundle.loaded.module:
        policy = policy.on(module)
    batch = policy.batches(replace(data, y=None), flag)
    n = len(batch["episode_index"])
    feats = {k: batch[k] for k in policy.row_shapes}
    chunks = [policy.chunk({k: v[i : i + ROWS] for k, v in feats.items()}) for i in range(0, n, ROWS)]
    return policy.post(torch.cat(chunks)).float().numpy()


def require_array_model(bundle: Bundle, command: str) -> Bundle:
    """Refuse, in one line, policies with named observation features where a command has no policy
    path yet (ONNX)."""
    if bundle.loaded.policy is not None:
        raise PropError(
            f"{command} takes array models; {bundle.path} is a {bundle.loaded.spec['adapter']} policy "
            "with named observation features",
            "run it with prop run or prop eval (ONNX export of such policies is not there yet)",
        )
    return bundle


def input_features(loaded: LoadedModel) -> list[str] | None:
    """A policy's named observation features (what a closed loop maps the environment's observation to);
    None for an array model, which takes one array (``array_observation`` prepares it)."""
    return list(loaded.policy.input_features) if loaded.policy is not None else None


def array_observation(bundle: Bundle, normalizer: ObsNormalizer | None = None) -> Callable | None:
    """The environment's observation -> the one array a module without a policy protocol takes:
    VecNormalize's statistics first (SB3 normalises the raw dict or array), then the adapter's layout
    (SB3: Dict entries flattened in the policy's key order, images HWC -> CHW). None for a LeRobot
    policy, whose own preprocessor does this (and which takes no ``normalizer``)."""
    if bundle.loaded.policy is not None:
        if normalizer is not None:
            raise PropError(
                "--vecnormalize is for Stable-Baselines3 policies; this bundle's policy normalises its "
                "inputs",
                "drop --vecnormalize",
            )
        return None
    spec = bundle.loaded.spec

    def prepare(obs):
        if normalizer is not None:
            obs = normalizer(obs)
        if spec.get("adapter") == "sb3":
            return observation_array(spec, obs)
        if isinstance(obs, dict):
            raise PropError(
                f"the environment's observations are dicts (keys {sorted(obs)})",
                "this bundle takes one array",
            )
        return obs

    return prepare


class _ArrayController:
    """A bundle without a policy protocol (MLP, SB3): ``KeyedPolicy`` after the environment's
    observation is prepared. ``module``: act with this module instead (``--original``), through the
    same observation preparation, clipping and argmax as the bundle."""

    def __init__(
        self, bundle: Bundle, key: np.ndarray | None, prepare: Callable, method: bool,
        allow_unenrolled: bool = False, module: nn.Module | None = None,
    ) -> None:  # fmt: skip
        self.policy = KeyedPolicy(bundle, key, method=method, allow_unenrolled=allow_unenrolled)
        if module is not None:
            self.policy.module = module.eval()
        self.prepare = prepare

    def reset(self, seed: int | None = None) -> None:
        pass

    def select_action(self, obs) -> np.ndarray:
        return self.policy.select_action(self.prepare(obs))


def controller(
    bundle: Bundle, key: np.ndarray | None, prepare: Callable | None, *, method: bool = False,
    allow_unenrolled: bool = False,
):  # fmt: skip
    """What a closed loop drives (``reset``, ``select_action``) for the bundle under one key: a LeRobot
    policy's ``KeyedPolicy`` as a user's own loop drives it, or an array model's after ``prepare``
    (``array_observation``)."""
    if bundle.loaded.policy is None:
        return _ArrayController(bundle, key, prepare, method, allow_unenrolled)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a sealed bundle's wrong keys open nothing, by design
        return KeyedPolicy(bundle, key, method=method, allow_unenrolled=allow_unenrolled)


def original_controller(bundle: Bundle, original: LoadedModel, prepare: Callable | None):
    """The original checkpoint (``--original``, rebuilt as the bundle's base is) driven as ``controller``
    drives the bundle; refused in one line if it is not the bundle's kind of model or shapes."""
    policy = bundle.loaded.policy
    if (original.policy is None) != (policy is None):
        raise PropError(
            "--original is not the kind of model the bundle holds (a LeRobot policy and an array model)",
            "pass the checkpoint the bundle was personalized from",
        )
    if policy is not None:
        return original.policy.controller(original.module.eval())
    shapes = [{k: tuple(v.shape) for k, v in m.state_dict().items()} for m in (bundle.loaded.module,
              original.module)]  # fmt: skip
    if shapes[0] != shapes[1]:
        raise PropError(
            "--original does not fit the bundle's model (other layers or shapes)",
            "pass the checkpoint the bundle was personalized from",
        )
    return _ArrayController(bundle, None, prepare, False, module=original.module)


def seed_noise(loaded: LoadedModel, seed: int) -> None:
    """A sampling policy draws its chunks' noise from ``seed`` (others have no noise)."""
    if loaded.policy is not None:
        loaded.policy.noise_seed = int(seed)
