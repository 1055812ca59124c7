"""The dm_env adapter: specs from the gym spaces, FIRST/MID/LAST time steps with the right discounts, and
dm_env's own conformance tests (``dm_env.test_utils.EnvironmentTestMixin``) on the pick env."""

from __future__ import annotations

import dm_env
import numpy as np
from absl.testing import absltest
from dm_env import specs, test_utils

from torm.env.dm_env_adapter import GymToDmEnv
from torm.env.grasp_select_env import TormGraspSelectEnv
from torm.env.pick_env import TormPickEnv


def test_specs_match_the_gym_spaces_and_truncation_keeps_discount_one():
    gym_env = TormPickEnv(cameras=("overview",), image_size=(32, 32), max_episode_steps=3)
    env = GymToDmEnv(gym_env, seed=0)
    try:
        obs_spec, act_spec = env.observation_spec(), env.action_spec()
        assert set(obs_spec) == set(gym_env.observation_space.spaces)
        rgb = obs_spec["overview_rgb"]
        assert isinstance(rgb, specs.BoundedArray) and rgb.shape == (32, 32, 3) and rgb.dtype == np.uint8
        assert rgb.maximum.max() == 255 and obs_spec["overview_depth"].dtype == np.float32
        assert isinstance(act_spec, specs.BoundedArray) and act_spec.shape == (7,)
        assert np.allclose(act_spec.minimum, gym_env.action_space.low) and np.allclose(act_spec.maximum, 1.0 * (
            gym_env.action_space.high))
        ts = env.reset()
        assert ts.step_type == dm_env.StepType.FIRST and ts.reward is None and ts.discount is None
        for name, spec in obs_spec.items():
            spec.validate(ts.observation[name])
        a = np.array([0, 0, -0.02, 0, 0, 0, -1], np.float32)
        steps = [env.step(a) for _ in range(3)]
        assert [s.step_type for s in steps] == [dm_env.StepType.MID] * 2 + [dm_env.StepType.LAST]
        assert steps[-1].discount == 1.0  # truncated: not a true end
        assert env.step(a).step_type == dm_env.StepType.FIRST  # step after LAST resets
        assert env.last_info["steps"] == 0
    finally:
        env.close()


def test_grasp_selection_through_dm_env_terminates_with_discount_zero():
    env = GymToDmEnv(TormGraspSelectEnv(scenario="rw1", top_k=4, n_points=512), seed=0)
    try:
        spec = env.action_spec()
        assert isinstance(spec, specs.DiscreteArray) and spec.num_values == 4
        assert env.observation_spec()["valid"].maximum == 1
        ts = env.step(np.int64(0))  # fresh env: step() resets first
        assert ts.first()
        ts = env.step(np.int64(0))
        assert ts.last() and ts.discount == 0.0 and ts.reward == 1.0 and env.last_info["outcome"] == "success"
    finally:
        env.close()


class PickEnvConformanceTest(test_utils.EnvironmentTestMixin, absltest.TestCase):
    """dm_env's interface contract on the pick env (state only, 5-step episodes so LAST steps occur)."""

    def make_object_under_test(self):
        return GymToDmEnv(TormPickEnv(cameras=(), max_episode_steps=5), seed=0)

    def make_action_sequence(self):
        rng = np.random.default_rng(0)
        for _ in range(12):
            a = rng.uniform(-1, 1, 7) * np.array([0.02] * 3 + [0.1] * 3 + [1.0])
            yield a.astype(np.float32)
