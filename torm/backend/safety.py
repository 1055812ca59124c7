"""The safety layer every backend goes through: joint limits, a TCP workspace box, speed limits.

:class:`SafeArm` wraps any :class:`~torm.backend.protocol.Arm` and refuses a trajectory before any
motion starts when a waypoint leaves the joint limits, the TCP leaves the workspace box, or the
finite-difference joint velocity/acceleration exceeds ``speed_scale`` x the limits.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from torm.backend.protocol import Arm, ArmState
from torm.errors import ConfigError, ExecutionError

log = logging.getLogger(__name__)


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
    """

    q_min: tuple[float, ...]
    q_max: tuple[float, ...]
    qd_max: tuple[float, ...]
    qdd_max: tuple[float, ...]
    workspace_min: tuple[float, float, float] = (-1.2, -1.2, -0.005)
    workspace_max: tuple[float, float, float] = (1.2, 1.2, 1.6)
    speed_scale: float = 0.5
    tolerance: float = 0.05

    def __post_init__(self) -> None:
        n = len(self.q_min)
        for name in ("q_max", "qd_max", "qdd_max"):
            if len(getattr(self, name)) != n:
                raise ConfigError(f"SafetyLimits.{name} has {len(getattr(self, name))} entries, q_min has {n}")
        if not np.all(np.asarray(self.q_max) > np.asarray(self.q_min)):
            raise ConfigError("SafetyLimits: every q_max must exceed q_min")
        if not (np.all(np.asarray(self.qd_max) > 0) and np.all(np.asarray(self.qdd_max) > 0)):
            raise ConfigError("SafetyLimits: qd_max and qdd_max must be positive")
        if not np.all(np.asarray(self.workspace_max) > np.asarray(self.workspace_min)):
            raise ConfigError("SafetyLimits: workspace_max must exceed workspace_min on every axis")
        if not 0.0 < self.speed_scale <= 1.0:
            raise ConfigError(f"SafetyLimits.speed_scale must be in (0, 1], got {self.speed_scale}")

    def check_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray, q_start: np.ndarray, fk) -> None:
        """Raise :class:`SafetyError` if the trajectory (times (T,) s, joints (T, n) rad) breaks a limit.

        ``fk(q) -> (4, 4)`` gives the TCP pose used for the workspace-box check.
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
        wmin, wmax = np.asarray(self.workspace_min), np.asarray(self.workspace_max)
        stride = max(1, len(q_txn) // 50)
        for i in list(range(0, len(q_txn), stride)) + [len(q_txn) - 1]:
            p = fk(q_txn[i])[:3, 3]
            if np.any(p < wmin) or np.any(p > wmax):
                raise SafetyError(
                    f"waypoint {i}: TCP at {np.round(p, 4).tolist()} m leaves the workspace box "
                    f"{list(wmin)}..{list(wmax)}"
                )


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

    def state(self) -> ArmState:
        return self.inner.state()

    def forward_kinematics(self, q: np.ndarray) -> np.ndarray:
        return self.inner.forward_kinematics(q)

    def follow_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray) -> ArmState:
        self.limits.check_trajectory(times_s, q_txn, self.inner.state().q, self.inner.forward_kinematics)
        log.debug("trajectory of %d points over %.2f s accepted", len(times_s), float(times_s[-1]))
        return self.inner.follow_trajectory(times_s, q_txn)

    def stop(self) -> None:
        self.inner.stop()
