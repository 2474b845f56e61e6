"""A reach task as a LeRobot task: scripted-expert recording, a small ACT or Diffusion Policy, their
training loop.

Nobody labels anything: the general behaviour is a scripted expert reaching the goal; the user's
preference is the same expert holding the end effector 10 cm above it. Both are recorded into local
LeRobotDatasets (state-only unless asked, no downloads). Needs the LeRobot environment
(scripts/setup-lerobot.sh).

Two simulators, the same observations, actions and expert (``sim``): ``mujoco`` (the default, what the
tests run) is examples/mujoco_reach.py, a 3-D reach on MuJoCo, wheels only; ``panda`` is panda-gym's
PandaReach-v3 (pybullet, compiled on Python 3.12: the `rl` extra), on which the paper's LeRobot figures
in examples/RESULTS.md were measured. A dataset names its simulator in its ``robot_type`` (``sim_of``).

Observation features: ``observation.state`` (6: end-effector position and velocity) and
``observation.environment_state`` (3: the goal); ``action`` (3) in [-1, 1]. With ``camera=True`` also
``observation.images.front``: the simulator's rendered camera (MuJoCo's off-screen renderer; panda-gym's
CPU renderer), 32 x 32 RGB, recorded as dtype image; ``CAMERA_ENV_ID`` (``PANDA_CAMERA_ENV_ID``) is the
same task whose observations carry that frame (``pixels``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")

ENV_ID = "examples.mujoco_reach:MujocoReach-v0"
PANDA_ENV_ID = "panda_gym:PandaReach-v3"
OBS_MAP = "observation.state=observation,observation.environment_state=desired_goal"
METRIC = "examples.lerobot_reach_task:user_preference"
FPS = 25  # both simulators step 0.04 s
HORIZON = 30  # recorded steps per episode; the expert needs ~3 (MuJoCo) or ~10 (PandaReach)
USER_OFFSET = np.array([0.0, 0.0, 0.10], np.float32)
SUCCESS = 0.05  # both tasks' distance threshold (PandaReach's)
STATE, ENV_STATE, ACTION = "observation.state", "observation.environment_state", "action"
CAMERA = "observation.images.front"
IMAGE = 32  # camera frames are IMAGE x IMAGE RGB
FEATURES = {
    STATE: {"dtype": "float32", "shape": (6,), "names": ["x", "y", "z", "vx", "vy", "vz"]},
    ENV_STATE: {"dtype": "float32", "shape": (3,), "names": ["gx", "gy", "gz"]},
    ACTION: {"dtype": "float32", "shape": (3,), "names": ["dx", "dy", "dz"]},
}
STATE_GOAL_FEATURE = {"dtype": "float32", "shape": (9,),
                      "names": [*FEATURES[STATE]["names"], "gx", "gy", "gz"]}  # fmt: skip
CAMERA_FEATURE = {"dtype": "image", "shape": (IMAGE, IMAGE, 3), "names": ["height", "width", "channels"]}
# The camera tasks for `prop eval --env`: importing this module registers them.
CAMERA_ENV_ID = "examples.lerobot_reach_task:MujocoReachCamera-v0"
PANDA_CAMERA_ENV_ID = "examples.lerobot_reach_task:PandaReachCamera-v0"
CAMERA_OBS_MAP = OBS_MAP + f",{CAMERA}=pixels"
# SmolVLA reads one state vector (observation.state): its camera task's state holds the goal too.
STATE_GOAL = "state_goal"  # the camera task's observation key: observation + desired_goal
SMOLVLA_OBS_MAP = f"{STATE}={STATE_GOAL},{CAMERA}=pixels"
INSTRUCTION = "reach the target"  # every frame's task text
# PandaReach: looking at the table from the front and above, so the goal sphere is in view wherever it
# is drawn. (MuJoCo's reach has its own `front` camera.)
CAMERA_VIEW = dict(renderer="Tiny", render_width=IMAGE, render_height=IMAGE, render_distance=0.9,
                   render_target_position=[0.0, 0.0, 0.1], render_yaw=60, render_pitch=-30)  # fmt: skip
# Per simulator: the state task, the camera task, the dataset's robot_type.
SIMS = {
    "mujoco": {"env": ENV_ID, "camera_env": CAMERA_ENV_ID, "robot_type": "mujoco_reach"},
    "panda": {"env": PANDA_ENV_ID, "camera_env": PANDA_CAMERA_ENV_ID, "robot_type": "panda"},
}
PANDA_MISSING = ("PandaReach needs panda-gym, which is not installed: .venv-lerobot/bin/pip install -e "
                 "'.[rl]' (pybullet compiles, ~14 min once), or use the MuJoCo reach: --sim mujoco")


def require_sim(sim: str) -> None:
    """Exit in one line if ``sim`` is not one of SIMS or its simulator is not installed."""
    if sim not in SIMS:
        raise SystemExit(f"error: unknown simulator {sim!r}: give one of {', '.join(SIMS)}")
    if sim == "panda":
        try:
            import panda_gym  # noqa: F401
        except ImportError:
            raise SystemExit(f"error: {PANDA_MISSING}") from None


def sim_of(root: Path) -> str:
    """The simulator a dataset recorded by ``record`` was recorded on (its robot_type)."""
    import json

    robot = json.loads((Path(root) / "meta" / "info.json").read_text()).get("robot_type")
    return next((k for k, v in SIMS.items() if v["robot_type"] == robot), "panda")


def env_id(sim: str, camera: bool) -> str:
    return SIMS[sim]["camera_env" if camera else "env"]


def _base_env(sim: str, camera: bool, **kwargs):
    import gymnasium as gym

    if sim == "panda":
        import panda_gym  # noqa: F401 - registers the environments

        view = dict(render_mode="rgb_array", **CAMERA_VIEW) if camera else {}
        return gym.make("PandaReach-v3", **view, **kwargs)
    from examples import mujoco_reach  # noqa: F401 - registers MujocoReach-v0

    view = dict(render_mode="rgb_array", width=IMAGE, height=IMAGE) if camera else {}
    return gym.make("MujocoReach-v0", **view, **kwargs)


def make_camera_env(sim: str = "mujoco", **kwargs):
    """The reach task whose observations also hold the rendered camera frame (``pixels``, HWC uint8)
    and the state with the goal (``state_goal``)."""
    import gymnasium as gym

    class WithPixels(gym.ObservationWrapper):
        def __init__(self, env):
            super().__init__(env)
            space = gym.spaces.Box(0, 255, (IMAGE, IMAGE, 3), np.uint8)
            both = gym.spaces.Box(-np.inf, np.inf, (9,), np.float32)
            self.observation_space = gym.spaces.Dict(
                {**env.observation_space.spaces, "pixels": space, STATE_GOAL: both}
            )

        def observation(self, obs):
            pixels = np.ascontiguousarray(self.env.render()[..., :3])
            return {**obs, "pixels": pixels, STATE_GOAL: state_goal(obs)}

    return WithPixels(_base_env(sim, True, **kwargs))


def make_panda_camera_env(**kwargs):
    return make_camera_env("panda", **kwargs)


def _register() -> None:
    import gymnasium as gym

    if "MujocoReachCamera-v0" not in gym.registry:
        gym.register("MujocoReachCamera-v0", entry_point=make_camera_env, max_episode_steps=50)
    if "PandaReachCamera-v0" not in gym.registry:
        gym.register("PandaReachCamera-v0", entry_point=make_panda_camera_env, max_episode_steps=50)


_register()


def user_preference(trajectory: dict) -> float:
    """`prop eval --metric`: 1 if the episode ends within 5 cm of the point 10 cm above the goal."""
    last = trajectory["observations"][-1]
    target = np.asarray(last["desired_goal"]) + USER_OFFSET
    return float(np.linalg.norm(np.asarray(last["achieved_goal"]) - target) < SUCCESS)


def state_goal(obs: dict) -> np.ndarray:
    return np.concatenate([obs["observation"], obs["desired_goal"]]).astype(np.float32)


def expert(obs: dict, offset: np.ndarray) -> np.ndarray:
    return np.clip(10.0 * (obs["desired_goal"] + offset - obs["observation"][:3]), -1, 1).astype(np.float32)


def record(
    root: Path, episodes: int, seed0: int, offset: np.ndarray, noise: float = 0.3, camera: bool = False,
    goal_in_state: bool = False, sim: str = "mujoco",
) -> None:  # fmt: skip
    """Expert episodes into a new LeRobotDataset at ``root``. The executed action carries Gaussian noise
    (states off the expert's path get recorded too); the recorded action is the clean one (DART).
    ``camera``: each frame's rendered camera image too (``CAMERA``). ``goal_in_state``: the state is
    observation + goal (9 values; SmolVLA reads one state vector). ``sim``: mujoco or panda (SIMS)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    require_sim(sim)
    ds = LeRobotDataset.create(
        repo_id=f"local/{root.name}",
        fps=FPS,
        features=FEATURES | ({CAMERA: CAMERA_FEATURE} if camera else {})
        | ({STATE: STATE_GOAL_FEATURE} if goal_in_state else {}),
        root=root,
        robot_type=SIMS[sim]["robot_type"],
        use_videos=False,
        video_backend="pyav",  # no video recorded; LeRobot 0.6 otherwise probes torchcodec
    )
    # A fixed horizon: no time limit, no stop on success.
    env = (make_camera_env(sim) if camera else _base_env(sim, False)).unwrapped
    rng = np.random.default_rng(seed0)
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed0 + ep)
        for _ in range(HORIZON):
            a = expert(obs, offset)
            frame = {
                STATE: state_goal(obs) if goal_in_state else obs["observation"].astype(np.float32),
                ENV_STATE: obs["desired_goal"].astype(np.float32),
            }
            if camera:
                frame[CAMERA] = np.ascontiguousarray(env.render()[..., :3])
            ds.add_frame({**frame, ACTION: a, "task": INSTRUCTION})
            obs, *_ = env.step(np.clip(a + noise * rng.standard_normal(3).astype(np.float32), -1, 1))
        ds.save_episode()
    ds.finalize()  # writes the parquet footers; without it the root does not load
    env.close()


