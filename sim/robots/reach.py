"""Start-up reach check: which share of the workspace box the arm reaches with the gripper pointing down.

A grid of TCP positions over the workspace box (``n_xy`` x ``n_xy`` in x, y at each of ``heights`` above the
table: the grasp height and the lifted height of a pick) is solved with the pick's IK (mink, the robot-only
model with the base at ``base_pose``), TCP approach axis pointing straight down and the closing axis along
world x or y (either counts). A point is reached when the IK residual is within the IK tolerances; a point
farther from the first joint than the arm's total link length (an upper bound on its reach, for an all-hinge
arm) is unreachable without solving. An arm
that reaches too little is refused with a message naming ``base_pose``, the key that moves it. Frames: world
(table frame), metres, radians. Results are cached per process (robot config, box, heights).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from torm.errors import SceneError
from torm.execution.ik import IKConfig, IKSolver

if TYPE_CHECKING:
    from sim.robots.config import RobotConfig

log = logging.getLogger(__name__)

#: Random restarts per point after the seeded solves failed (execution's solve_free; fewer than execution's
#: RESTARTS because an arm out of reach pays them at every unreachable point of the grid).
REACH_RESTARTS = 4
#: TCP heights above the table checked (m): a grasp on a ~10 cm object, and the same lifted by the pick's 25 cm.
DEFAULT_HEIGHTS = (0.05, 0.30)
_AXES = "xyz"


@dataclass(frozen=True)
class ReachReport:
    """What the arm reaches.

    Attributes:
        robot: robot name.
        share: reached points / tested points (0..1).
        points_nx3: (N, 3) tested TCP positions (world, m).
        reached: (N,) whether each was reached.
        base_position: (3,) the arm base in the world (m).
        bounds: (2, 3) the workspace box tested (m).
    """

    robot: str
    share: float
    points_nx3: np.ndarray
    reached: np.ndarray
    base_position: tuple[float, float, float]
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]

    def summary(self) -> str:
        lo, hi = np.asarray(self.bounds)
        s = (f"robot {self.robot!r} reaches {self.share * 100:.0f} % of the workspace box x {lo[0]:.2f}..{hi[0]:.2f}, "
             f"y {lo[1]:.2f}..{hi[1]:.2f} m with the gripper pointing down "
             f"({int(self.reached.sum())} of {len(self.reached)} points")
        missed = self.points_nx3[~self.reached]
        if len(missed):
            s += ", e.g. not " + ", ".join(str(np.round(p, 3).tolist()) for p in missed[:2])
        return s + ")"

    def advice(self, where: str = "its robot.yaml") -> str:
        """What to change, from where the base stands: inside the box (move it out past an edge), near it (the
        arm is too short: closer), or far (closer)."""
        lo, hi = np.asarray(self.bounds)
        centre = 0.5 * (lo + hi)
        base = np.asarray(self.base_position)
        d = float(np.linalg.norm((centre - base)[:2]))
        now = (f"move the arm base with `base_pose` in {where} (now position {list(self.base_position)}, "
               f"{d:.2f} m from the box centre {np.round(centre[:2], 3).tolist()})")
        if np.all(base[:2] >= lo[:2]) and np.all(base[:2] <= hi[:2]):
            return (f"{now}: the base stands inside the workspace box, where a downward-pointing gripper cannot "
                    "reach the points around it; put it outside one edge of the box, facing it, or lower "
                    "`reach_min_share` if the arm is meant to cover only part of the box")
        missed = self.points_nx3[~self.reached]
        far = float(np.mean(np.linalg.norm((missed - base)[:, :2], axis=1))) if len(missed) else 0.0
        return (f"{now}: the missed points lie {far:.2f} m from the base on average; move it closer to the box, or "
                "lower `reach_min_share` in the robot YAML if the arm is meant to cover only part of the box")


def _down_rotation(approach_axis: str, closing_axis: str, closing_world: np.ndarray) -> np.ndarray:
    cols = {approach_axis: np.array([0.0, 0.0, -1.0]), closing_axis: np.asarray(closing_world, float)}
    other = next(a for a in _AXES if a not in cols)
    i = _AXES.index(other)
    cols[other] = np.cross(cols[_AXES[(i + 1) % 3]], cols[_AXES[(i + 2) % 3]])
    return np.column_stack([cols[a] for a in _AXES])


def grid_points(bounds_2x3: np.ndarray, table_height: float, heights=DEFAULT_HEIGHTS, n_xy: int = 4) -> np.ndarray:
    """(n_xy * n_xy * len(heights), 3) TCP positions over the box, corners included (m)."""
    lo, hi = np.asarray(bounds_2x3, float)
    xs, ys = np.linspace(lo[0], hi[0], n_xy), np.linspace(lo[1], hi[1], n_xy)
    return np.array([[x, y, table_height + h] for h in heights for x in xs for y in ys])


def max_reach(model: mujoco.MjModel, rcfg: RobotConfig) -> tuple[np.ndarray, float]:
    """(first joint anchor (3,) m, upper bound on the TCP's distance from it m): the summed distances between
    consecutive joint anchors and from the last one to the TCP, each fixed in a link; inf unless every arm joint
    is a hinge."""
    ids = rcfg.resolve(model)
    d = mujoco.MjData(model)
    mujoco.mj_kinematics(model, d)
    anchors = d.xanchor[ids.arm_joints]
    if not all(int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_HINGE) for j in ids.arm_joints):
        return anchors[0], float("inf")
    chain = np.vstack([anchors, d.site_xpos[ids.tcp_site][None]])
    return anchors[0], float(np.sum(np.linalg.norm(np.diff(chain, axis=0), axis=1)))


@functools.lru_cache(maxsize=16)
def _cached(rcfg: RobotConfig, bounds: tuple, table_height: float, heights: tuple, n_xy: int) -> ReachReport:
    model = rcfg.robot_model()
    origin, reach = max_reach(model, rcfg)
    ik = IKSolver(model, tuple(rcfg.arm.joints), rcfg.arm.tcp_site, IKConfig())  # the pick's IK settings
    g = rcfg.gripper.geometry
    rots = [_down_rotation(g.approach_axis, g.closing_axis, c) for c in ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0])]
    pts = grid_points(np.asarray(bounds), table_height, heights, n_xy)
    home = rcfg.arm.home_q
    reached = np.zeros(len(pts), bool)
    last_ok = home
    for i, p in enumerate(pts):
        if np.linalg.norm(p - origin) > reach + 1e-3:
            continue
        # execution's free-move solve (IKSolver.solve_free): from home in either closing direction, then from the
        # last reached point's joints (a neighbour), and last with execution's random restarts
        tries = [(home, R, 0) for R in rots] + ([(last_ok, rots[0], 0)] if last_ok is not home else [])
        tries += [(home, rots[0], REACH_RESTARTS)]
        for seed, R, restarts in tries:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, p
            res = ik.solve_free(T, seed, restarts=restarts, seed=i)
            if res.converged:
                reached[i], last_ok = True, res.q
                break
    return ReachReport(rcfg.name, float(reached.mean()), pts, reached,
                       tuple(float(v) for v in rcfg.base_pose.position), bounds)


def reach_report(rcfg: RobotConfig, bounds_2x3: np.ndarray, table_height: float = 0.0,
                 heights: tuple[float, ...] = DEFAULT_HEIGHTS, n_xy: int = 4) -> ReachReport:
    """Which share of the workspace box ``bounds_2x3`` ((2, 3) m, world) the arm reaches (see the module doc)."""
    b = np.asarray(bounds_2x3, float)
    bounds = (tuple(float(v) for v in b[0]), tuple(float(v) for v in b[1]))
    return _cached(rcfg, bounds, float(table_height), tuple(float(h) for h in heights), int(n_xy))


def base_in_box(base_xyz: tuple[float, float, float], bounds_2x3: np.ndarray) -> str:
    """Where the arm base's footprint overlaps the workspace box in x-y: ``""`` when it does not, else a description
    (``"x 0.33..0.77 m and y -0.22..0.22 m contain it"``). ``base_xyz``: (3,) m world; ``bounds_2x3``: (2, 3) m."""
    lo, hi = np.asarray(bounds_2x3, float)
    x, y = float(base_xyz[0]), float(base_xyz[1])
    if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]:
        return f"x {lo[0]:.2f}..{hi[0]:.2f} m and y {lo[1]:.2f}..{hi[1]:.2f} m contain it"
    return ""


def require_reach(rcfg: RobotConfig, bounds_2x3: np.ndarray, min_share: float, table_height: float = 0.0,
                  where: str | None = None) -> ReachReport:
    """:func:`reach_report`, raising SceneError naming ``base_pose`` when the share is below ``min_share``."""
    rep = reach_report(rcfg, bounds_2x3, table_height)
    where = where or f"the robot.yaml of {rcfg.name!r}"
    overlap = base_in_box(rep.base_position, bounds_2x3)
    if overlap:
        log.warning("robot %s: its base at (%.2f, %.2f) m lies inside the workspace box (%s); objects placed there "
                    "would stand in the arm's base; move base_pose in %s", rcfg.name, rep.base_position[0],
                    rep.base_position[1], overlap, where)
    if rep.share < min_share:
        raise SceneError(f"{rep.summary()}, below the {min_share * 100:.0f} % needed; {rep.advice(where)}")
    if rep.share < 1.0:
        log.warning("%s; picks there will be unreachable: %s", rep.summary(), rep.advice(where))
    else:
        log.info("%s", rep.summary())
    return rep


def check_transit_height(rcfg: RobotConfig, bounds_2x3: np.ndarray, transit_height: float, table_height: float = 0.0,
                         key: str = "pick.transit_height") -> float:
    """Refuse a transit height (m, world z) at which the arm reaches no point above the workspace box.

    The pick moves above each pre-grasp at ``transit_height`` (:class:`torm.execution.pick_config.PickConfig`); at a
    height the arm cannot reach pointing down every object would be reported "unreachable" instead of the
    configuration being wrong. Checks a 3 x 3 grid over the box at that height (:func:`reach_report`); 0 disables
    the transit and passes.

    Returns:
        the share of the grid reached (1.0 when ``transit_height`` is 0).

    Raises:
        ConfigError: naming ``key``, the value, the arm's reach and the fix, when no grid point is reached.
    """
    from torm.errors import ConfigError

    if transit_height <= 0:
        return 1.0
    b = np.asarray(bounds_2x3, float)
    origin, reach = max_reach(rcfg.robot_model(), rcfg)
    rep = reach_report(rcfg, b, table_height, heights=(float(transit_height) - table_height,), n_xy=3)
    if rep.share == 0.0:
        centre = np.array([0.5 * (b[0, 0] + b[1, 0]), 0.5 * (b[0, 1] + b[1, 1])])
        horiz = float(np.linalg.norm(centre - origin[:2]))
        top = origin[2] + np.sqrt(max(reach**2 - horiz**2, 0.0)) if np.isfinite(reach) else float("inf")
        raise ConfigError(
            f"{key}={transit_height:g} m: the {rcfg.name} arm reaches no point above the workspace box at that height "
            f"with the gripper pointing down (its links stretch at most to z = {top:.2f} m over the box centre); "
            f"give a lower {key} (default 0.25) or 0 to move straight to each pre-grasp")
    if rep.share < 1.0:
        log.warning("%s=%.3f m: the arm reaches %.0f %% of the workspace box at that height; picks below the "
                    "unreached part will be unreachable", key, transit_height, 100 * rep.share)
    return rep.share
