"""Gymnasium environments (and a dm_env adapter) on the simulated robot.

Importing :mod:`torm` (or :mod:`torm.env`) registers, with versioned ids:

- ``torm/TormPick-v0``: low-level pick for RL (:class:`torm.env.pick_env.TormPickEnv`): images and
  proprioception in, end-effector delta poses and a gripper command out; the paper's lift test as reward.
- ``torm/TormGraspSelect-v0``: high-level grasp selection (:class:`torm.env.grasp_select_env.TormGraspSelectEnv`):
  choose one of the planner's top-K grasps for a perceived object; reward 1 when the executed pick passes the
  paper's success test. Variants: ``torm/TormGraspSelectMeasured-v0`` (the ``measured`` world, oracle
  perception) and ``torm/TormGraspSelectHard-v0`` (packed ``syn_hard`` suite, ``measured`` world, TORM perception
  through the segmentation error model, K = 16).

``gymnasium.make("torm/TormPick-v0")`` works after ``import torm``; as in Gymnasium-Robotics,
``gymnasium.register_envs(torm)`` keeps linters from flagging that import as unused. Without any import,
``gymnasium.make("torm:torm/TormPick-v0")`` works too (gymnasium imports the module named before the colon).
The specs carry ``max_episode_steps`` (TimeLimit): 200 steps for TormPick, 1 for TormGraspSelect (one pick).
Wrap any of them with :class:`torm.env.dm_env_adapter.GymToDmEnv` for dm_env / dm-control agents.
"""

from __future__ import annotations

import gymnasium

#: Episode lengths of the registered specs (steps).
PICK_MAX_EPISODE_STEPS = 200
GRASP_SELECT_MAX_EPISODE_STEPS = 1

PICK_ID = "torm/TormPick-v0"
GRASP_SELECT_ID = "torm/TormGraspSelect-v0"
#: TormGraspSelect in the harness's ``measured`` world (contact, grip force, mass, calibration and execution
#: errors drawn per layout from sourced ranges), where a grasp choice can fail as the harness's picks do.
GRASP_SELECT_MEASURED_ID = "torm/TormGraspSelectMeasured-v0"
#: The realistic, hard grasp-selection variant: the packed ``syn_hard`` suite drawn per reset, the ``measured``
#: world, the TORM pipeline perceiving through the segmentation error model (``noisy``, the paper preset) and the
#: planner's top 16, so that the planner plans on imperfect reconstructions of cluttered scenes and the choice
#: reaches candidates the arm cannot reach or that hit a neighbour.
GRASP_SELECT_HARD_ID = "torm/TormGraspSelectHard-v0"
#: Settings of :data:`GRASP_SELECT_HARD_ID` (keyword arguments of its spec).
GRASP_SELECT_HARD_KWARGS = {"suite": "syn_hard", "realism": "measured", "perception": "torm", "segmenter": "noisy",
                            "top_k": 16}
#: The hard variant in the ``stress`` world at 3x the measured ranges (sim/REALISM.md): contact, grip force, mass,
#: calibration and execution errors beyond what a cell shows, so the planner's first choice fails often enough that
#: the choice matters (benchmarks/results/grasp_select_policies_stress.md: best-of-K above the planner).
GRASP_SELECT_STRESS_ID = "torm/TormGraspSelectStress-v0"
GRASP_SELECT_STRESS_KWARGS = {**GRASP_SELECT_HARD_KWARGS, "realism": "stress", "stress": 3.0}


def register_envs() -> None:
    """Register the torm envs with gymnasium (idempotent; called at import)."""
    registry = gymnasium.envs.registration.registry
    if PICK_ID not in registry:
        gymnasium.register(id=PICK_ID, entry_point="torm.env.pick_env:TormPickEnv", disable_env_checker=False,
                           max_episode_steps=PICK_MAX_EPISODE_STEPS)
    if GRASP_SELECT_ID not in registry:
        gymnasium.register(id=GRASP_SELECT_ID, entry_point="torm.env.grasp_select_env:TormGraspSelectEnv",
                           max_episode_steps=GRASP_SELECT_MAX_EPISODE_STEPS)
    if GRASP_SELECT_MEASURED_ID not in registry:
        gymnasium.register(id=GRASP_SELECT_MEASURED_ID, entry_point="torm.env.grasp_select_env:TormGraspSelectEnv",
                           max_episode_steps=GRASP_SELECT_MAX_EPISODE_STEPS, kwargs={"realism": "measured"})
    if GRASP_SELECT_HARD_ID not in registry:
        gymnasium.register(id=GRASP_SELECT_HARD_ID, entry_point="torm.env.grasp_select_env:TormGraspSelectEnv",
                           max_episode_steps=GRASP_SELECT_MAX_EPISODE_STEPS, kwargs=dict(GRASP_SELECT_HARD_KWARGS))
    if GRASP_SELECT_STRESS_ID not in registry:
        gymnasium.register(id=GRASP_SELECT_STRESS_ID, entry_point="torm.env.grasp_select_env:TormGraspSelectEnv",
                           max_episode_steps=GRASP_SELECT_MAX_EPISODE_STEPS, kwargs=dict(GRASP_SELECT_STRESS_KWARGS))


register_envs()

__all__ = ["GRASP_SELECT_HARD_ID", "GRASP_SELECT_HARD_KWARGS", "GRASP_SELECT_ID", "GRASP_SELECT_MAX_EPISODE_STEPS",
           "GRASP_SELECT_MEASURED_ID", "GRASP_SELECT_STRESS_ID", "GRASP_SELECT_STRESS_KWARGS", "PICK_ID",
           "PICK_MAX_EPISODE_STEPS", "register_envs"]
