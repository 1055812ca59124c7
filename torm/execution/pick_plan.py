"""Planning a pick: grasp -> TCP frame, the translation direction, IK along straight lines, and line timing.

Backend-agnostic (only an :class:`~torm.execution.ik.IKSolver`, a :class:`ToolFrame` and optionally a
:class:`~torm.execution.robot_collision.RobotCollisionChecker`). Units: m, rad, s; world frame (the table frame,
z up; the IK model holds the robot at its base pose in it).

Frames. A :class:`~torm.types.Grasp` has x = approach (into the object), y = closing axis, origin midway
between the pads with the fingertips at ``x = grasp.depth``. The robot's TCP frame (from its robot config)
has its own approach/closing axes and the fingertips at ``tip_approach + tcp_offset(width)`` along its approach
axis (the offset is 0 unless the pads move along the approach as they close), so ``T_world_tcp`` puts the TCP
approach axis on grasp x, the closing axis on grasp y and the TCP origin at
``grasp origin + (grasp.depth - tip_approach - tcp_offset(grasp.width)) * x``.

Motions. Every segment of a pick is a straight Cartesian line (position interpolated linearly, orientation
slerped) sampled every ``line_step`` m as IK waypoints, each residual checked (:class:`UnreachableError`
otherwise), each configuration checked for self/table collision; the free move from the start falls back to a
joint-space move when no straight line works. :func:`time_line` times a line with one minimum-jerk profile
along a cubic joint spline, slowed until the sampled joint velocities and accelerations respect
``speed_scale`` x the arm's limits.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from torm.errors import ConfigError, ExecutionError
from torm.execution.ik import IKConfig, IKSolver, UnreachableError
from torm.execution.pick_config import PickConfig
from torm.execution.robot_collision import RobotCollisionChecker
from torm.execution.trajectory import PEAK_VEL, min_jerk
from torm.types import Grasp

log = logging.getLogger(__name__)

_AXES = "xyz"


@dataclass(frozen=True)
class ToolFrame:
    """Where the TCP frame's axes point relative to the gripper (from the robot config's gripper geometry).

    Attributes:
        approach_axis: TCP axis from the palm towards the fingertips ("x", "y" or "z").
        closing_axis: TCP axis along which the pads move.
        tip_approach: fingertip position along the approach axis in the TCP frame (m), with the pads where
            ``tcp_offset`` is 0.
        max_opening: the gripper's stroke (m).
        tcp_offset: pairs (pad gap m, pad-centre position along the approach axis in the TCP frame m), gaps
            increasing: where the pads (and fingertips) sit along the approach at each opening, for grippers whose
            pads move along the approach as they close; empty = always 0.
    """

    approach_axis: str = "z"
    closing_axis: str = "y"
    tip_approach: float = 0.01875
    max_opening: float = 0.085
    tcp_offset: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.approach_axis not in _AXES or self.closing_axis not in _AXES or self.approach_axis == self.closing_axis:
            raise ConfigError(f"ToolFrame axes must be two different of x/y/z, got {self.approach_axis!r}, "
                              f"{self.closing_axis!r}")
        if not self.max_opening > 0:
            raise ConfigError("ToolFrame.max_opening must be positive (m)")
        gaps = [w for w, _ in self.tcp_offset]
        if any(b <= a for a, b in zip(gaps[:-1], gaps[1:], strict=True)):
            raise ConfigError("ToolFrame.tcp_offset gaps must be strictly increasing (m)")

    def offset_at(self, width: float) -> float:
        """Pad-centre position along the approach axis (m) at pad gap ``width`` (m), interpolated; 0 without a table."""
        if not self.tcp_offset:
            return 0.0
        return float(np.interp(width, [w for w, _ in self.tcp_offset], [o for _, o in self.tcp_offset]))

    @classmethod
    def from_robot_config(cls, robot_config: Any) -> ToolFrame:
        """From a ``sim.robots.config.RobotConfig`` (duck-typed: ``gripper.geometry``, optional
        ``gripper.tcp_offset``)."""
        g = robot_config.gripper.geometry
        table = tuple((float(w), float(o)) for w, o in getattr(robot_config.gripper, "tcp_offset", ()) or ())
        return cls(str(g.approach_axis), str(g.closing_axis), float(g.tip_approach), float(g.max_opening), table)


def make_ik_solver(robot_config: Any, config: IKConfig | None = None) -> IKSolver:
    """An :class:`IKSolver` on the robot-only model of a robot config (duck-typed: ``robot_spec()`` or ``mjcf``,
    ``arm.joints``, ``arm.tcp_site``); the base sits at the config's base pose, so targets are world poses."""
    from torm.execution.robot_model import robot_model_of

    return IKSolver(robot_model_of(robot_config), tuple(robot_config.arm.joints), robot_config.arm.tcp_site, config)


