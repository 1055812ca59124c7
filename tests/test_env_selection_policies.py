"""Grasp-selection policies on outcome-table rows: the heuristics choose what they say, PPO learns a bandit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torm.env.grasp_select_env import FEATURE_NAMES, TormGraspSelectEnv
from torm.env.outcome_table import INVALID
from torm.env.selection_policies import choices, clearance_choice, successes, train_ppo
from torm.errors import UnknownNameError

K, M = 3, 4


def _rows(n: int, good: int, seed: int) -> list[dict]:
    """Synthetic rows: random features, all candidates valid except the last on odd rows; only ``good`` succeeds."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        cand = rng.uniform(-0.1, 0.1, (K, len(FEATURE_NAMES)))
        valid = [1, 1, int(i % 2 == 0)]
        rewards = [float(a == good and valid[a]) for a in range(K)]
        outcomes = ["success" if r else ("slipped_during_lift" if v else INVALID)
                    for r, v in zip(rewards, valid, strict=True)]
        rows.append({"seed": i, "scenario": "syn", "rewards": rewards, "outcomes": outcomes,
                     "obs": {"candidates": cand.tolist(), "valid": valid, "object_summary": [0.1] * 10,
                             "object_points": np.zeros((M, 3)).tolist()}})
    return rows


def test_heuristics_choose_what_they_say():
    rows = _rows(6, good=1, seed=0)
    ci = FEATURE_NAMES.index("clearance")
    for r in rows:
        valid = np.flatnonzero(r["obs"]["valid"])
        clear = np.asarray(r["obs"]["candidates"])[valid, ci]
        assert clearance_choice(r["obs"]) == valid[np.argmax(clear)]
    rnd = choices("random", rows, rng=np.random.default_rng(1))
    assert all(r["obs"]["valid"][a] for r, a in zip(rows, rnd, strict=True))
    assert choices("planner", rows) == [0] * 6
    assert successes(rows, choices("best_of_k", rows)) == 6 and successes(rows, [0] * 6) == 0
    with pytest.raises(UnknownNameError, match="clearance"):
        choices("greedy", rows)


def test_ppo_learns_a_bandit_whose_second_candidate_always_succeeds(tmp_path):
    pytest.importorskip("stable_baselines3")
    env = TormGraspSelectEnv(top_k=K, object_points=M)  # only its spaces are used (no world is built)
    spaces = (env.observation_space, env.action_space)
    model, curve, secs = train_ppo(_rows(40, 1, 0), _rows(20, 1, 1), spaces, timesteps=2048, eval_every=1024,
                                   seed=0, model_path=tmp_path / "ppo.zip")
    assert curve[0]["steps"] == 0 and curve[-1]["steps"] == 2048 and secs > 0
    assert curve[-1]["heldout_successes"] >= 18, curve  # held-out rows: it picks candidate 1
    assert (tmp_path / "ppo.zip").is_file()


def test_the_shipped_stress_policy_loads_and_acts_on_the_live_envs_observations():
    """The committed PPO policy (docs/envs/grasp_select.md's five lines) reads the live env's observation space:
    a change of the env's spaces that would break the shipped policy fails here."""
    pytest.importorskip("stable_baselines3")
    import gymnasium as gym
    from stable_baselines3 import PPO

    import torm.env  # noqa: F401  (registers the envs)

    path = Path(__file__).resolve().parents[1] / "benchmarks/results/policies/grasp_select_ppo_stress3.zip"
    policy = PPO.load(str(path), device="cpu")
    env = gym.make("torm/TormGraspSelectStress-v0")  # no world is built before reset
    try:
        assert policy.observation_space == env.observation_space and policy.action_space == env.action_space
        obs = env.observation_space.sample()
        action = int(policy.predict(obs, deterministic=True)[0])
        assert env.action_space.contains(action)
    finally:
        env.close()
