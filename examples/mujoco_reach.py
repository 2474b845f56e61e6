"""A 3-D reach task on MuJoCo, shaped like panda-gym's PandaReach-v3 (end-effector control): the closed
loop of the LeRobot tests and examples, with wheels only (MuJoCo), nothing compiled (issue 38).

An end effector (a 1 kg sphere on three slide joints, no gravity: what PandaReach's inverse kinematics
makes of its arm) is moved by position-delta actions: ``action`` (3) in [-1, 1] asks for ``action x 5
cm`` from where it is, which position actuators (critically damped, ~40 ms to settle) follow over one
control step of 0.04 s (20 physics steps of 2 ms, as panda-gym). The goal is drawn uniformly in a 30 x
30 x 30 cm box above the table at each reset; the end effector starts at the same point each episode.
Observations as PandaReach's: ``observation`` (6: end-effector position and velocity), ``achieved_goal``
(3), ``desired_goal`` (3); success (and `terminated`) within 5 cm of the goal, sparse reward -1 until
then, ``info["is_success"]``. The model is an MJCF string built here; ``render_mode="rgb_array"``
renders the ``front`` camera with ``mujoco.Renderer`` (no shadows: 32 x 32 frames take ~1 ms on a CPU).

Rendering off-screen on a Linux machine without a display needs EGL or OSMesa: importing this module
sets ``MUJOCO_GL=egl`` unless it is set already (Mesa's EGL renders on the CPU through llvmpipe).
``python -m examples.mujoco_reach --check-rendering`` renders one frame (scripts/setup-lerobot.sh's last
step) and otherwise fails in one line naming the packages to install.

Registered ids (importing the module registers them): ``examples.mujoco_reach:MujocoReach-v0``.
"""

from __future__ import annotations

import os
import sys

import numpy as np

# mujoco reads MUJOCO_GL when first imported: if it was imported before this module, without it, it
# renders through GLFW, which needs a display (said in the error, rendering_error).
_LATE = "mujoco" in sys.modules and "MUJOCO_GL" not in os.environ
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402

DT = 0.04  # one control step: 20 physics steps of 2 ms (panda-gym's)
STEP = 0.05  # metres per unit of action
SUCCESS = 0.05  # distance to the goal that counts as reached (PandaReach's)
START = np.array([0.0, 0.0, 0.2])  # the end effector at reset
GOAL_LOW, GOAL_HIGH = np.array([-0.15, -0.15, 0.0]), np.array([0.15, 0.15, 0.3])  # PandaReach's goal box
LOW, HIGH = np.array([-0.3, -0.3, 0.0]), np.array([0.3, 0.3, 0.5])  # where the end effector may go
RENDER = 480  # default frame side (width and height)
FIX = "Debian/Ubuntu: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri (EGL, llvmpipe on the CPU), or " \
      "apt-get install libosmesa6 and set MUJOCO_GL=osmesa"  # fmt: skip

MJCF = f"""
<mujoco model="reach">
  <option timestep="0.002" gravity="0 0 0" integrator="implicitfast"/>
  <visual><quality shadowsize="0"/><global offwidth="{RENDER}" offheight="{RENDER}"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".55 .55 .5" rgb2=".45 .45 .4"
             width="64" height="64"/>
    <material name="table" texture="grid" texrepeat="6 6"/>
  </asset>
  <worldbody>
    <light directional="true" pos="0 0 2" dir="0 0 -1" castshadow="false"/>
    <geom name="table" type="plane" size="0.4 0.4 0.01" pos="0 0 -0.02" material="table"/>
    <body name="lookat" pos="0 0 0.15"/>
    <camera name="front" pos="0.75 0.35 0.6" mode="targetbody" target="lookat" fovy="50"/>
    <body name="hand" pos="0 0 0">
      <joint name="x" type="slide" axis="1 0 0" range="{LOW[0]} {HIGH[0]}"/>
      <joint name="y" type="slide" axis="0 1 0" range="{LOW[1]} {HIGH[1]}"/>
      <joint name="z" type="slide" axis="0 0 1" range="{LOW[2]} {HIGH[2]}"/>
      <geom type="sphere" size="0.025" mass="1" rgba=".15 .25 .9 1" contype="0" conaffinity="0"/>
    </body>
    <body name="goal" mocap="true">
      <geom type="sphere" size="0.03" rgba=".1 .9 .1 .8" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <position joint="x" kp="10000" kv="200" ctrlrange="{LOW[0]} {HIGH[0]}"/>
    <position joint="y" kp="10000" kv="200" ctrlrange="{LOW[1]} {HIGH[1]}"/>
    <position joint="z" kp="10000" kv="200" ctrlrange="{LOW[2]} {HIGH[2]}"/>
  </actuator>
</mujoco>
"""