def grasp_to_tcp(grasp: Grasp, tool: ToolFrame, flip: bool = False) -> np.ndarray:
    """``T_world_tcp`` (4, 4) that executes ``grasp`` (see the module docstring); ``flip`` turns it 180 deg about
    the approach axis (the closing axis reversed), which a symmetric parallel gripper cannot tell apart."""
    Tg = grasp.T_world_grasp
    gx, gy = Tg[:3, 0], Tg[:3, 1] * (-1.0 if flip else 1.0)
    cols: dict[str, np.ndarray] = {tool.approach_axis: gx, tool.closing_axis: gy}
    other = next(a for a in _AXES if a not in cols)
    i = _AXES.index(other)
    cols[other] = np.cross(cols[_AXES[(i + 1) % 3]], cols[_AXES[(i + 2) % 3]])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([cols[a] for a in _AXES])
    # the fingertips sit at tip_approach + offset(width) along the TCP approach axis when the pads are at the grasp
    T[:3, 3] = Tg[:3, 3] + (grasp.depth - tool.tip_approach - tool.offset_at(grasp.width)) * gx
    return T


def free_directions(object_xy: np.ndarray, other_xy: np.ndarray | Sequence[Sequence[float]],
                    workspace: np.ndarray, distance: float = 0.20, n_directions: int = 16) -> np.ndarray:
    """Horizontal unit directions (K, 2) for the translation, best first: those whose target
    ``object_xy + distance * d`` lies inside ``workspace``, sorted by the target's clearance from the other
    objects (ties: by the distance to the workspace edges). Pass them to :func:`execute_pick`, which falls back
    to the next direction when one is unreachable.

    Args:
        object_xy: (2,) the picked object's position (m).
        other_xy: (K, 2) the other objects' positions (m); may be empty.
        workspace: (2, 2) or (2, 3) box [[x_min, y_min, ...], [x_max, y_max, ...]] the target must stay in (m).
        distance: translation length (m).
        n_directions: headings tried, evenly spaced.

    Raises:
        ExecutionError: when no heading keeps the target inside the workspace.
    """
    p = np.asarray(object_xy, float)[:2]
    others = np.asarray(other_xy, float).reshape(-1, 2) if len(other_xy) else np.zeros((0, 2))
    lo, hi = np.asarray(workspace, float)[0, :2], np.asarray(workspace, float)[1, :2]
    scored = []
    for a in np.arange(n_directions) * (2 * np.pi / n_directions):
        d = np.array([np.cos(a), np.sin(a)])
        tgt = p + distance * d
        margin = float(np.min(np.concatenate([tgt - lo, hi - tgt])))
        if margin < 0:
            continue
        clear = float(np.min(np.linalg.norm(others - tgt, axis=1))) if len(others) else np.inf
        scored.append(((round(min(clear, 10.0), 4), margin), d))
    if not scored:
        raise ExecutionError(f"no horizontal direction moves the object at {p.round(3).tolist()} by {distance} m "
                             f"while staying in the workspace {lo.tolist()}..{hi.tolist()}; enlarge the workspace "
                             "or shorten the translation")
    scored.sort(key=lambda kd: kd[0], reverse=True)
    return np.array([d for _, d in scored])


def free_direction(object_xy: np.ndarray, other_xy: np.ndarray | Sequence[Sequence[float]],
                   workspace: np.ndarray, distance: float = 0.20, n_directions: int = 16) -> np.ndarray:
    """The best direction (2,) of :func:`free_directions`: target inside ``workspace``, farthest from the others."""
    return free_directions(object_xy, other_xy, workspace, distance, n_directions)[0]


