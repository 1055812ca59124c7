"""A trained grasp-selection policy on disk: the Stable-Baselines3 file and a card naming the env it was trained for.

``save_policy(model, "p.zip", env_id=...)`` writes ``p.zip`` (Stable-Baselines3's own format) and ``p.json`` (the
card: env id, algorithm, observation keys and shapes, the candidate feature names, the action count, how it was
trained). ``load_policy("p.zip", env_id=env.spec.id)`` refuses a policy trained for another env or another
observation layout, by name, before it acts. Five lines::

    import gymnasium as gym, torm
    from torm.env.policy_io import load_policy
    env = gym.make("torm/TormGraspSelectStress-v0")
    policy = load_policy("benchmarks/results/policies/grasp_select_ppo_stress3.zip", env_id=env.spec.id)
    obs, info = env.reset(seed=100000); obs, reward, *_ = env.step(policy.act(obs, info["action_mask"]))

:meth:`LoadedPolicy.act` never picks an action outside the mask when one is valid: ``MaskablePPO`` (sb3-contrib)
takes the mask itself; a plain ``PPO`` policy's action probabilities are masked and the most probable valid action
is taken. Stable-Baselines3 (and sb3-contrib for ``MaskablePPO``) is the optional ``rl`` extra.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ConfigError, TormError, UnknownNameError

#: the card format written by :func:`save_policy`
CARD_FORMAT = 1
#: algorithms a card may name (Stable-Baselines3 class names)
ALGORITHMS = ("MaskablePPO", "PPO")
RL_INSTALL = 'pip install "torm-glass[rl]"'


class PolicyFileError(TormError):
    """A policy file is missing, has no card, or was trained for another env or observation layout."""


def _space_signature(space: Any) -> dict[str, list[int]]:
    """``{key: shape}`` of a ``Dict`` observation space (what a policy's network was built for)."""
    return {k: [int(n) for n in s.shape] for k, s in sorted(space.spaces.items())}


def card_path(path: str | Path) -> Path:
    """The card beside a policy file (``p.zip`` -> ``p.json``)."""
    return Path(path).with_suffix(".json")


def save_policy(model: Any, path: str | Path, env_id: str, observation_space: Any, action_space: Any,
                trained_on: dict[str, Any] | None = None) -> Path:
    """Write ``model`` to ``path`` (``.zip``) and its card beside it (:func:`write_card`); returns the card's path.

    Args:
        model: a Stable-Baselines3 ``PPO`` or sb3-contrib ``MaskablePPO``.
        path: the ``.zip`` to write.
        env_id: the registered id the policy acts in (versioned, e.g. ``torm/TormGraspSelectStress-v0``).
        observation_space: that env's observation space (``Dict``).
        action_space: that env's action space (``Discrete(K)``).
        trained_on: how it was trained (steps, layouts, hyperparameters): copied into the card.
    """
    algo = type(model).__name__
    if algo not in ALGORITHMS:
        raise UnknownNameError("policy algorithm", algo, ALGORITHMS)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(str(path))
    return write_card(path, algo, env_id, observation_space, action_space, trained_on)


def write_card(path: str | Path, algorithm: str, env_id: str, observation_space: Any, action_space: Any,
               trained_on: dict[str, Any] | None = None) -> Path:
    """Write the card of the policy file ``path`` (``.json`` beside it); returns the card's path."""
    from torm.env.grasp_select_env import FEATURE_NAMES

    if algorithm not in ALGORITHMS:
        raise UnknownNameError("policy algorithm", algorithm, ALGORITHMS)
    card = {"format": CARD_FORMAT, "env_id": env_id, "algorithm": algorithm,
            "observation": _space_signature(observation_space), "action_n": int(action_space.n),
            "feature_names": list(FEATURE_NAMES), "trained_on": dict(trained_on or {}),
            "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")}
    out = card_path(path)
    out.write_text(json.dumps(card, indent=1) + "\n")
    return out


