"""ManiSkill's vocabulary on torm/TormPick-v0 (issue 39): obs_mode state / rgb / rgbd / pointcloud, control_mode."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import torm
from torm.errors import UnknownNameError

gym.register_envs(torm)

KEYS = {"joint_pos", "joint_vel", "tcp_pose", "gripper_width"}


@pytest.mark.parametrize(("obs_mode", "extra"), [
    ("state", set()), ("rgb", {"overview_rgb"}), ("rgbd", {"overview_rgb", "overview_depth"}),
    ("pointcloud", {"pointcloud_xyz", "pointcloud_rgb"})])
def test_obs_modes_give_the_named_observations(obs_mode, extra):
    env = gym.make("torm/TormPick-v0", obs_mode=obs_mode, image_size=(32, 48), pointcloud_points=256)
    try:
        obs, _ = env.reset(seed=1)
        assert set(obs) == KEYS | extra
        assert env.observation_space.contains(obs)
        if obs_mode == "pointcloud":
            xyz = obs["pointcloud_xyz"]
            assert xyz.shape == (256, 3) and xyz.dtype == np.float32
            # the overview camera sees the table top (z ~ 0) around the workspace, in the world frame
            assert np.median(np.abs(xyz[:, 2])) < 0.3 and 0.0 < np.median(xyz[:, 0]) < 1.2
            again, _ = env.reset(seed=1)
            assert np.array_equal(again["pointcloud_xyz"], xyz)  # seeded
    finally:
        env.close()


def test_pointcloud_env_passes_the_checker_and_bad_modes_list_the_choices():
    env = gym.make("torm/TormPick-v0", obs_mode="pointcloud", image_size=(24, 32), pointcloud_points=64)
    try:
        check_env(env.unwrapped, skip_close_check=True)
    finally:
        env.close()
    with pytest.raises(UnknownNameError, match="pointcloud, rgb, rgbd, state"):
        gym.make("torm/TormPick-v0", obs_mode="depth")
    with pytest.raises(UnknownNameError, match="pd_ee_delta_pose"):
        gym.make("torm/TormPick-v0", control_mode="pd_joint_pos")


SELECT_KEYS = {"candidates", "valid", "object_summary", "object_points"}


@pytest.mark.parametrize(("obs_mode", "extra"), [
    ("state", set()), ("rgb", {"overview_rgb"}), ("rgbd", {"overview_rgb", "overview_depth"}),
    ("pointcloud", {"pointcloud_xyz", "pointcloud_rgb"})])
def test_grasp_select_takes_the_same_obs_modes(obs_mode, extra):
    env = gym.make("torm/TormGraspSelect-v0", obs_mode=obs_mode, image_size=(24, 32), pointcloud_points=64)
    try:
        obs, info = env.reset(seed=0)
        assert set(obs) == SELECT_KEYS | extra  # no ground truth unless privileged_state
        assert env.observation_space.contains(obs)
        again, _ = env.reset(seed=0)
        assert all(np.array_equal(obs[k], again[k]) for k in obs)  # seeded
        if obs_mode == "rgbd":
            assert 0.2 < float(np.median(obs["overview_depth"])) < 3.0  # the table, about a metre away
        if obs_mode == "pointcloud":
            check_env(env.unwrapped, skip_render_check=True)
    finally:
        env.close()


def test_grasp_select_privileged_state_names_the_real_target_and_bad_modes_list_the_choices():
    env = gym.make("torm/TormGraspSelect-v0", privileged_state=True)
    try:
        obs, _ = env.reset(seed=0)
        true = obs["true_target"]
        assert true[3] == 1.0  # the oracle's target is a real object ...
        centroid = obs["object_summary"][:3]
        assert np.linalg.norm(true[:2] - centroid[:2]) < 0.05  # ... under the perceived centroid
    finally:
        env.close()
    with pytest.raises(UnknownNameError, match="obs_mode 'depth'; valid choices: pointcloud, rgb, rgbd, state"):
        gym.make("torm/TormGraspSelect-v0", obs_mode="depth")