# ------------------------------------------------------------------------------------------------ planning
@dataclass
class PickPlan:
    """IK solutions for one grasp candidate (joint arrays in rad, poses (4, 4) in the world).

    ``poses`` holds the TCP poses ``pre_grasp``, ``grasp``, ``lift``, ``translate``, ``lower``, ``retreat``;
    ``q_pre_grasp`` (n,) are the pre-grasp joints; ``lines`` maps each straight segment (``approach``, ``lift``,
    ``translate``, ``lower``, ``retreat``; ``free`` when the move from the start is Cartesian; ``descend`` from the
    transit pose when one is used) to its (W, n) joint waypoints and its effective length (m); ``q_free`` (n,)
    is where the free move ends (the transit pose, else the pre-grasp); without a ``free`` line it is a
    minimum-jerk joint move. ``direction`` (2,) is the unit horizontal translation direction.
    """

    grasp: Grasp
    flipped: bool
    poses: dict[str, np.ndarray]
    q_pre_grasp: np.ndarray
    lines: dict[str, tuple[np.ndarray, float]]
    direction: np.ndarray
    q_free: np.ndarray


def _shift(T: np.ndarray, dp: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, 3] = T[:3, 3] + dp
    return out


#: A TCP rotation of theta rad counts as ``ROTATION_RADIUS * theta`` m of travel when sampling and timing lines (m).
ROTATION_RADIUS = 0.15


def _interp_pose(T0: np.ndarray, T1: np.ndarray, s: float, slerp: Slerp | None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = T0[:3, :3] if slerp is None else slerp([s]).as_matrix()[0]
    T[:3, 3] = T0[:3, 3] + s * (T1[:3, 3] - T0[:3, 3])
    return T


def _ik_line(ik: IKSolver, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray, cfg: PickConfig,
             what: str, collision: RobotCollisionChecker | None = None) -> tuple[np.ndarray, float]:
    """(W, n) IK waypoints along the straight line T0 -> T1 starting at ``q0``, and its effective length (m).

    The position moves on a straight line; the orientation is slerped from T0's to T1's (constant when they are
    equal). The effective length is the travel (m) plus ``ROTATION_RADIUS`` x the rotation angle (rad).
    Every waypoint is checked against ``collision`` (self/table) when given."""
    travel = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    rots = Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]]))
    angle = float((rots[0].inv() * rots[1]).magnitude())
    slerp = Slerp([0.0, 1.0], rots) if angle > 1e-6 else None
    length = travel + ROTATION_RADIUS * angle
    n = max(2, int(np.ceil(length / cfg.line_step)) + 1)
    qs = [np.asarray(q0, float)]
    q = qs[0]
    for s in np.linspace(0.0, 1.0, n)[1:]:
        q_new = ik.solve_or_raise(_interp_pose(T0, T1, s, slerp), q, what=f"{what} waypoint")
        jump = float(np.max(np.abs(q_new - q)))
        if jump > cfg.max_joint_step:
            raise UnreachableError(f"{what}: the straight line needs a joint jump of {jump:.2f} rad between "
                                   f"waypoints (IK branch switch or singularity); try another grasp")
        if collision is not None:
            collision.check(q_new, f"{what} waypoint")
        qs.append(q_new)
        q = q_new
    return np.array(qs), length


def _check_box(poses: dict[str, np.ndarray], box: tuple[np.ndarray, np.ndarray] | None) -> None:
    if box is None:
        return
    for name, T in poses.items():
        p = T[:3, 3]
        if np.any(p < box[0]) or np.any(p > box[1]):
            raise UnreachableError(f"{name} TCP position {p.round(3).tolist()} m is outside the safety box "
                                   f"{box[0].tolist()}..{box[1].tolist()}")


def _solve(ik: IKSolver, T: np.ndarray, q_seed: np.ndarray, what: str) -> np.ndarray:
    """IK for a free-move target (:meth:`IKSolver.solve_free`: seeded, polished, then random restarts; the same
    solve the start-up reach check uses, :mod:`sim.robots.reach`)."""
    res = ik.solve_free(T, q_seed)
    if not res.converged:
        raise UnreachableError(f"{what} at {T[:3, 3].round(4).tolist()} m is unreachable: IK residual "
                               f"{res.pos_err * 1000:.1f} mm / {np.degrees(res.rot_err):.1f} deg")
    return res.q


def _check_joint_move(collision: RobotCollisionChecker | None, q0: np.ndarray, q1: np.ndarray, what: str,
                      n: int = 20) -> None:
    """Check the straight joint-space path q0 -> q1 (what a minimum-jerk joint move follows) at ``n`` samples."""
    if collision is not None:
        collision.check_path(q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0), what)


