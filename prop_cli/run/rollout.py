"""Closed-loop evaluation of a bundle in a gymnasium environment, per key condition (`prop eval`).

Conditions: the user's key, no key, random keys and one-bit neighbours of the user's key (one fixed
key per episode, folded into a copy of the weights, so a keyed step costs a base step), and optionally
the original checkpoint. Per condition: mean return, success (``info["is_success"]`` at the episode's
end, where the environment reports it) and the user's preference metric, each with its standard error.
Every condition runs the same evaluation seeds: random keys and neighbours take them in turn,
``episodes_per_key`` each (6 keys x 5 episodes = the 30 seeds of the other conditions), so the
conditions differ only in the key, not in the starting states. A key enrolled in nothing of the bundle
is refused; allowed (``--allow-unenrolled-key``), it runs the bundle's base and its row is
``key_not_enrolled``, not ``user_key``. Random keys and neighbours measure the method itself, unchecked.
The environment: ``envs``.
"""

from __future__ import annotations

import importlib
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from prop_adapters.sb3.vecnormalize import ObsNormalizer
from prop_cli.bundle import Bundle
from prop_cli.config import EvalSettings
from prop_cli.core import metrics
from prop_cli.core.key_sampling import one_bit_neighbours, random_keys
from prop_cli.errors import PropError
from prop_cli.files import check_writable, staged_dir

from .envs import frame, make_env
from .policy import array_observation, controller, input_features, original_controller, require_enrolled

# A trajectory as the preference metric receives it.
Trajectory = dict  # {"observations": [...], "actions": [...], "rewards": [...], "infos": [...]}
Metric = Callable[[Trajectory], float]


def parse_obs_map(spec: str | None) -> dict[str, str]:
    """``feature=env_key,...`` -> {policy feature: key of the environment's dict observation}."""
    if not spec:
        return {}
    out = {}
    for part in spec.split(","):
        feature, sep, key = part.strip().partition("=")
        if not sep or not feature or not key:
            raise PropError(
                f"--obs-map {spec!r}: {part!r} is not feature=key",
                "write it like observation.state=observation,observation.environment_state=desired_goal",
            )
        out[feature] = key
    return out


def load_metric(spec: str | None) -> Metric | None:
    """``package.module:function`` -> the function (called with each episode's trajectory)."""
    if not spec:
        return None
    mod_name, sep, attr = spec.partition(":")
    if not sep or not mod_name or not attr:
        raise PropError(f"--metric {spec!r} is not package.module:function", "name a function f(trajectory)")
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # a metric file next to where prop runs, as with `python -m`
    try:
        fn = getattr(importlib.import_module(mod_name), attr)
    except Exception as e:  # noqa: BLE001 - ImportError, AttributeError or the module's own errors
        raise PropError(
            f"--metric {spec!r}: cannot load it ({type(e).__name__}: {e})", "check the name"
        ) from None
    if not callable(fn):
        raise PropError(f"--metric {spec!r} is not callable", "name a function f(trajectory) -> float")
    return fn


def _observation(obs, features: list[str] | None, obs_map: dict[str, str]):
    """The environment's observation as the policy takes it (a dict of arrays by feature name)."""
    if features is None:
        return obs  # one array in: the controller prepares it (policy.array_observation)
    if not isinstance(obs, dict):
        if len(features) != 1:
            raise PropError(f"the environment gives one array; the policy takes {features}", "use --obs-map")
        return {features[0]: obs}
    out = {}
    for f in features:
        key = obs_map.get(f, f)
        if key not in obs:
            raise PropError(
                f"the environment's observation has no {key!r} for the policy's {f!r} (it has {sorted(obs)})",
                "map it with --obs-map feature=key",
            )
        out[f] = np.asarray(obs[key], np.float32) if np.asarray(obs[key]).dtype != np.uint8 else obs[key]
    return out


