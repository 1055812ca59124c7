"""The safety layer every backend goes through: joint limits, a TCP workspace box, speed limits.

:class:`SafeArm` wraps any :class:`~torm.backend.protocol.Arm` and refuses a trajectory before any
motion starts when it breaks a limit. What is checked (:meth:`SafetyLimits.check_trajectory`):

- **the whole path, not samples.** A trajectory is the piecewise-linear joint path from the arm's
  current position through every waypoint (what a trajectory controller does with position-only
  points, and how ``SimArm`` interpolates). Joint limits: every waypoint inside them means every
  point of every segment is (a linear segment stays inside a box). TCP box: proven for the continuous
  path with a Lipschitz bound when the arm's lever arms are known: the TCP moves at most
  ``sum_j r_j |dq_j|`` for a joint change ``dq``, where ``r_j`` (m/rad) bounds the distance from joint
  ``j``'s axis to the TCP (:func:`lever_arms_from_mujoco`: the chain length from joint ``j``'s anchor
  to the TCP, which no configuration can exceed). A segment whose two ends lie ``d_a`` and ``d_b``
  inside the box (distance to the nearest face) with ``d_a + d_b > sum_j r_j |dq_j|`` cannot leave the
  box anywhere; otherwise it is bisected. A segment that still cannot be proven once its bound is below
  ``path_resolution`` is refused: accepted paths are inside the box everywhere, and every path that
  keeps ``path_resolution / 2`` from the faces is accepted.
- Without lever arms (an arm that does not offer ``tcp_lever_arms()``, limits without
  ``tcp_lever_arms``) the segments are subdivided until each sub-step moves every joint by at most
  ``max_joint_step`` and the TCP by at most ``path_resolution`` (measured), and every sub-sample must
  lie ``path_resolution / 2`` inside the box: dense, but not a proof.
- Speeds and accelerations: finite differences of the waypoints (each linear segment moves at constant
  speed) against ``speed_scale`` x the limits (+ ``tolerance``).

Not checked: collisions of links other than the TCP with the table or objects, and the start
position's joint limits (it is where the arm is); the start TCP must be inside the box.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from torm.backend.protocol import Arm, ArmState
from torm.errors import ConfigError, ExecutionError

log = logging.getLogger(__name__)

#: Deepest bisection of one segment in the TCP-box proof (2^-40 of the segment: never reached in practice).
MAX_BISECTIONS = 40

FK = Callable[[np.ndarray], np.ndarray]


class SafetyError(ExecutionError):
    """A commanded motion violates the safety limits; nothing was sent to the robot."""


@dataclass(frozen=True)
class SafetyLimits:
    """Limits enforced on every backend.

    Attributes:
        q_min, q_max: joint position limits (rad), one per joint.
        qd_max: joint speed limits (rad/s).
        qdd_max: joint acceleration limits (rad/s^2).
        workspace_min, workspace_max: TCP box corners in the world frame (m).
        speed_scale: fraction of ``qd_max``/``qdd_max`` allowed, in (0, 1].
        tolerance: relative slack on velocity/acceleration checks of sampled trajectories.
        path_resolution: TCP distance (m) below which the path check stops refining (see the module docstring).
        tcp_lever_arms: ``r_j`` (m/rad) per joint bounding the TCP's distance from joint ``j``'s axis;
            empty: taken from the arm's ``tcp_lever_arms()`` when it has one.
        max_joint_step: largest joint change (rad) of a sub-step in the fallback check without lever arms.
    """

    q_min: tuple[float, ...]
    q_max: tuple[float, ...]
    qd_max: tuple[float, ...]
    qdd_max: tuple[float, ...]
    workspace_min: tuple[float, float, float] = (-1.2, -1.2, -0.005)
    workspace_max: tuple[float, float, float] = (1.2, 1.2, 1.6)
    speed_scale: float = 0.5
    tolerance: float = 0.05
    path_resolution: float = 0.002
    tcp_lever_arms: tuple[float, ...] = ()
    max_joint_step: float = 0.02

    def __post_init__(self) -> None:
        n = len(self.q_min)
        for name in ("q_max", "qd_max", "qdd_max"):
            if len(getattr(self, name)) != n:
                raise ConfigError(f"SafetyLimits.{name} has {len(getattr(self, name))} entries, q_min has {n}")
        if not np.all(np.isfinite(np.r_[self.q_min, self.q_max, self.qd_max, self.qdd_max, self.workspace_min,
                                        self.workspace_max, self.tcp_lever_arms])):
            raise ConfigError("SafetyLimits: every limit must be a finite number")
        if not np.all(np.asarray(self.q_max) > np.asarray(self.q_min)):
            raise ConfigError("SafetyLimits: every q_max must exceed q_min")
        if not (np.all(np.asarray(self.qd_max) > 0) and np.all(np.asarray(self.qdd_max) > 0)):
            raise ConfigError("SafetyLimits: qd_max and qdd_max must be positive")
        if not np.all(np.asarray(self.workspace_max) > np.asarray(self.workspace_min)):
            raise ConfigError("SafetyLimits: workspace_max must exceed workspace_min on every axis")
        if not 0.0 < self.speed_scale <= 1.0:
            raise ConfigError(f"SafetyLimits.speed_scale must be in (0, 1], got {self.speed_scale}")
        if not (self.path_resolution > 0 and self.max_joint_step > 0):
            raise ConfigError("SafetyLimits.path_resolution (m) and max_joint_step (rad) must be positive")
        if self.tcp_lever_arms and (len(self.tcp_lever_arms) != n or min(self.tcp_lever_arms) < 0):
            raise ConfigError(f"SafetyLimits.tcp_lever_arms needs {n} values >= 0 (m/rad), got {self.tcp_lever_arms}")

    def check_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray, q_start: np.ndarray, fk: FK,
                         lever_arms: np.ndarray | None = None) -> None:
        """Raise :class:`SafetyError` if the trajectory (times (T,) s, joints (T, n) rad) breaks a limit.

        ``fk(q) -> (4, 4)`` gives the TCP pose (world frame, m) used for the workspace-box check;
        ``lever_arms`` (n,) m/rad overrides ``tcp_lever_arms`` (see the module docstring).
        """
        times_s = np.asarray(times_s, float)
        q_txn = np.atleast_2d(np.asarray(q_txn, float))
        if len(times_s) != len(q_txn):
            raise SafetyError(f"trajectory has {len(times_s)} times but {len(q_txn)} waypoints")
        if not (np.all(np.isfinite(q_txn)) and np.all(np.isfinite(times_s))):
            raise SafetyError("trajectory contains NaN/inf; refusing to move")
        if len(times_s) and (times_s[0] <= 0 or np.any(np.diff(times_s) <= 0)):
            raise SafetyError("trajectory times must start after now (> 0 s) and increase strictly")
        lo, hi = np.asarray(self.q_min), np.asarray(self.q_max)
        bad = np.argwhere((q_txn < lo - 1e-9) | (q_txn > hi + 1e-9))
        if len(bad):
            i, j = bad[0]
            raise SafetyError(
                f"waypoint {i}: joint {j} = {q_txn[i, j]:.4f} rad outside [{lo[j]:.4f}, {hi[j]:.4f}]"
            )
        q_all = np.vstack([np.asarray(q_start, float)[None], q_txn])
        t_all = np.concatenate([[0.0], times_s])
        dt = np.diff(t_all)[:, None]
        qd = np.diff(q_all, axis=0) / dt
        slack = 1.0 + self.tolerance
        vmax = np.asarray(self.qd_max) * self.speed_scale * slack
        over = np.argwhere(np.abs(qd) > vmax)
        if len(over):
            i, j = over[0]
            raise SafetyError(
                f"segment {i}: joint {j} speed {abs(qd[i, j]):.3f} rad/s exceeds {vmax[j]:.3f} "
                f"(speed_scale {self.speed_scale}); slow the motion down"
            )
        if len(qd) > 1:
            qdd = np.diff(qd, axis=0) / (0.5 * (dt[1:] + dt[:-1]))
            amax = np.asarray(self.qdd_max) * self.speed_scale * slack
            over = np.argwhere(np.abs(qdd) > amax)
            if len(over):
                i, j = over[0]
                raise SafetyError(
                    f"waypoint {i}: joint {j} acceleration {abs(qdd[i, j]):.2f} rad/s^2 exceeds {amax[j]:.2f}"
                )
        r = lever_arms if lever_arms is not None else (np.asarray(self.tcp_lever_arms) if self.tcp_lever_arms
                                                      else None)
        self.check_path_in_box(q_all, fk, r)

    # -- the TCP box along the continuous path -------------------------------------------------------
    def _margin(self, p: np.ndarray) -> float:
        """Distance (m) from ``p`` to the nearest face of the box; negative outside."""
        return float(min(np.min(p - np.asarray(self.workspace_min)), np.min(np.asarray(self.workspace_max) - p)))

    def _box_error(self, where: str, p: np.ndarray) -> SafetyError:
        return SafetyError(f"{where}: TCP at {np.round(p, 4).tolist()} m leaves the workspace box "
                           f"{list(self.workspace_min)}..{list(self.workspace_max)}")

    def check_path_in_box(self, q_path: np.ndarray, fk: FK, lever_arms: np.ndarray | None = None) -> None:
        """Refuse the piecewise-linear joint path ``q_path`` (K, n) rad unless the TCP stays inside the box.

        With ``lever_arms`` (n,) m/rad the proof of the module docstring; without, the dense fallback.
        """
        q_path = np.atleast_2d(np.asarray(q_path, float))
        p = np.array([fk(q)[:3, 3] for q in q_path])
        margins = np.array([self._margin(x) for x in p])
        if margins[0] < 0:
            raise SafetyError(f"the arm is outside the workspace box now (TCP at {np.round(p[0], 4).tolist()} m, "
                              f"box {list(self.workspace_min)}..{list(self.workspace_max)}); move it back in "
                              "by hand or widen the box")
        bad = np.flatnonzero(margins < 0)
        if len(bad):
            raise self._box_error(f"waypoint {bad[0] - 1}", p[bad[0]])
        for k in range(len(q_path) - 1):
            where = "the move to waypoint 0" if k == 0 else f"segment {k - 1}->{k}"
            if lever_arms is not None:
                self._prove_segment(q_path[k], q_path[k + 1], margins[k], margins[k + 1], fk,
                                    np.asarray(lever_arms, float), where)
            else:
                self._sample_segment(q_path[k], q_path[k + 1], p[k], p[k + 1], fk, where)

    def _prove_segment(self, qa: np.ndarray, qb: np.ndarray, da: float, db: float, fk: FK, r: np.ndarray,
                       where: str) -> None:
        stack = [(qa, qb, da, db, 0)]
        while stack:
            qa, qb, da, db, depth = stack.pop()
            bound = float(r @ np.abs(qb - qa))  # largest TCP displacement along this piece (m)
            if da + db > bound:
                continue  # every point is within bound*s of qa or bound*(1-s) of qb: inside
            if bound <= self.path_resolution or depth >= MAX_BISECTIONS:
                pm = fk(0.5 * (qa + qb))[:3, 3]
                raise SafetyError(f"{where}: the TCP path comes within {self.path_resolution * 1000:.1f} mm of the "
                                  f"workspace box near {np.round(pm, 4).tolist()} m and cannot be proven to stay "
                                  f"inside {list(self.workspace_min)}..{list(self.workspace_max)}")
            qm = 0.5 * (qa + qb)
            pm = fk(qm)[:3, 3]
            dm = self._margin(pm)
            if dm < 0:
                raise self._box_error(f"{where} (between waypoints)", pm)
            stack += [(qa, qm, da, dm, depth + 1), (qm, qb, dm, db, depth + 1)]

    def _sample_segment(self, qa: np.ndarray, qb: np.ndarray, pa: np.ndarray, pb: np.ndarray, fk: FK,
                        where: str) -> None:
        half = 0.5 * self.path_resolution
        n0 = max(1, int(np.ceil(np.max(np.abs(qb - qa)) / self.max_joint_step)))
        stack = [(qa + (qb - qa) * i / n0, qa + (qb - qa) * (i + 1) / n0, None, None, 0) for i in range(n0)]
        stack[0] = (stack[0][0], stack[0][1], pa, None, 0)
        stack[-1] = (stack[-1][0], stack[-1][1], stack[-1][2], pb, 0)
        while stack:
            q0, q1, p0, p1, depth = stack.pop()
            p0 = fk(q0)[:3, 3] if p0 is None else p0
            p1 = fk(q1)[:3, 3] if p1 is None else p1
            for x in (p0, p1):
                if self._margin(x) < half:
                    raise self._box_error(f"{where} (between waypoints, {half * 1000:.1f} mm margin)", x)
            if np.linalg.norm(p1 - p0) > self.path_resolution and depth < MAX_BISECTIONS:
                qm = 0.5 * (q0 + q1)
                pm = fk(qm)[:3, 3]
                stack += [(q0, qm, p0, pm, depth + 1), (qm, q1, pm, p1, depth + 1)]


def lever_arms_from_mujoco(model, joint_names: tuple[str, ...], site: str) -> np.ndarray | None:
    """``r_j`` (m/rad) per arm joint bounding the distance from joint ``j``'s axis to ``site`` in any configuration.

    For hinge joints in a serial chain the distance between the anchors of two consecutive joints (and
    from the last anchor to the site) does not depend on the configuration (each anchor lies on its own
    rotation axis), so ``r_j`` = the sum of those distances from joint ``j`` on is a bound for every
    configuration (triangle inequality). Returns None when the model is not such a chain (a slide joint,
    a joint out of chain order, another joint between the last arm joint and the site).
    """
    import mujoco

    ids = [int(model.joint(j).id) for j in joint_names]
    if any(model.jnt_type[i] != mujoco.mjtJoint.mjJNT_HINGE for i in ids):
        return None
    sid = int(model.site(site).id)
    chain = [int(model.jnt_bodyid[i]) for i in ids] + [int(model.site_bodyid[sid])]
    for k in range(len(ids)):
        later = set(ids[k + 1:])  # joints allowed on the way from joint k's body down to the next link
        b = chain[k + 1]
        while b != chain[k]:  # the next joint (or the site) must hang below joint k's body ...
            if b <= 0:
                return None
            own = set(range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]))
            if not own <= later:  # ... with no joint of another kinematic branch in between
                return None
            b = int(model.body_parentid[b])
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    pts = np.vstack([data.xanchor[ids], data.site_xpos[model.site(site).id][None]])
    links = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return np.cumsum(links[::-1])[::-1].copy()


class SafeArm:
    """An :class:`Arm` whose every trajectory is checked against :class:`SafetyLimits` before it is sent."""

    def __init__(self, arm: Arm, limits: SafetyLimits) -> None:
        if len(limits.q_min) != len(arm.joint_names):
            raise ConfigError(
                f"safety limits cover {len(limits.q_min)} joints but the arm has {len(arm.joint_names)}"
            )
        self.inner = arm
        self.limits = limits
        self.joint_names = arm.joint_names
        self._lever_arms: np.ndarray | bool | None = None

    def state(self) -> ArmState:
        return self.inner.state()

    def forward_kinematics(self, q: np.ndarray) -> np.ndarray:
        return self.inner.forward_kinematics(q)

    def lever_arms(self) -> np.ndarray | None:
        """``r_j`` (m/rad) used by the path check: the limits' ``tcp_lever_arms`` or the arm's ``tcp_lever_arms()``."""
        if self.limits.tcp_lever_arms:
            return np.asarray(self.limits.tcp_lever_arms, float)
        if self._lever_arms is None and hasattr(self.inner, "tcp_lever_arms"):
            r = self.inner.tcp_lever_arms()
            self._lever_arms = np.asarray(r, float) if r is not None else False
        return self._lever_arms if self._lever_arms is not False else None

    def check(self, times_s: np.ndarray, q_txn: np.ndarray) -> None:
        """Raise :class:`SafetyError` if the trajectory from the current position breaks a limit (nothing moves)."""
        self.limits.check_trajectory(times_s, q_txn, self.inner.state().q, self.inner.forward_kinematics,
                                     self.lever_arms())

    def follow_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray) -> ArmState:
        self.check(times_s, q_txn)
        log.debug("trajectory of %d points over %.2f s accepted", len(times_s), float(times_s[-1]))
        return self.inner.follow_trajectory(times_s, q_txn)

    def stop(self) -> None:
        self.inner.stop()