def plan_pick(grasp: Grasp, ik: IKSolver, tool: ToolFrame, q_start: np.ndarray, translate_direction: np.ndarray,
              config: PickConfig | None = None, workspace_box: tuple[np.ndarray, np.ndarray] | None = None,
              flip: bool = False, collision: RobotCollisionChecker | None = None) -> PickPlan:
    """Solve IK for every pose of the pick of ``grasp`` from ``q_start`` (n,) rad.

    ``translate_direction`` (2,) or (3,) is the horizontal direction of the translation (normalised here).
    ``workspace_box`` (min (3,), max (3,)) m: TCP positions outside it make the grasp unreachable.
    ``collision``: when given, every configuration (free-move samples and line waypoints) is checked for
    self-collision and robot-table contact. A pre-grasp below ``config.transit_height`` is reached through a
    transit pose straight above it (joint move to the transit pose, then a vertical line down).

    Raises:
        UnreachableError: some pose has no converged IK solution, a line needs a joint jump, a configuration
            collides, or a pose is outside ``workspace_box``.
    """
    cfg = config or PickConfig()
    d = np.zeros(3)
    d[:2] = np.asarray(translate_direction, float)[:2]
    if not np.linalg.norm(d) > 1e-9:
        raise ConfigError("translate_direction must be a non-zero horizontal vector")
    d /= np.linalg.norm(d)
    T_grasp = grasp_to_tcp(grasp, tool, flip)
    approach = grasp.T_world_grasp[:3, 0]
    up = np.array([0.0, 0.0, 1.0])
    T_pre = _shift(T_grasp, -cfg.pre_grasp_distance * approach)
    T_lift = _shift(T_grasp, (cfg.lift_height + cfg.lift_margin) * up)
    T_trans = _shift(T_lift, cfg.translate_distance * d)
    T_lower = _shift(T_grasp, cfg.translate_distance * d + cfg.place_clearance * up)
    T_retreat = _shift(T_lower, -cfg.pre_grasp_distance * approach)
    poses = {"pre_grasp": T_pre, "grasp": T_grasp, "lift": T_lift, "translate": T_trans, "lower": T_lower,
             "retreat": T_retreat}
    use_transit = T_pre[2, 3] < cfg.transit_height - 1e-6
    if use_transit:
        poses["transit"] = _shift(T_pre, (cfg.transit_height - T_pre[2, 3]) * up)
    _check_box(poses, workspace_box)
    q_start = np.asarray(q_start, float)
    lines: dict[str, tuple[np.ndarray, float]] = {}
    T_free = poses.get("transit", T_pre)
    what = "transit pose" if use_transit else "pre-grasp"
    try:  # preferred: a straight Cartesian move (predictable sweep of the gripper)
        lines["free"] = _ik_line(ik, ik.forward(q_start), T_free, q_start, cfg, f"move to the {what}", collision)
        q_free = lines["free"][0][-1]
    except UnreachableError as exc:  # fall back to a joint-space move
        log.debug("Cartesian move to the %s failed (%s); using a joint move", what, exc)
        q_free = _solve(ik, T_free, q_start, what)
        if collision is not None:
            collision.check(q_free, what)
        _check_joint_move(collision, q_start, q_free, f"joint move to the {what}")
    if use_transit:
        lines["descend"] = _ik_line(ik, T_free, T_pre, q_free, cfg, "descend", collision)
        q_pre = lines["descend"][0][-1]
    else:
        q_pre = q_free
    lines["approach"] = _ik_line(ik, T_pre, T_grasp, q_pre, cfg, "approach", collision)
    lines["lift"] = _ik_line(ik, T_grasp, T_lift, lines["approach"][0][-1], cfg, "lift", collision)
    lines["translate"] = _ik_line(ik, T_lift, T_trans, lines["lift"][0][-1], cfg, "translate", collision)
    lines["lower"] = _ik_line(ik, T_trans, T_lower, lines["translate"][0][-1], cfg, "lower", collision)
    lines["retreat"] = _ik_line(ik, T_lower, T_retreat, lines["lower"][0][-1], cfg, "retreat", collision)
    return PickPlan(grasp=grasp, flipped=flip, poses=poses, q_pre_grasp=q_pre, lines=lines, direction=d[:2].copy(),
                    q_free=q_free)