def vla_features(features: dict | None = None) -> dict:
    """A tiny VLA's features (``features``, else the arm's state and the camera; the 3-d action) on the
    CPU, as its config takes them (examples/smolvla_tiny.py, examples/pi_tiny.py)."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    inputs = features or {
        STATE: PolicyFeature(FeatureType.STATE, (6,)),
        CAMERA: PolicyFeature(FeatureType.VISUAL, (3, IMAGE, IMAGE)),
    }  # fmt: skip
    outputs = {ACTION: PolicyFeature(FeatureType.ACTION, (3,))}
    return dict(input_features=inputs, output_features=outputs, device="cpu")


def build_act(stats: dict | None = None, **overrides):
    """A small ACT (dim 64; 2 encoder, 1 decoder, 2 VAE layers; chunk 10) with its processors."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    settings = dict(
        input_features={
            STATE: PolicyFeature(FeatureType.STATE, (6,)), ENV_STATE: PolicyFeature(FeatureType.ENV, (3,))
        },
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (3,))},
        device="cpu", pretrained_backbone_weights=None, dim_model=64, n_heads=4, dim_feedforward=256,
        n_encoder_layers=2, n_decoder_layers=1, n_vae_encoder_layers=2, latent_dim=16, chunk_size=10,
        n_action_steps=5, dropout=0.1,
    )  # fmt: skip
    cfg = ACTConfig(**(settings | overrides))
    policy = ACTPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    return policy, pre, post


