"""torm/TormGraspSelect-v0: gymnasium's checker, features that describe the planner's candidates, and the
planner's best grasp (action 0) picking the rw1 glass cylinder by the paper's success test."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import torm  # noqa: F401  (importing torm registers the envs)
from torm.env.errors import InvalidActionError
from torm.env.grasp_select_env import FEATURE_NAMES, TormGraspSelectEnv
from torm.errors import ConfigError, UnknownNameError


def test_registered_env_passes_the_gymnasium_checker():
    env = gym.make("torm/TormGraspSelect-v0", scenario="rw1", top_k=4)
    try:
        check_env(env.unwrapped, skip_close_check=True)
        assert env.action_space == gym.spaces.Discrete(4)
        assert env.observation_space["candidates"].shape == (4, len(FEATURE_NAMES))
    finally:
        env.close()


def test_planner_best_candidate_picks_the_rw1_cylinder():
    env = TormGraspSelectEnv(scenario="rw1", perception="oracle", render_mode="rgb_array")
    try:
        obs, info = env.reset(seed=0)
        assert info["target_label"] == 1000 and info["n_perceived"] == 1 and info["n_candidates"] == 8
        assert obs["valid"].tolist() == [1] * 8
        cands = env.candidates
        scores = [g.score for g in cands]
        assert scores == sorted(scores, reverse=True)  # index 0 = the planner's best
        f = obs["candidates"]
        c = obs["object_summary"][:3]
        T0 = cands[0].T_world_grasp
        assert np.allclose(f[0, 0:3], T0[:3, 3] - c, atol=1e-6) and np.allclose(f[0, 3:6], T0[:3, 0], atol=1e-6)
        assert np.allclose(f[:, FEATURE_NAMES.index("score")], scores, atol=1e-6)
        # the cylinder (60 mm x 100 mm) seen through the oracle cloud: centroid on the object, 6 x 6 x 10 cm box
        true_c = env.backend.world.objects[0].T_world_obj[:3, 3]
        assert np.allclose(c[:2], true_c[:2], atol=0.005) and 0.03 < c[2] < 0.07
        assert np.allclose(obs["object_summary"][3:6], [0.06, 0.06, 0.10], atol=0.005)
        assert np.all(np.abs(obs["object_points"]) < 0.07)
        rest = env.backend.ground_truth.object_poses()[1][:3, 3]
        obs2, reward, terminated, truncated, info = env.step(0)
        assert reward == 1.0 and terminated and not truncated, info
        assert info["outcome"] == "success" and info["pick"]["judgement"]["lift_m"] >= 0.24
        assert info["picked_object"] == 1  # the judge (ground truth) names the real object that was picked
        moved = np.linalg.norm(env.backend.ground_truth.object_poses()[1][:2, 3] - rest[:2])
        assert abs(moved - 0.20) < 0.01  # really translated 20 cm and put back
        assert env.render().shape == (240, 320, 3)
        with pytest.raises(ConfigError, match="one step"):
            env.step(1)
        # the same seed gives the same candidates
        obs3, _ = env.reset(seed=0)
        assert np.array_equal(obs3["candidates"], obs["candidates"])
        _, reward3, *_ = env.step(0)
        assert reward3 == reward
    finally:
        env.close()


def test_bad_actions_and_missing_candidates():
    env = TormGraspSelectEnv(scenario="rw1", top_k=4, n_points=512)
    try:
        env.reset(seed=1)
        with pytest.raises(InvalidActionError, match=r"0\.\.3"):
            env.step(4)
        with pytest.raises(InvalidActionError, match="Discrete"):
            env.step(1.5)
        env._grasps = env._grasps[:2]  # fewer candidates than K: choosing a missing one fails without moving
        t0 = env.backend.clock.now()
        _, r, term, _, info = env.step(3)
        assert r == 0.0 and term and info["invalid_choice"] and env.backend.clock.now() == t0
        with pytest.raises(UnknownNameError, match="oracle"):
            TormGraspSelectEnv(perception="lidar")
    finally:
        env.close()


def test_measured_variant_draws_the_harness_realism_per_layout():
    import gymnasium as gym

    from sim.realism import sample_realism
    from torm.env import GRASP_SELECT_MEASURED_ID

    env = gym.make(GRASP_SELECT_MEASURED_ID, scenario="rw1")
    try:
        _, info = env.reset(seed=3)
        drawn = sample_realism("measured", 3, [False])
        assert info["realism"] == "measured" and info["layout_seed"] == 3
        assert info["grip_force_n"] == pytest.approx(min(max(drawn.grip_force_n, 20.0), 235.0))
        assert env.unwrapped._backend.realism.pad_friction == pytest.approx(drawn.pad_friction)
        _, reward, terminated, _, step_info = env.step(0)
        assert terminated and reward in (0.0, 1.0) and "outcome" in step_info
    finally:
        env.close()
    with pytest.raises(Exception, match="realism"):
        gym.make("torm/TormGraspSelect-v0", realism="perfect")


def test_perception_and_planning_run_on_the_loop_view_without_ground_truth(monkeypatch):
    """The env perceives through the harness's loop functions on a LoopBackend: a ground-truth read fails there."""
    import torm.loop
    from torm.backend.blind import GroundTruthAccessError, LoopBackend

    seen = {}
    real_perceive = torm.loop.perceive

    def spy(config, backend, rng, timings, **kw):
        seen["backend"] = backend
        with pytest.raises(GroundTruthAccessError):
            backend.ground_truth  # noqa: B018
        return real_perceive(config, backend, rng, timings, **kw)

    monkeypatch.setattr(torm.loop, "perceive", spy)
    env = TormGraspSelectEnv(scenario="rw1", top_k=2, n_points=256, n_views=4)
    try:
        _, info = env.reset(seed=2)
        assert isinstance(seen["backend"], LoopBackend)
        assert info["perception_info"]["table_height_m"] == pytest.approx(0.0)  # the cell's declaration
        assert env.trial.scenario == "rw1" and env.trial.seed == 2 and env.trial.method == "oracle"
    finally:
        env.close()


