"""Gymnasium environments (and a dm_env adapter) on the simulated robot.

Importing :mod:`torm.env` registers, with versioned ids:

- ``torm/TormPick-v0``: low-level pick for RL (:class:`torm.env.pick_env.TormPickEnv`): images and
  proprioception in, end-effector delta poses and a gripper command out; the paper's lift test as reward.
- ``torm/TormGraspSelect-v0``: high-level grasp selection (:class:`torm.env.grasp_select_env.TormGraspSelectEnv`):
  choose one of the planner's top-K grasps for a target object; reward 1 when the executed pick passes the
  paper's success test.

``gymnasium.make("torm/TormPick-v0")`` works after ``import torm.env``; without the import use
``gymnasium.make("torm.env:torm/TormPick-v0")`` (gymnasium imports the module named before the colon).
Wrap any of them with :class:`torm.env.dm_env_adapter.GymToDmEnv` for dm_env / dm-control agents.
"""

from __future__ import annotations

import gymnasium

PICK_ID = "torm/TormPick-v0"
GRASP_SELECT_ID = "torm/TormGraspSelect-v0"


def register_envs() -> None:
    """Register the torm envs with gymnasium (idempotent; called at import)."""
    registry = gymnasium.envs.registration.registry
    if PICK_ID not in registry:
        gymnasium.register(id=PICK_ID, entry_point="torm.env.pick_env:TormPickEnv", disable_env_checker=False)
    if GRASP_SELECT_ID not in registry:
        gymnasium.register(id=GRASP_SELECT_ID, entry_point="torm.env.grasp_select_env:TormGraspSelectEnv")


register_envs()

__all__ = ["GRASP_SELECT_ID", "PICK_ID", "register_envs"]