def check_observation(env, seed: int, features: list[str] | None, obs_map: dict[str, str], prepare) -> None:
    """The first observation taken as the policy takes it, before any rollout: a missing --obs-map is
    reported before the first episode starts (with the names it gives that the policy does not take:
    a mistyped feature; others are fine, one map may serve several policies)."""
    obs, _ = env.reset(seed=int(seed))
    if features is None:
        prepare(obs)
        return
    try:
        _observation(obs, features, obs_map)
    except PropError as e:
        unknown = sorted(set(obs_map) - set(features))
        if not unknown:
            raise
        names = ", ".join(map(repr, unknown))
        raise PropError(f"{e.what} (--obs-map's {names}: not a feature the policy takes)", e.fix) from None


def _episodes(
    env, controller, seeds: list[int], features, obs_map, settings: EvalSettings, metric, frames=None
) -> list:
    """Roll out one episode per seed; ``frames`` (a list): the first episode's rendered frames go in it."""
    results = []
    for n, seed in enumerate(seeds):
        obs, _ = env.reset(seed=int(seed))
        controller.reset(int(seed))  # a sampling policy's noise follows the episode's seed (paired)
        film = frames is not None and n == 0
        if film:
            frames.append(frame(env))
        traj: Trajectory = {"observations": [obs], "actions": [], "rewards": [], "infos": []}
        total, steps, info = 0.0, 0, {}
        while True:
            action = controller.select_action(_observation(obs, features, obs_map))
            obs, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            steps += 1
            if film:
                frames.append(frame(env))
            for k, v in (("observations", obs), ("actions", action), ("rewards", reward), ("infos", info)):
                traj[k].append(v)
            if truncated or (terminated and not settings.ignore_terminated):
                break
            if settings.max_steps and steps >= settings.max_steps:
                break
        r = {"return": total, "steps": steps}
        if "is_success" in info:
            r["success"] = float(info["is_success"])
        if metric is not None:
            r["metric"] = float(metric(traj))
        results.append(r)
    return results


def check_video(video: Path | None) -> None:
    """Before any rollout: the writer is installed and the folder is new (nothing is overwritten)."""
    if video is None:
        return
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise PropError(
            "--video needs imageio and imageio-ffmpeg", "pip install 'prop-keys[video]'"
        ) from None
    if Path(video).exists() or Path(video).is_symlink():
        raise PropError(f"--video {video} exists", "give a new folder (videos are never overwritten)")
    parent = Path(video).resolve().parent
    if not parent.is_dir():
        raise PropError(f"--video {video}: folder {parent} does not exist", "create it first")
    check_writable(parent, "video folder", "--video", Path(video))  # before the rollouts, not after


def write_videos(video: Path, films: dict[str, list[np.ndarray]], fps: float) -> None:
    """One mp4 per condition (its first episode), written together at the end: all or nothing."""
    import imageio.v2 as imageio

    with staged_dir(Path(video), what="video folder", flag="--video") as tmp:
        for label, frames in films.items():
            imageio.mimsave(tmp / f"{label}.mp4", frames, fps=fps, macro_block_size=1)


def _summary(results: list[dict]) -> dict:
    out: dict = {"episodes": len(results)}
    for field in ("return", "success", "metric", "steps"):
        vals = [r[field] for r in results if field in r]
        if vals:
            mean = float(np.mean(vals))
            se = float(np.std(vals, ddof=1) / math.sqrt(len(vals))) if len(vals) > 1 else 0.0
            out[field] = {"mean": mean, "se": se}
    return out


def bits_string(bits: np.ndarray) -> str:
    """A key as a 0/1 string, as ``--key-bits`` takes it."""
    return "".join(str(int(b)) for b in bits)


def parse_key_bits(spec: str, n_bits: int) -> np.ndarray:
    """``--key-bits``: a 0/1 string of the bundle's key length -> the key's bits."""
    if len(spec) != n_bits or set(spec) - {"0", "1"}:
        raise PropError(
            f"--key-bits is not {n_bits} characters of 0 and 1 (got {len(spec)})",
            "copy a key's bits from `prop eval --json` (conditions.random_keys.per_key[].key.bits)",
        )
    return np.frombuffer(spec.encode(), np.uint8) - ord("0")