def build_diffusion(
    stats: dict | None = None, features: dict | None = None, camera: bool = False, **overrides
):
    """A small Diffusion Policy: U-Net down_dims 32/64/128 (1.1 M parameters with state inputs), horizon
    16, 8 actions per query, 2 observation frames, DDPM with 100 training and 10 inference steps.
    ``camera``: the camera frame is an input too (LeRobot's ResNet-18 encoder with group norm, random
    init, no crop)."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    inputs = features or {
        STATE: PolicyFeature(FeatureType.STATE, (6,)), ENV_STATE: PolicyFeature(FeatureType.ENV, (3,))
    }  # fmt: skip
    if camera:
        inputs = inputs | {CAMERA: PolicyFeature(FeatureType.VISUAL, (3, IMAGE, IMAGE))}
    settings = dict(
        input_features=inputs, output_features={ACTION: PolicyFeature(FeatureType.ACTION, (3,))},
        device="cpu", n_obs_steps=2, horizon=16, n_action_steps=8, down_dims=(32, 64, 128), kernel_size=5,
        n_groups=8, diffusion_step_embed_dim=64, num_train_timesteps=100, num_inference_steps=10,
        crop_shape=None, pretrained_backbone_weights=None, use_group_norm=True,
    )  # fmt: skip
    cfg = DiffusionConfig(**(settings | overrides))
    policy = DiffusionPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    return policy, pre, post


BUILDERS = {"act": build_act, "diffusion": build_diffusion}


def dataset_stats(root: Path, keys: tuple[str, ...] = (STATE, ENV_STATE, ACTION)) -> dict:
    """The root's meta/stats.json as the normaliser takes it (mean/std/min/max tensors per feature);
    the camera's too where the root has one."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    meta = LeRobotDatasetMetadata(f"local/{root.name}", root=root)
    keys = (*keys, CAMERA) if CAMERA in meta.stats and CAMERA not in keys else keys
    return {
        k: {s: torch.as_tensor(np.asarray(v), dtype=torch.float32) for s, v in meta.stats[k].items()
            if s in ("mean", "std", "min", "max")}
        for k in keys
    }  # fmt: skip


def train_base(
    root: Path, out: Path, steps: int, batch: int = 32, lr: float = 3e-4, seed: int = 0, kind: str = "act",
    built: tuple | None = None, camera: bool = False,
) -> float:  # fmt: skip
    """LeRobot's training step (lerobot_train.update_policy: forward -> backward -> clip 10 -> AdamW) on
    the dataset held in memory; writes the policy folder with save_pretrained. Returns ms per step.
    ``kind``: act or diffusion (the small builds above); ``built``: (policy, pre, post) built already;
    ``camera``: the camera frame is an input too (Diffusion)."""
    import time

    from prop_adapters.lerobot import POLICIES
    from prop_cli.datasources import load_data

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    policy, pre, post = built or BUILDERS[kind](dataset_stats(root), **({"camera": True} if camera else {}))
    data = POLICIES[policy.config.type](policy, pre, post).batches(load_data(root), "--data")
    data.pop("episode_index")
    opt = torch.optim.AdamW(policy.parameters(), lr=lr, weight_decay=1e-4)
    policy.train()
    t0 = time.perf_counter()
    for _ in range(steps):
        idx = torch.from_numpy(rng.integers(0, len(data[ACTION]), batch))
        loss, _ = policy.forward({k: v[idx] for k, v in data.items()})
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        opt.step()
    ms = 1000 * (time.perf_counter() - t0) / steps
    policy.eval()
    for part in (policy, pre, post):
        part.save_pretrained(out)
    return ms
