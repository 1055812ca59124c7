"""Plan-time collision check of arm configurations: self-collision and robot-vs-table, on a robot-only model.

IK knows only joint limits, so it happily returns a configuration that folds the wrist into the forearm or
drives a link into the table; position control then jams the arm there. :class:`RobotCollisionChecker`
rejects such configurations before anything moves. It uses the robot-only model (its base at the robot config's
base pose, :mod:`torm.execution.robot_model`) plus a table plane at ``table_height`` (world frame, z up, m); the
finger joints stay at their initial (open) values.
Objects are not included: avoiding them is the grasp planner's job, and hitting them is judged by the pick.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from torm.errors import ConfigError
from torm.execution.ik import UnreachableError

TABLE_GEOM = "__plan_table"


class RobotCollisionChecker:
    """Finds penetrating contacts of the robot with itself or the table for arm joints ``q`` (n,) rad.

    Args:
        mjcf: the robot MJCF file (base at the world origin) or a robot-only MjSpec (consumed: the table is added).
        joint_names: the arm joints, in the order of ``q``.
        table_height: z of the table top (m); None for no table.
        tolerance: penetration depth (m) below which a contact is ignored (touching is fine).
    """

    def __init__(self, mjcf: str | Path | mujoco.MjSpec, joint_names: tuple[str, ...],
                 table_height: float | None = 0.0, tolerance: float = 1e-3) -> None:
        spec = mjcf if isinstance(mjcf, mujoco.MjSpec) else mujoco.MjSpec.from_file(str(mjcf))
        if table_height is not None:
            spec.worldbody.add_geom(name=TABLE_GEOM, type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1],
                                    pos=[0, 0, float(table_height)], contype=1, conaffinity=1)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        missing = [j for j in joint_names if mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, j) < 0]
        if missing:
            raise ConfigError(f"robot model has no joint(s) {missing}")
        self._qadr = np.array([self.model.jnt_qposadr[self.model.joint(j).id] for j in joint_names])
        self.tolerance = float(tolerance)

    @classmethod
    def from_robot_config(cls, robot_config: Any, table_height: float | None = 0.0,
                          tolerance: float = 1e-3) -> RobotCollisionChecker:
        """From a ``sim.robots.config.RobotConfig`` (duck-typed: ``robot_spec()`` or ``mjcf``, ``arm.joints``)."""
        from torm.execution.robot_model import robot_spec_of

        return cls(robot_spec_of(robot_config), tuple(robot_config.arm.joints), table_height, tolerance)

    def _body(self, geom: int) -> str:
        if self.model.geom(geom).name == TABLE_GEOM:
            return "table"
        return self.model.body(self.model.geom_bodyid[geom]).name or f"body{self.model.geom_bodyid[geom]}"

    def collisions(self, q: np.ndarray) -> list[tuple[str, str, float]]:
        """(body a, body b, penetration m) for every contact deeper than ``tolerance`` at joints ``q``."""
        d = self.data
        d.qpos[self._qadr] = np.asarray(q, float)
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_collision(self.model, d)
        out = []
        for c in d.contact[: d.ncon]:
            if c.dist < -self.tolerance:
                out.append((self._body(c.geom1), self._body(c.geom2), float(-c.dist)))
        return out

    def check(self, q: np.ndarray, what: str = "configuration") -> None:
        """Raise :class:`UnreachableError` naming the colliding bodies when ``q`` collides."""
        hits = self.collisions(q)
        if hits:
            desc = ", ".join(f"{a}-{b} {pen * 1000:.1f} mm" for a, b, pen in hits[:3])
            raise UnreachableError(f"{what}: the robot would collide with itself or the table ({desc}); "
                                   "try another grasp")

    def check_path(self, q_wxn: np.ndarray, what: str = "path", skip_first: bool = True) -> None:
        """:meth:`check` every configuration of a (W, n) joint path (the first one optionally skipped)."""
        for i, q in enumerate(np.atleast_2d(q_wxn)):
            if i == 0 and skip_first:
                continue
            self.check(q, f"{what} waypoint {i}")
