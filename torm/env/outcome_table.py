"""Every candidate's outcome on a set of layouts, recorded once, and an env that replays them.

A ``TormGraspSelect`` step runs a whole pick in physics (2-6 s on one core), and an episode's outcome is a
deterministic function of (layout seed, action) (the env's seeding contract). So a policy comparison or a bandit
training run need not pay the physics twice: :func:`record_layout` resets a layout once per candidate and executes
each (perception and planning are cached per seed, so only the picks cost), and :class:`OutcomeTableEnv` replays
the recorded observations and outcomes as a Gymnasium env with the same spaces. A policy trained on the table acts
on the live env unchanged; :func:`replay_matches_live` checks the recording against fresh episodes.

Rows are plain JSON (one per layout): ``seed``, ``scenario``, ``obs`` (the reset observation, lists), ``rewards``
(K floats; 0 for invalid candidates), ``outcomes`` (K strings; ``invalid`` where ``valid`` is 0), ``info`` (the
reset info's scalars).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from torm.errors import ConfigError

log = logging.getLogger(__name__)

#: Outcome string recorded for a candidate index the layout has no grasp for.
INVALID = "invalid"


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def record_layout(env: gym.Env, seed: int) -> dict[str, Any]:
    """One table row: reset ``env`` (a ``TormGraspSelect`` env) at ``seed`` and execute every valid candidate.

    Each candidate runs in a fresh episode of the same seed (same observation, physics reset), so the row holds
    exactly what ``reset(seed=seed); step(a)`` returns for every ``a``.
    """
    obs, info = env.reset(seed=seed)
    K = int(env.action_space.n)
    rewards, outcomes = [0.0] * K, [INVALID] * K
    for a in range(K):
        if not obs["valid"][a]:
            continue
        again, _ = env.reset(seed=seed)
        if not all(np.array_equal(again[k], obs[k]) for k in obs):
            raise ConfigError(f"layout seed {seed}: a second reset gave another observation; the env is not "
                              "deterministic per seed, so its outcomes cannot be tabled")
        _, reward, _, _, step_info = env.step(a)
        rewards[a], outcomes[a] = float(reward), str(step_info.get("outcome"))
    scalars = {k: _plain(v) for k, v in info.items() if isinstance(v, (int, float, str, bool, np.number))}
    return {"seed": int(seed), "scenario": info.get("scenario"), "obs": {k: _plain(v) for k, v in obs.items()},
            "rewards": rewards, "outcomes": outcomes, "info": scalars}


def row_observation(row: dict[str, Any], space: gym.spaces.Dict) -> dict[str, np.ndarray]:
    """The row's observation as arrays of ``space``'s dtypes and shapes."""
    out = {}
    for k, sub in space.spaces.items():
        a = np.asarray(row["obs"][k], dtype=sub.dtype)
        if a.shape != sub.shape:
            raise ConfigError(f"table row seed {row.get('seed')}: obs[{k!r}] has shape {a.shape}, the env's space "
                              f"{sub.shape}; record the table with the same env settings (top_k, object_points)")
        out[k] = a
    return out


class OutcomeTableEnv(gym.Env):
    """A one-step env that replays recorded layouts (see the module docstring).

    Args:
        rows: table rows (:func:`record_layout`), at least one.
        observation_space: the live env's observation space (``Dict``).
        action_space: the live env's ``Discrete(K)``.

    ``reset(seed=s)`` draws a row uniformly with the env RNG (``options={"index": i}`` picks row ``i``); ``step(a)``
    returns the recorded reward, ``terminated=True`` and ``info`` with the outcome, the row's seed and scenario.
    """

    metadata = {"render_modes": []}

    def __init__(self, rows: Sequence[dict[str, Any]], observation_space: gym.spaces.Dict,
                 action_space: gym.spaces.Discrete) -> None:
        if not rows:
            raise ConfigError("OutcomeTableEnv needs at least one recorded layout")
        K = int(action_space.n)
        for r in rows:
            if len(r["rewards"]) != K:
                raise ConfigError(f"table row seed {r.get('seed')} has {len(r['rewards'])} candidates, the action "
                                  f"space {K}")
        self.observation_space, self.action_space = observation_space, action_space
        self._obs = [row_observation(r, observation_space) for r in rows]
        self._rows = list(rows)
        self._i: int | None = None
        self._mask = np.ones(K, dtype=bool)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        if set(options) - {"index"}:
            raise ConfigError(f"unknown reset option(s) {sorted(set(options) - {'index'})}; valid: ['index']")
        i = options.get("index")
        self._i = int(self.np_random.integers(len(self._rows))) if i is None else int(i)
        if not 0 <= self._i < len(self._rows):
            raise ConfigError(f"reset option index={self._i}: the table has rows 0..{len(self._rows) - 1}")
        r = self._rows[self._i]
        self._mask = self._obs[self._i]["valid"].astype(bool)
        return ({k: v.copy() for k, v in self._obs[self._i].items()},
                {"seed": r["seed"], "scenario": r["scenario"], "action_mask": self._mask.copy()})

    def action_masks(self) -> np.ndarray:
        """(K,) bool: the candidates of the row drawn at the last reset (what sb3-contrib's ``MaskablePPO`` calls;
        the live env's ``info["action_mask"]``). All True before the first reset."""
        return self._mask.copy()

    def step(self, action):
        if self._i is None:
            raise ConfigError("call reset() before step(); table episodes are one step long")
        a = int(np.asarray(action))
        if not 0 <= a < self.action_space.n:
            raise ConfigError(f"action {action!r} outside Discrete({self.action_space.n})")
        r, obs = self._rows[self._i], self._obs[self._i]
        self._i = None
        outcome = r["outcomes"][a]
        info = {"seed": r["seed"], "scenario": r["scenario"], "outcome": outcome, "is_success": r["rewards"][a] > 0,
                "invalid_choice": outcome == INVALID}
        return {k: v.copy() for k, v in obs.items()}, float(r["rewards"][a]), True, False, info


def replay_matches_live(env: gym.Env, row: dict[str, Any], actions: Sequence[int]) -> list[str]:
    """Differences between a recorded row and fresh live episodes of ``env`` for ``actions`` (empty = they match)."""
    problems = []
    for a in actions:
        obs, _ = env.reset(seed=row["seed"])
        want = row_observation(row, env.observation_space)
        if not all(np.allclose(obs[k], want[k], atol=1e-6) for k in want):
            problems.append(f"seed {row['seed']}: the reset observation differs from the recorded one")
            continue
        _, reward, _, _, info = env.step(int(a))
        if float(reward) != row["rewards"][a]:
            problems.append(f"seed {row['seed']} action {a}: live reward {reward} ({info.get('outcome')}), recorded "
                            f"{row['rewards'][a]} ({row['outcomes'][a]})")
    return problems


__all__ = ["INVALID", "OutcomeTableEnv", "record_layout", "replay_matches_live", "row_observation"]
