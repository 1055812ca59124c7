"""Every registered torm env id (issue 39): gymnasium's checker, seeded determinism, and realism recorded in info.

The grasp-selection variants run with a small capture (few views, small K) to keep the test short; their world,
perception and realism are the registered ones."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import torm
from torm.env import GRASP_SELECT_HARD_ID, GRASP_SELECT_ID, GRASP_SELECT_MEASURED_ID, GRASP_SELECT_STRESS_ID, PICK_ID

gym.register_envs(torm)

CHEAP = {"n_views": 8, "capture_scale": 0.25, "top_k": 2, "n_points": 256}
VARIANTS = {PICK_ID: {"obs_mode": "state"}, GRASP_SELECT_ID: CHEAP, GRASP_SELECT_MEASURED_ID: CHEAP,
            GRASP_SELECT_HARD_ID: {**CHEAP, "n_views": 12}, GRASP_SELECT_STRESS_ID: {**CHEAP, "n_views": 12}}


def test_every_registered_torm_id_is_covered():
    ids = {i for i in gym.envs.registration.registry if i.startswith("torm/")}
    assert ids == set(VARIANTS)


@pytest.mark.parametrize("env_id", sorted(VARIANTS))
def test_registered_variant_passes_the_checker_and_is_seeded(env_id):
    env = gym.make(env_id, **VARIANTS[env_id])
    try:
        check_env(env.unwrapped, skip_render_check=True, skip_close_check=True)
        obs1, info1 = env.reset(seed=4)
        if env_id == PICK_ID:
            actions = np.random.default_rng(0).uniform(-1, 1, (5, 7)).astype(np.float32)
            for a in actions:
                out1 = env.step(a)
            obs2, _ = env.reset(seed=4)
            for a in actions:
                out2 = env.step(a)
            assert all(np.array_equal(out1[0][k], out2[0][k]) for k in out1[0]) and out1[1] == out2[1]
        else:
            assert info1["scenario"] and info1["realism"] == env.spec.kwargs.get("realism", "ideal")
            r1 = env.step(0)[1]
            obs2, _ = env.reset(seed=4)
            r2 = env.step(0)[1]
            assert r1 == r2
        assert all(np.array_equal(obs1[k], obs2[k]) for k in obs1)
    finally:
        env.close()


def test_pick_env_draws_the_realism_profile_and_records_it():
    from sim.realism import sample_realism

    env = gym.make(PICK_ID, obs_mode="state", realism="measured")
    try:
        _, info = env.reset(seed=6)
        drawn = sample_realism("measured", 6, [False])
        assert info["realism"] == "measured" and info["layout_seed"] == 6
        assert info["realism_drawn"]["pad_friction"] == pytest.approx(drawn.pad_friction)
        assert env.unwrapped.backend.realism.object_mass_scale == pytest.approx(drawn.object_mass_scale)
        assert info["realism_drawn"]["object_friction"] == pytest.approx(drawn.object_friction)
    finally:
        env.close()
    with pytest.raises(Exception, match="realism"):
        gym.make(PICK_ID, realism="perfect")
