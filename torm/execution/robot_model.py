"""The robot-only MuJoCo model of a robot config, for IK, FK and plan-time collision checks.

Duck-typed so ``torm`` does not import ``sim``: a config with ``robot_spec()`` (``sim.robots.config.RobotConfig``:
arm + gripper composed, base at its ``base_pose`` in the world) is asked for it; a config with only an ``mjcf``
path is loaded from that file (base at the world origin). Frames: world, metres, radians.
"""

from __future__ import annotations

from typing import Any

import mujoco

from torm.errors import ConfigError, SceneError


def robot_spec_of(robot_config: Any) -> mujoco.MjSpec:
    """A fresh MjSpec of the robot alone (base at its base pose in the world)."""
    make = getattr(robot_config, "robot_spec", None)
    if callable(make):
        return make()
    mjcf = getattr(robot_config, "mjcf", None)
    if mjcf is None:
        raise ConfigError("the robot config has neither robot_spec() nor an mjcf path")
    try:
        return mujoco.MjSpec.from_file(str(mjcf))
    except ValueError as exc:
        raise SceneError(f"robot MJCF {mjcf} cannot be parsed: {exc}") from exc


def robot_model_of(robot_config: Any) -> mujoco.MjModel:
    """The compiled robot-only model (see :func:`robot_spec_of`)."""
    make = getattr(robot_config, "robot_model", None)
    if callable(make):
        return make()
    try:
        return robot_spec_of(robot_config).compile()
    except ValueError as exc:
        raise SceneError(f"the robot model does not compile: {exc}") from exc
