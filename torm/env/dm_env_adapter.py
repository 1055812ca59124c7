"""A :class:`dm_env.Environment` wrapping any gymnasium env (e.g. the torm envs) for dm_env / dm-control agents.

Time steps: ``reset()`` -> ``FIRST`` (reward and discount None); ``step(a)`` -> ``MID`` with discount 1, or
``LAST`` when the gym episode ends: discount 0 when it *terminated* (a true end: success, failure, physics
error) and 1 when it was *truncated* (time limit: the value of the next state still counts). ``step`` on a
fresh env or after a ``LAST`` step resets (returns ``FIRST``), as dm_env prescribes.

Specs come from the gym spaces (:func:`space_to_spec`): ``Box`` -> ``BoundedArray`` (``Array`` when no bound is
finite), ``Discrete`` -> ``DiscreteArray`` (``BoundedArray`` when ``start != 0``), ``MultiBinary`` ->
``BoundedArray`` 0..1, ``MultiDiscrete`` -> ``BoundedArray`` 0..nvec-1, ``Dict`` -> dict of specs (same keys),
``Tuple`` -> tuple of specs. The gym ``info`` dict of the last call is kept in :attr:`GymToDmEnv.last_info`.
"""

from __future__ import annotations

from typing import Any

import dm_env
import gymnasium as gym
import numpy as np
from dm_env import specs
from gymnasium import spaces

from torm.errors import ConfigError


def space_to_spec(space: spaces.Space, name: str | None = None) -> Any:
    """The dm_env spec (or nested dict/tuple of specs) of a gymnasium space (see the module docstring)."""
    if isinstance(space, spaces.Box):
        low, high = np.asarray(space.low), np.asarray(space.high)
        if not (np.any(np.isfinite(low)) or np.any(np.isfinite(high))):
            return specs.Array(space.shape, space.dtype, name=name)
        return specs.BoundedArray(space.shape, space.dtype, low, high, name=name)
    if isinstance(space, spaces.Discrete):
        if int(space.start) == 0:
            return specs.DiscreteArray(int(space.n), dtype=space.dtype, name=name)
        return specs.BoundedArray((), space.dtype, int(space.start), int(space.start + space.n - 1), name=name)
    if isinstance(space, spaces.MultiBinary):
        return specs.BoundedArray(space.shape, space.dtype, 0, 1, name=name)
    if isinstance(space, spaces.MultiDiscrete):
        return specs.BoundedArray(space.shape, space.dtype, np.zeros(space.shape, space.dtype),
                                  np.asarray(space.nvec) - 1 + np.asarray(space.start), name=name)
    if isinstance(space, spaces.Dict):
        return {k: space_to_spec(s, k) for k, s in space.spaces.items()}
    if isinstance(space, spaces.Tuple):
        return tuple(space_to_spec(s, f"{name or 'item'}_{i}") for i, s in enumerate(space.spaces))
    raise ConfigError(f"no dm_env spec for gymnasium space {type(space).__name__}; supported: Box, Discrete, "
                      "MultiBinary, MultiDiscrete, Dict, Tuple")


def _to_gym_action(space: spaces.Space, action: Any) -> Any:
    if isinstance(space, spaces.Discrete):
        return int(np.asarray(action).reshape(()))
    if isinstance(space, (spaces.Box, spaces.MultiBinary, spaces.MultiDiscrete)):
        return np.asarray(action, dtype=space.dtype)
    if isinstance(space, spaces.Dict):
        return {k: _to_gym_action(s, action[k]) for k, s in space.spaces.items()}
    if isinstance(space, spaces.Tuple):
        return tuple(_to_gym_action(s, a) for s, a in zip(space.spaces, action, strict=True))
    return action


class GymToDmEnv(dm_env.Environment):
    """dm_env view of a gymnasium env.

    Args:
        env: the gymnasium env (e.g. ``gymnasium.make("torm/TormPick-v0")``); closed by :meth:`close`.
        seed: passed to the first ``reset`` (later resets continue the env's RNG), None for an unseeded start.
    """

    def __init__(self, env: gym.Env, seed: int | None = None) -> None:
        self.gym_env = env
        self._seed = seed
        self._reset_next = True
        self._obs_spec = space_to_spec(env.observation_space, "observation")
        self._act_spec = space_to_spec(env.action_space, "action")
        self.last_info: dict[str, Any] = {}

    def reset(self) -> dm_env.TimeStep:
        obs, self.last_info = self.gym_env.reset(seed=self._seed)
        self._seed = None
        self._reset_next = False
        return dm_env.restart(obs)

    def step(self, action: Any) -> dm_env.TimeStep:
        if self._reset_next:
            return self.reset()
        obs, reward, terminated, truncated, self.last_info = self.gym_env.step(
            _to_gym_action(self.gym_env.action_space, action))
        reward = float(reward)
        if terminated:
            self._reset_next = True
            return dm_env.termination(reward, obs)
        if truncated:
            self._reset_next = True
            return dm_env.truncation(reward, obs)
        return dm_env.transition(reward, obs)

    def observation_spec(self) -> Any:
        return self._obs_spec

    def action_spec(self) -> Any:
        return self._act_spec

    def close(self) -> None:
        self.gym_env.close()
