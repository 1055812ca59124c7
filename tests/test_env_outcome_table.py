"""The outcome table: every candidate's recorded outcome equals a live episode's, and the replay env is a valid
Gymnasium env with the live env's spaces."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from torm.env.grasp_select_env import TormGraspSelectEnv
from torm.env.outcome_table import INVALID, OutcomeTableEnv, record_layout, replay_matches_live
from torm.errors import ConfigError


@pytest.fixture(scope="module")
def recorded():
    env = TormGraspSelectEnv(scenario="rw1", top_k=3, n_points=256, n_views=4)
    try:
        row = record_layout(env, 0)
        yield env, row
    finally:
        env.close()


def test_a_recorded_layout_replays_like_the_live_env(recorded):
    env, row = recorded
    assert row["seed"] == 0 and row["scenario"] == "rw1" and len(row["rewards"]) == 3
    valid = np.asarray(row["obs"]["valid"])
    assert [o == INVALID for o in row["outcomes"]] == (valid == 0).tolist()
    assert all(r in (0.0, 1.0) for r in row["rewards"])
    assert row["rewards"][0] == 1.0 and row["outcomes"][0] == "success"  # rw1's cylinder, the planner's best
    assert replay_matches_live(env, row, [0]) == []
    tampered = {**row, "rewards": [0.0] + row["rewards"][1:]}
    assert replay_matches_live(env, tampered, [0])  # a wrong record is caught


def test_table_env_is_a_gymnasium_env_with_the_live_spaces(recorded):
    env, row = recorded
    other = {**row, "seed": 9, "rewards": [0.0, 1.0, 0.0], "outcomes": ["slipped", "success", INVALID]}
    table = OutcomeTableEnv([row, other], env.observation_space, env.action_space)
    check_env(table, skip_render_check=True)
    obs, info = table.reset(options={"index": 1})
    assert env.observation_space.contains(obs) and info["seed"] == 9
    _, reward, terminated, truncated, info = table.step(1)
    assert reward == 1.0 and terminated and not truncated and info["outcome"] == "success"
    table.reset(options={"index": 1})
    assert table.step(2)[4]["invalid_choice"]
    with pytest.raises(ConfigError, match="rows 0..1"):
        table.reset(options={"index": 2})
    with pytest.raises(ConfigError, match="candidates"):
        OutcomeTableEnv([{**row, "rewards": [1.0]}], env.observation_space, env.action_space)