def test_suite_draws_scenarios_by_seed_and_overrides_reach_the_trial_config():
    from torm.env.grasp_select_env import GraspSelectEnvConfig

    cfg = GraspSelectEnvConfig(suite="rw", perception="torm", segmenter="noisy", realism="measured",
                               trial_overrides=("reconstruction.grid_res=48",))
    assert cfg.scenarios == tuple(f"rw{i}" for i in range(1, 9))
    trial = cfg.trial_config("rw4", 7)
    assert (trial.scenario, trial.seed, trial.method) == ("rw4", 7, "torm")
    assert trial.segmentation.segmenter == "noisy" and trial.world.realism == "measured"
    assert trial.reconstruction.grid_res == 48 and trial.grasp.top_k == cfg.top_k
    with pytest.raises(ConfigError, match="grid_rez"):
        GraspSelectEnvConfig(trial_overrides=("reconstruction.grid_rez=48",))
    with pytest.raises(UnknownNameError, match="syn_hard"):
        GraspSelectEnvConfig(suite="hard")
    env = TormGraspSelectEnv(suite="rw", top_k=2, n_points=256, n_views=4)
    try:
        drawn = [env.reset(seed=s)[1]["scenario"] for s in (0, 1, 2, 0)]
        assert drawn[0] == drawn[3] and all(d.startswith("rw") for d in drawn)
    finally:
        env.close()


def test_action_mask_names_the_candidates_the_gymnasium_way():
    """``info["action_mask"]`` at reset and step and ``action_masks()`` (what sb3-contrib's MaskablePPO calls) mark
    exactly the indices with a candidate; a random policy that samples inside the mask never makes an invalid
    choice; before reset the mask is empty."""
    env = TormGraspSelectEnv(scenario="rw1", top_k=4, n_points=512)
    try:
        assert env.action_masks().tolist() == [False] * 4
        obs, info = env.reset(seed=1)
        mask = info["action_mask"]
        assert mask.dtype == bool and mask.tolist() == obs["valid"].astype(bool).tolist()
        assert np.array_equal(env.action_masks(), mask) and mask.any()
        env._obs["valid"][2:] = 0  # as if only two candidates existed
        env._grasps = env._grasps[:2]
        m = env.action_masks()
        assert m.tolist() == [True, True, False, False]
        a = int(env.action_space.sample(mask=m.astype(np.int8)))  # gymnasium's masked sampling
        assert m[a]
        _, _, _, _, info = env.step(a)
        assert not info["invalid_choice"] and info["action_mask"].tolist() == m.tolist()
    finally:
        env.close()