@dataclass(frozen=True)
class LoadedPolicy:
    """A loaded policy and its card; :meth:`act` picks a candidate index for one observation."""

    model: Any
    card: dict[str, Any]

    def act(self, obs: dict[str, np.ndarray], action_mask: np.ndarray | None = None) -> int:
        """The deterministic action for ``obs``, restricted to ``action_mask`` ((K,) bool; default ``obs["valid"]``)
        when at least one action is valid."""
        mask = np.asarray(obs.get("valid") if action_mask is None else action_mask, dtype=bool).reshape(-1)
        return masked_action(self.model, obs, mask)


def masked_action(model: Any, obs: dict[str, np.ndarray], mask: np.ndarray) -> int:
    """The most probable action of ``model`` among those ``mask`` allows (all of them when none is allowed)."""
    obs = {k: np.asarray(v) for k, v in obs.items()}
    if not mask.any():
        mask = np.ones_like(mask)
    if type(model).__name__ == "MaskablePPO":
        return int(model.predict(obs, action_masks=mask, deterministic=True)[0])
    import torch

    obs_t, _ = model.policy.obs_to_tensor(obs)
    with torch.no_grad():
        probs = model.policy.get_distribution(obs_t).distribution.probs[0].cpu().numpy()
    return int(np.argmax(np.where(mask, probs, -1.0)))


def load_policy(path: str | Path, env_id: str | None = None, observation_space: Any = None) -> LoadedPolicy:
    """Load a policy written by :func:`save_policy`.

    Args:
        path: the policy's ``.zip``; its card (``.json``) must be beside it.
        env_id: the env it is about to act in; a policy trained for another id (or another version) is refused.
        observation_space: that env's space; a policy built for other observation keys or shapes is refused.

    Raises:
        PolicyFileError: the file or its card is missing, or the card names another env, version, feature layout
            or observation layout than the ones given.
        ConfigError: Stable-Baselines3 (or sb3-contrib for ``MaskablePPO``) is not installed.
    """
    from torm.env.grasp_select_env import FEATURE_NAMES

    path = Path(path).expanduser()
    if not path.is_file():
        raise PolicyFileError(f"policy file {path} does not exist; the shipped ones are in "
                              "benchmarks/results/policies/")
    cp = card_path(path)
    if not cp.is_file():
        raise PolicyFileError(f"{path} has no card {cp.name} beside it, so the env it was trained for is unknown; "
                              "save policies with torm.env.policy_io.save_policy")
    card = json.loads(cp.read_text())
    if card.get("algorithm") not in ALGORITHMS:
        raise UnknownNameError("policy algorithm", str(card.get("algorithm")), ALGORITHMS)
    if env_id is not None and card.get("env_id") != env_id:
        raise PolicyFileError(f"{path.name} was trained for {card.get('env_id')}, not {env_id}: a policy from "
                              "another env or env version reads other candidates; train one for this env "
                              "(benchmarks/grasp_select_policies.py --env-id ...)")
    if list(card.get("feature_names", [])) != list(FEATURE_NAMES):
        raise PolicyFileError(f"{path.name} was trained on candidate features {card.get('feature_names')}; this "
                              f"torm's are {list(FEATURE_NAMES)}: retrain it")
    if observation_space is not None and card.get("observation") != _space_signature(observation_space):
        raise PolicyFileError(f"{path.name} was trained on observations {card.get('observation')}, the env gives "
                              f"{_space_signature(observation_space)} (another obs_mode or top_k?)")
    try:
        if card["algorithm"] == "MaskablePPO":
            from sb3_contrib import MaskablePPO as Algo  # noqa: N811
        else:
            from stable_baselines3 import PPO as Algo  # noqa: N811
    except ImportError as exc:
        raise ConfigError(f"loading a {card['algorithm']} policy needs Stable-Baselines3 and sb3-contrib: "
                          f"{RL_INSTALL}") from exc
    return LoadedPolicy(Algo.load(str(path), device="cpu"), card)


__all__ = ["ALGORITHMS", "CARD_FORMAT", "LoadedPolicy", "PolicyFileError", "card_path", "load_policy",
           "masked_action", "save_policy", "write_card"]
