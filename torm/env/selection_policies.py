"""Grasp-selection policies for ``TormGraspSelect`` and a PPO baseline trained on an outcome table.

Policies map an observation (or a table row's) to a candidate index:

- ``random``: a uniformly random *valid* candidate (the action-mask baseline);
- ``planner``: index 0, the planner's best (TORM's own choice);
- ``clearance``: the valid candidate farthest from the other perceived objects, ties by the planner's score;
- ``ppo``: a trained policy (:func:`train_ppo`: sb3-contrib's ``MaskablePPO`` by default, deterministic, restricted to
  the valid candidates as the action mask says);
- ``best_of_k``: hindsight, any candidate of the row succeeds (an upper bound, not a policy).

:func:`train_ppo` trains on :class:`torm.env.outcome_table.OutcomeTableEnv` (one-step episodes, gamma 0: a
contextual bandit) and scores the deterministic policy on held-out rows along the way. Stable-Baselines3 and
sb3-contrib are the optional ``rl`` extra (``pip install "torm-glass[rl]"``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from torm.env.grasp_select_env import FEATURE_NAMES
from torm.env.outcome_table import OutcomeTableEnv
from torm.env.policy_io import ALGORITHMS, masked_action
from torm.errors import UnknownNameError

log = logging.getLogger(__name__)

POLICIES = ("random", "planner", "clearance", "ppo", "best_of_k")
#: PPO settings of :func:`train_ppo` (Stable-Baselines3 names).
PPO_HYPERPARAMETERS: dict[str, Any] = {"n_steps": 256, "batch_size": 64, "learning_rate": 3e-4, "ent_coef": 0.01,
                                       "gamma": 0.0}


def clearance_choice(obs: dict[str, Any]) -> int:
    """The valid candidate farthest from the other objects, ties broken by the planner's score (0 if none)."""
    valid = np.flatnonzero(np.asarray(obs["valid"]))
    if len(valid) == 0:
        return 0
    feats = np.asarray(obs["candidates"], float)[valid]
    clear = feats[:, FEATURE_NAMES.index("clearance")]
    score = feats[:, FEATURE_NAMES.index("score")]
    return int(valid[np.lexsort((-score, -clear))[0]])


def _as_obs(row_obs: dict[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(v, np.int8 if k == "valid" else np.float32) for k, v in row_obs.items()}


def choices(policy: str, rows: list[dict[str, Any]], model: Any = None,
            rng: np.random.Generator | None = None) -> list[int | None]:
    """The action ``policy`` takes on each table row (None for ``best_of_k``).

    ``model``: the PPO model (``ppo`` only); ``rng``: the generator of ``random``.
    """
    if policy not in POLICIES:
        raise UnknownNameError("policy", policy, POLICIES)
    out: list[int | None] = []
    for r in rows:
        valid = np.flatnonzero(np.asarray(r["obs"]["valid"]))
        if policy == "random":
            out.append(int(rng.choice(valid)) if len(valid) else 0)
        elif policy == "planner":
            out.append(0)
        elif policy == "clearance":
            out.append(clearance_choice(r["obs"]))
        elif policy == "ppo":
            out.append(masked_action(model, _as_obs(r["obs"]), np.asarray(r["obs"]["valid"], bool)))
        else:
            out.append(None)
    return out


def successes(rows: list[dict[str, Any]], actions: list[int | None]) -> int:
    """How many rows the actions succeed on (None = any candidate of the row succeeds)."""
    return int(sum((max(r["rewards"]) if a is None else r["rewards"][a]) > 0
                   for r, a in zip(rows, actions, strict=True)))


def train_ppo(train_rows: list[dict[str, Any]], eval_rows: list[dict[str, Any]], spaces: tuple[Any, Any],
              timesteps: int, eval_every: int, seed: int, model_path: str | Path | None = None,
              algorithm: str = "MaskablePPO") -> tuple[Any, list[dict[str, Any]], float]:
    """PPO (``MultiInputPolicy``, :data:`PPO_HYPERPARAMETERS`) on the training rows; ``MaskablePPO`` (the default)
    samples and learns only among the valid candidates (the table env's ``action_masks``).

    Args:
        train_rows: outcome-table rows to train on (:func:`torm.env.outcome_table.record_layout`).
        eval_rows: held-out outcome-table rows, scored during training.
        spaces: the live env's (observation_space, action_space).
        timesteps: PPO steps (one table episode each).
        eval_every: score the deterministic policy on both row sets every this many steps.
        seed: PPO's seed (the table env's draws too).
        model_path: where to save the model (``.zip``); None = not saved (:func:`torm.env.policy_io.save_policy`
            writes it with its card; this writes the bare file).
        algorithm: ``MaskablePPO`` (sb3-contrib) or ``PPO`` (Stable-Baselines3, unmasked while training).

    Returns:
        (model, learning curve rows ``{steps, heldout_successes, heldout_n, train_successes, train_n}``, seconds).
    """
    if algorithm not in ALGORITHMS:
        raise UnknownNameError("algorithm", algorithm, ALGORITHMS)
    from stable_baselines3.common.callbacks import BaseCallback

    if algorithm == "MaskablePPO":
        from sb3_contrib import MaskablePPO as Algo  # noqa: N811
    else:
        from stable_baselines3 import PPO as Algo  # noqa: N811

    env = OutcomeTableEnv(train_rows, *spaces)
    curve: list[dict[str, Any]] = []

    def score(model: Any, steps: int) -> None:
        k = successes(eval_rows, choices("ppo", eval_rows, model)) if eval_rows else 0
        k_tr = successes(train_rows, choices("ppo", train_rows, model))
        curve.append({"steps": int(steps), "heldout_successes": k, "heldout_n": len(eval_rows),
                      "train_successes": k_tr, "train_n": len(train_rows)})
        log.info("PPO %d steps: held-out %d/%d, training %d/%d", steps, k, len(eval_rows), k_tr, len(train_rows))

    class Curve(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % eval_every == 0:
                score(self.model, self.num_timesteps)
            return True

    model = Algo("MultiInputPolicy", env, seed=seed, verbose=0, device="cpu", **PPO_HYPERPARAMETERS)
    score(model, 0)
    t = time.perf_counter()
    model.learn(total_timesteps=timesteps, callback=Curve())
    secs = time.perf_counter() - t
    if curve[-1]["steps"] != model.num_timesteps:
        score(model, model.num_timesteps)
    if model_path is not None:
        Path(model_path).parent.mkdir(parents=True, exist_ok=True)
        model.save(str(model_path))
    return model, curve, secs


__all__ = ["POLICIES", "PPO_HYPERPARAMETERS", "choices", "clearance_choice", "successes", "train_ppo"]