def rendering_error(e: BaseException) -> str:
    """One line: why MuJoCo cannot render off-screen here, and what to install."""
    gl = os.environ.get("MUJOCO_GL", "")
    why = " ".join(f"{type(e).__name__}: {e}".split())[:200]
    if _LATE:
        return (f"MuJoCo cannot render off-screen ({why}): mujoco was imported before MUJOCO_GL was set; "
                "set MUJOCO_GL=egl (or osmesa) in the environment before starting Python")
    return f"MuJoCo cannot render off-screen with MUJOCO_GL={gl or '(unset)'} ({why}); {FIX}"


class MujocoReach(gym.Env):
    """The task described at the top of this module."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": round(1 / DT)}

    def __init__(self, render_mode: str | None = None, width: int = RENDER, height: int = RENDER) -> None:
        import mujoco

        self.model = mujoco.MjModel.from_xml_string(MJCF)
        self.data = mujoco.MjData(self.model)
        self.substeps = round(DT / self.model.opt.timestep)
        self.render_mode, self.width, self.height = render_mode, width, height
        self._renderer = None
        self.goal = np.zeros(3)
        box = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
        self.observation_space = gym.spaces.Dict({
            "observation": gym.spaces.Box(-np.inf, np.inf, (6,), np.float32),
            "achieved_goal": box, "desired_goal": box,
        })  # fmt: skip
        self.action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)

    def _obs(self) -> dict:
        pos, vel = self.data.qpos.astype(np.float32), self.data.qvel.astype(np.float32)
        return {"observation": np.concatenate([pos, vel]), "achieved_goal": pos.copy(),
                "desired_goal": self.goal.astype(np.float32)}  # fmt: skip

    def _distance(self) -> float:
        return float(np.linalg.norm(self.data.qpos - self.goal))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        import mujoco

        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self.data.ctrl[:] = START
        self.goal = self.np_random.uniform(GOAL_LOW, GOAL_HIGH)
        self.data.mocap_pos[0] = self.goal  # the goal sphere, drawn (no contact)
        mujoco.mj_forward(self.model, self.data)
        return self._obs(), {"is_success": self._distance() < SUCCESS}

    def step(self, action):
        import mujoco

        a = np.clip(np.asarray(action, np.float64).reshape(3), -1.0, 1.0)
        self.data.ctrl[:] = np.clip(self.data.qpos + STEP * a, LOW, HIGH)
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        success = self._distance() < SUCCESS
        return self._obs(), -float(not success), success, False, {"is_success": success}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            import mujoco

            try:
                self._renderer = mujoco.Renderer(self.model, self.height, self.width)
            except Exception as e:  # no EGL/OSMesa library, no device: say which and what to install
                raise RuntimeError(rendering_error(e)) from None
        self._renderer.update_scene(self.data, camera="front")
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _register() -> None:
    if "MujocoReach-v0" not in gym.registry:
        gym.register("MujocoReach-v0", entry_point=MujocoReach, max_episode_steps=50)


_register()


def check_rendering(side: int = 32) -> str:
    """Render one frame of a reset task; raise RuntimeError (one line) if it cannot or if the frame does
    not show the goal."""
    import time

    try:
        import mujoco

        env = MujocoReach(render_mode="rgb_array", width=side, height=side)
    except Exception as e:
        raise RuntimeError(rendering_error(e)) from None
    env.reset(seed=0)
    t = time.perf_counter()
    frame = env.render()
    ms = 1000 * (time.perf_counter() - t)
    env.close()
    green = (frame[..., 1].astype(int) - frame[..., [0, 2]].max(-1) > 60).any()
    if frame.shape != (side, side, 3) or not green:
        raise RuntimeError(f"MuJoCo rendered a frame without the goal in it ({frame.shape}); {FIX}")
    gl = os.environ.get("MUJOCO_GL", "(unset)")
    return f"ok: MuJoCo {mujoco.__version__} renders off-screen with MUJOCO_GL={gl} " \
        f"({side}x{side}, {ms:.0f} ms)"


if __name__ == "__main__":
    if sys.argv[1:] != ["--check-rendering"]:
        sys.exit("usage: python -m examples.mujoco_reach --check-rendering")
    try:
        print(check_rendering())
    except RuntimeError as e:
        sys.exit(f"error: {e}")
