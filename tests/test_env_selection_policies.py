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


@pytest.mark.parametrize("algorithm", ["MaskablePPO", "PPO"])
def test_ppo_learns_a_bandit_whose_second_candidate_always_succeeds(tmp_path, algorithm):
    pytest.importorskip("sb3_contrib")
    env = TormGraspSelectEnv(top_k=K, object_points=M)  # only its spaces are used (no world is built)
    spaces = (env.observation_space, env.action_space)
    model, curve, secs = train_ppo(_rows(40, 1, 0), _rows(20, 1, 1), spaces, timesteps=2048, eval_every=1024,
                                   seed=0, model_path=tmp_path / "ppo.zip", algorithm=algorithm)
    assert type(model).__name__ == algorithm
    assert curve[0]["steps"] == 0 and curve[-1]["steps"] == 2048 and secs > 0
    assert curve[-1]["heldout_successes"] >= 18, curve  # held-out rows: it picks candidate 1
    assert (tmp_path / "ppo.zip").is_file()


@pytest.mark.parametrize("algorithm", ["MaskablePPO", "PPO"])
def test_a_trained_policy_never_picks_outside_the_mask_and_its_card_names_its_env(tmp_path, algorithm):
    pytest.importorskip("sb3_contrib")
    from torm.env.outcome_table import OutcomeTableEnv
    from torm.env.policy_io import PolicyFileError, load_policy, save_policy

    env = TormGraspSelectEnv(top_k=K, object_points=M)
    spaces = (env.observation_space, env.action_space)
    rows = _rows(8, 1, 0)
    table = OutcomeTableEnv(rows, *spaces)
    obs, info = table.reset(options={"index": 1})  # odd row: the last candidate is invalid
    assert info["action_mask"].tolist() == [True, True, False] and table.action_masks().tolist() == [True, True, False]
    model, _, _ = train_ppo(rows, rows, spaces, timesteps=256, eval_every=256, seed=0, algorithm=algorithm)
    save_policy(model, tmp_path / "p.zip", "torm/TormGraspSelect-v0", *spaces, trained_on={"note": "test"})
    policy = load_policy(tmp_path / "p.zip", env_id="torm/TormGraspSelect-v0", observation_space=spaces[0])
    assert policy.card["algorithm"] == algorithm and policy.card["action_n"] == K
    for only in range(K):  # whatever the network prefers, a one-candidate mask leaves that candidate
        mask = np.arange(K) == only
        assert policy.act(obs, mask) == only
    picked = choices("ppo", rows, policy.model)
    assert picked and all(r["obs"]["valid"][a] for r, a in zip(rows, picked, strict=True))
    with pytest.raises(PolicyFileError, match="trained for torm/TormGraspSelect-v0, not torm/TormGraspSelectHard-v0"):
        load_policy(tmp_path / "p.zip", env_id="torm/TormGraspSelectHard-v0")
    other = TormGraspSelectEnv(top_k=K + 1, object_points=M)
    with pytest.raises(PolicyFileError, match="another obs_mode or top_k"):
        load_policy(tmp_path / "p.zip", observation_space=other.observation_space)
    (tmp_path / "p.json").unlink()
    with pytest.raises(PolicyFileError, match="has no card"):
        load_policy(tmp_path / "p.zip")
    with pytest.raises(PolicyFileError, match="does not exist"):
        load_policy(tmp_path / "missing.zip")


@pytest.mark.parametrize("name, env_id", [("grasp_select_ppo_stress3", "torm/TormGraspSelectStress-v0"),
                                          ("grasp_select_ppo_tormgraspselecthard_v0", "torm/TormGraspSelectHard-v0")])
def test_the_shipped_policies_load_for_their_env_and_act_within_the_mask(name, env_id):
    """The committed policies (docs/envs/grasp_select.md's five lines) load for the env their card names and read
    its observation space: a change of the env's spaces that would break them fails here."""
    pytest.importorskip("sb3_contrib")
    import gymnasium as gym

    import torm.env  # noqa: F401  (registers the envs)
    from torm.env.policy_io import load_policy

    path = Path(__file__).resolve().parents[1] / "benchmarks/results/policies" / f"{name}.zip"
    env = gym.make(env_id)  # no world is built before reset
    try:
        policy = load_policy(path, env_id=env.spec.id, observation_space=env.observation_space)
        assert policy.model.action_space == env.action_space
        obs = env.observation_space.sample()
        mask = np.zeros(env.action_space.n, bool)
        mask[[2, 5]] = True
        assert policy.act(obs, mask) in (2, 5)
    finally:
        env.close()