def probe_key(key: np.ndarray | None, n_bits: int, key_bits: str | None, flip_bit: int | None):
    """``--key-bits`` / ``--flip-bit``: one wrong key to roll out again -> (row name, bits, identity)
    or None. A neighbour is named by its flipped bit only, never by its bits."""
    if key_bits is not None and flip_bit is not None:
        raise PropError("--key-bits and --flip-bit together", "re-run one key at a time")
    if key_bits is not None:
        return "key_bits", parse_key_bits(key_bits, n_bits), {"bits": key_bits}
    if flip_bit is None:
        return None
    if key is None:
        raise PropError("--flip-bit needs your key", "pass --key-file or --passphrase")
    if not 0 <= flip_bit < len(key):
        raise PropError(f"--flip-bit {flip_bit} is outside 0..{len(key) - 1}", "give a bit of your key")
    return "flipped_bit", one_bit_neighbours(key)[flip_bit], {"flipped_bit": flip_bit}


def worst_key(per_key: list[dict]) -> dict:
    """The key of a group that keeps least of the original: lowest success where the environment
    reports it, else lowest return (the figure ``prop eval`` shows next to the group's mean); ``index``:
    its place in ``per_key``."""
    field = "success" if all("success" in r for r in per_key) else "return"
    i = min(range(len(per_key)), key=lambda j: per_key[j][field]["mean"])
    return per_key[i] | {"by": field, "index": i}


def drift(
    per_key: list[list[dict]], seeds: list[list[int]], against: str, reference: dict[int, dict]
) -> dict:
    """Whether a key group's closed-loop drift is systematic: per key, its mean (success where every
    episode reports it, else return) on its seeds minus the reference's (the original, else no key) on
    the same seeds; keys worse / better / tied, with a two-sided sign test over the untied keys
    (``systematic``: p < metrics.SYSTEMATIC_P) and ``warn``: systematic with most keys worse. With
    success, also the paired episodes: lost (the reference's success, the key's failure) and gained."""
    rows = [r for rs in per_key for r in rs] + list(reference.values())
    field = "success" if all("success" in r for r in rows) else "return"
    diffs = [
        float(np.mean([r[field] for r in rs]) - np.mean([reference[s][field] for s in ss]))
        for rs, ss in zip(per_key, seeds)
    ]
    side = metrics.sides(diffs)
    out = {"against": against, "by": field, "keys": side["keys"], "worse": side["below"],
           "better": side["above"], "ties": side["ties"], "p": side["p"], "systematic": side["systematic"],
           "warn": side["systematic"] and side["below"] > side["above"]}  # fmt: skip
    if field == "success":
        pairs = [
            (reference[s]["success"], r["success"]) for rs, ss in zip(per_key, seeds) for r, s in zip(rs, ss)
        ]
        lost = sum(ref > mine for ref, mine in pairs)
        gained = sum(mine > ref for ref, mine in pairs)
        out["episodes"] = {"lost": lost, "gained": gained, "p": metrics.sign_test(lost, gained)}
    return out


