"""examples/metaworld: the record step's shapes and resize, and the user's variation (the moved goal)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot")
pytest.importorskip("metaworld")
pytestmark = pytest.mark.lerobot
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from examples.metaworld import task as mw  # noqa: E402

TASK = mw.TASKS[0]


def test_resize_is_the_plugins_bilinear_antialiased_interpolate():
    x = torch.rand(3, mw.RENDER, mw.RENDER)
    want = torch.nn.functional.interpolate(x[None], size=(mw.IMAGE, mw.IMAGE), mode="bilinear",
                                           antialias=True, align_corners=False)[0]  # fmt: skip
    assert torch.equal(mw.resize_images(x), want)
    plugin = pytest.importorskip("lerobot_policy_prop.modeling_prop")
    assert torch.equal(plugin.resize_frames(x, (mw.IMAGE, mw.IMAGE)), want)


def test_moved_shifts_objects_and_goal_not_the_hand_nor_padding():
    raw = np.arange(39, dtype=np.float64) + 1
    raw[11:14] = 0  # a task with one object: the second object's slot is padding
    out = mw.moved(raw, mw.USER_OFFSET)
    assert np.array_equal(out[:4], raw[:4]) and np.array_equal(out[18:22], raw[18:22])
    for s in (slice(4, 7), slice(22, 25), slice(36, 39)):
        assert np.allclose(out[s] - raw[s], mw.USER_OFFSET)
    assert np.array_equal(out[11:14], raw[11:14])


def test_record_writes_the_plugin_sized_frames_and_the_user_expert_holds_the_moved_goal(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    counts = mw.record(tmp_path / "user", TASK, 1, 50_000, mw.USER_OFFSET, horizon=4)
    assert counts["episodes"] == 1 and counts["frames"] == 4
    ds = LeRobotDataset(f"local/{TASK}-user", root=tmp_path / "user")
    item = ds[0]
    assert tuple(item[mw.IMAGE_KEY].shape) == (3, mw.IMAGE, mw.IMAGE)
    assert tuple(item[mw.STATE].shape) == (4,) and tuple(item[mw.ACTION].shape) == (4,)
    assert item["task"] == "Press a button from the top"
    # the stored frame is the env's first 480x480 frame through resize_images, rounded to 1/255
    env = mw.Env(TASK)
    obs = env.reset(50_000)
    assert obs["pixels"].shape == (mw.RENDER, mw.RENDER, 3)
    want = torch.from_numpy(mw.to_uint8_hwc(mw.frame(obs["pixels"]))).permute(2, 0, 1).float() / 255
    assert torch.allclose(item[mw.IMAGE_KEY], want, atol=1e-6)
    # the user's expert, fed the moved button, holds the hand 10 cm above it: the user's criterion
    # holds and MetaWorld's own success (the button pressed) does not
    pressed = False
    for _ in range(70):
        obs, _, _, _, info = env.step(env.expert(mw.USER_OFFSET))
        pressed = pressed or bool(info["is_success"])
    assert mw.user_success(mw.hand(obs), env.object0) and not pressed
    json.dumps(counts)
    env.close()


def test_each_tasks_user_criterion_compares_its_own_coordinates():
    o0 = np.array([0.1, 0.6, 0.17])
    # handle-press: the hand presses the table 10 cm along x from the handle; its height is the table's
    on_table = o0 + mw.user_offset("handle-press-v3") + np.array([0.0, -0.02, -0.125])
    assert mw.user_success(on_table, o0, "handle-press-v3")
    assert not mw.user_success(o0 + np.array([0.0, -0.02, -0.125]), o0, "handle-press-v3")  # the handle
    # button-press-topdown: 10 cm up, in all three coordinates
    assert mw.user_success(o0 + mw.USER_OFFSET, o0, TASK)
    assert not mw.user_success(o0 + mw.USER_OFFSET + np.array([0.0, 0.0, -0.08]), o0, TASK)
    # drawer-close: the hand parks 10 cm in front of the open drawer's handle, at any height
    parked = o0 + mw.user_offset("drawer-close-v3") + np.array([0.005, 0.0, 0.19])
    assert mw.user_success(parked, o0, "drawer-close-v3") and not mw.user_success(o0, o0, "drawer-close-v3")
    with pytest.raises(SystemExit, match="no user variation"):
        mw.user_offset("reach-v3")