def plan_first_reachable(candidates: Sequence[Grasp], ik: IKSolver, tool: ToolFrame, q_start: np.ndarray,
                         translate_direction: np.ndarray, config: PickConfig | None = None,
                         workspace_box: tuple[np.ndarray, np.ndarray] | None = None,
                         collision: RobotCollisionChecker | None = None,
                         ) -> tuple[PickPlan | None, int, list[tuple[int, str]]]:
    """Try candidates in the given (score) order; return (plan or None, index used or -1, [(index, why)] failed).

    ``translate_direction`` is one horizontal direction (2,) or alternatives (K, 2), best first (see
    :func:`free_directions`); for each candidate the first direction with a reachable plan is used.
    """
    cfg = config or PickConfig()
    dirs = np.atleast_2d(np.asarray(translate_direction, float))
    failed: list[tuple[int, str]] = []
    for i, g in enumerate(list(candidates)[: cfg.max_candidates]):
        flips = [False, True] if cfg.try_flipped else [False]
        if cfg.try_flipped:  # prefer the wrist orientation closer to the current one (less wrist rotation)
            R_now = ik.forward(q_start)[:3, :3]
            flips.sort(key=lambda f: -float(np.trace(R_now.T @ grasp_to_tcp(g, tool, f)[:3, :3])))
        reasons: list[str] = []
        for f in flips:
            for d in dirs:
                try:
                    return plan_pick(g, ik, tool, q_start, d, cfg, workspace_box, f, collision), i, failed
                except UnreachableError as exc:
                    if str(exc) not in reasons:
                        reasons.append(str(exc))
        failed.append((i, "; ".join(reasons)))
        log.info("grasp candidate %d unreachable: %s", i, reasons[0])
    return None, -1, failed


# ------------------------------------------------------------------------------------------------ timing
def _fd_ratio(t: np.ndarray, q: np.ndarray, q0: np.ndarray, vmax: np.ndarray, amax: np.ndarray) -> tuple[float, float]:
    """Largest finite-difference |qd|/vmax and |qdd|/amax of samples (t (T,), q (T, n)) starting at rest at q0."""
    q_all = np.vstack([q0[None], q])
    dt = np.diff(np.concatenate([[0.0], t]))[:, None]
    qd = np.diff(q_all, axis=0) / dt
    rv = float(np.max(np.abs(qd) / vmax))
    ra = 0.0
    if len(qd) > 1:
        qdd = np.diff(qd, axis=0) / (0.5 * (dt[1:] + dt[:-1]))
        ra = float(np.max(np.abs(qdd) / amax))
    return rv, ra


def time_line(q_wxn: np.ndarray, length: float, speed: float, qd_max: np.ndarray, qdd_max: np.ndarray,
              speed_scale: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Time a joint path along a straight Cartesian line: one min-jerk profile over a cubic spline through the
    (W, n) waypoints (equally spaced in Cartesian arc length ``length`` m), peak TCP speed ``speed`` m/s, slowed
    until sampled joint speeds/accelerations stay within 0.95 x ``speed_scale`` x the limits. Returns times (T,) s
    (first > 0) and joints (T, n) rad; the first waypoint is the start (not included)."""
    q_wxn = np.asarray(q_wxn, float)
    s_knots = np.linspace(0.0, 1.0, len(q_wxn))
    spline = CubicSpline(s_knots, q_wxn, axis=0) if len(q_wxn) > 2 else None
    vmax, amax = 0.95 * speed_scale * qd_max, 0.95 * speed_scale * qdd_max
    T = max(PEAK_VEL * length / speed, 0.1)
    for _ in range(20):
        n = max(1, int(np.ceil(T / dt - 1e-9)))
        t = np.linspace(T / n, T, n)
        s = min_jerk(t / T)
        q = spline(s) if spline is not None else q_wxn[0] + (q_wxn[-1] - q_wxn[0]) * s[:, None]
        q[-1] = q_wxn[-1]
        rv, ra = _fd_ratio(t, q, q_wxn[0], vmax, amax)
        if rv <= 1.0 and ra <= 1.0:
            return t, q
        T *= max(1.05, rv, np.sqrt(ra))
    raise ExecutionError(f"could not time a {length:.3f} m line within the joint limits; check the IK waypoints")