def evaluate_bundle(
    bundle: Bundle,
    env_id: str,
    key: np.ndarray | None,
    settings: EvalSettings,
    *,
    obs_map: dict[str, str] | None = None,
    metric: Metric | None = None,
    original=None,
    progress: Callable[[str], None] | None = None,
    normalizer: ObsNormalizer | None = None,
    video: Path | None = None,
    allow_unenrolled: bool = False,
    probe: tuple[str, np.ndarray, dict] | None = None,
) -> dict:
    """Roll the bundle out under each key condition; ``original`` (a LoadedModel) adds its condition;
    ``normalizer`` (SB3 VecNormalize statistics) normalises observations before the policy; ``video``:
    a new folder that gets one mp4 per condition (its first episode; for key groups, the first key's).
    ``key`` must be enrolled in the bundle (``allow_unenrolled``: its row, ``key_not_enrolled``, runs
    the base). ``probe`` (``probe_key``): one more wrong key, on the ``--episodes`` seeds; each random
    key and neighbour also gets its own row in ``per_key``, and the group its ``worst_key`` and
    ``drift`` (``drift``: against the original on the same seeds, else no key)."""
    settings.validate(has_key=key is not None)
    check_video(video)
    # A key enrolled in nothing is refused, and a changed bundle, here, before any rollout; allowed, its
    # row is named for what runs (the base), not "user_key".
    enrolled = require_enrolled(bundle, key, allow_unenrolled)
    user_row = "user_key" if enrolled else "key_not_enrolled"
    films: dict[str, list[np.ndarray]] = {}

    def film(label: str) -> list | None:
        return None if video is None or label in films else films.setdefault(label, [])

    prepare = array_observation(bundle, normalizer)  # refuses --vecnormalize for a LeRobot policy
    env = make_env(env_id, render=video is not None, seed=settings.seed)
    features = input_features(bundle.loaded)
    obs_map = obs_map or {}
    check_observation(env, settings.seed, features, obs_map, prepare)
    first = [settings.seed + i for i in range(settings.episodes)]
    rng = np.random.default_rng((settings.seed, 0x5EED))

    def run(label: str, codes_or_bits, seeds: list[int], name: str, method: bool = False) -> list[dict]:
        # The user's key runs what it enrolled (checked; allowed or refused above); random keys and
        # neighbours measure the method itself, the encoder's response to any key (as an attacker
        # holding the files runs them).
        if progress is not None:
            progress(label)
        ctl = controller(bundle, codes_or_bits, prepare, method=method, allow_unenrolled=allow_unenrolled)
        return _episodes(env, ctl, seeds, features, obs_map, settings, metric, film(name))

    # Checked before any rollout.
    original_ctl = original_controller(bundle, original, prepare) if original is not None else None
    report: dict = {"env": env_id, "seeds": [first[0], first[-1]], "conditions": {}}
    cond = report["conditions"]
    if original_ctl is not None:
        if progress is not None:
            progress("original")
        ctl = original_ctl
        ref = _episodes(env, ctl, first, features, obs_map, settings, metric, film("original"))
        cond["original"] = _summary(ref)
        reference = ("original", dict(zip(first, ref)))
    no_key = run("no key", None, first, "no_key")
    cond["no_key"] = _summary(no_key)
    if original_ctl is None:
        reference = ("no_key", dict(zip(first, no_key)))
    if key is not None:
        label = "user key" if user_row == "user_key" else "key not enrolled (the bundle's base)"
        cond[user_row] = _summary(run(label, key, first, user_row))
    if probe is not None:  # one wrong key again (--key-bits, --flip-bit), through the encoder
        name, bits, ident = probe
        cond[name] = _summary(run(name.replace("_", " "), bits, first, name, method=True)) | {"key": ident}
    rand = random_keys(settings.random_keys, bundle.key_bits, rng, exclude=key)
    # Each key's identity, to re-run it: a random key's bits (a public wrong key); a neighbour's flipped
    # bit only (its bits with the index would give the user's key away).
    groups = [("random_keys", rand, [{"bits": bits_string(b)} for b in rand])]
    if key is not None and settings.neighbours:
        flips = rng.choice(len(key), settings.neighbours, replace=False)
        groups.append(("neighbour1_keys", one_bit_neighbours(key)[flips],
                       [{"flipped_bit": int(i)} for i in flips]))  # fmt: skip
    for label, keys, idents in groups:
        results, per_key, key_runs, key_seeds = [], [], [], []
        for j, (bits, ident) in enumerate(zip(keys, idents)):
            # The conditions' seeds, in turn: R keys x m episodes cover the same starting states as
            # the user key, no key and the original (paired, not merely as many).
            m = settings.episodes_per_key
            seeds = [first[(j * m + i) % len(first)] for i in range(m)]
            r = run(f"{label} {j + 1}/{len(keys)}", bits, seeds, label, method=True)
            results += r
            key_runs.append(r)
            key_seeds.append(seeds)
            per_key.append({"key": ident, "seeds": seeds} | _summary(r))
        if len(keys):
            cond[label] = _summary(results) | {"keys": len(keys), "per_key": per_key,
                                               "worst_key": worst_key(per_key),
                                               "drift": drift(key_runs, key_seeds, *reference)}  # fmt: skip
    fps = float(env.metadata.get("render_fps") or 25)
    env.close()
    if video is not None:
        write_videos(video, films, fps)
        report["video"] = {"folder": str(video), "files": sorted(f"{k}.mp4" for k in films), "fps": fps}
    return report
