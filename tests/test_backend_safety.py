"""Minimum-jerk trajectories and the safety layer."""

from __future__ import annotations

import numpy as np
import pytest

from torm.backend import ArmState, SafeArm, SafetyError, SafetyLimits
from torm.errors import ConfigError
from torm.execution.trajectory import (
    PEAK_ACC,
    PEAK_VEL,
    chain_waypoints,
    min_jerk,
    min_jerk_duration,
    min_jerk_segment,
)


def test_min_jerk_boundary_conditions_and_peaks():
    u = np.linspace(0, 1, 200001)
    s = min_jerk(u)
    assert s[0] == 0 and np.isclose(s[-1], 1)
    du = u[1] - u[0]
    ds = np.gradient(s, du)
    dds = np.gradient(ds, du)
    assert abs(ds[0]) < 1e-4 and abs(ds[-1]) < 1e-4  # rest to rest
    assert np.isclose(ds.max(), PEAK_VEL, rtol=1e-4)
    assert np.isclose(np.abs(dds).max(), PEAK_ACC, rtol=1e-3)


def test_duration_respects_limits():
    q0 = np.zeros(3)
    q1 = np.array([1.0, -0.2, 0.05])
    vmax = np.array([1.0, 1.0, 1.0])
    amax = np.array([100.0, 100.0, 100.0])
    T = min_jerk_duration(q0, q1, vmax, amax, speed_scale=0.5)
    assert np.isclose(T, PEAK_VEL * 1.0 / 0.5)  # velocity-bound on joint 0
    t, q = min_jerk_segment(q0, q1, T, 1e-3)
    v = np.diff(np.vstack([q0, q]), axis=0) / 1e-3
    assert np.all(np.abs(v) <= 0.5 * vmax + 1e-3)
    assert np.allclose(q[-1], q1) and np.isclose(t[-1], T)
    # An acceleration-bound move.
    T2 = min_jerk_duration(q0, q1, vmax * 100, amax * 0 + 1.0)
    assert np.isclose(T2, np.sqrt(PEAK_ACC * 1.0 / 1.0))


class _FakeArm:
    joint_names = ("a", "b")

    def __init__(self) -> None:
        self.q = np.zeros(2)
        self.sent = []

    def state(self) -> ArmState:
        return ArmState(self.q.copy(), np.zeros(2), self.forward_kinematics(self.q), 0.0)

    def forward_kinematics(self, q):
        T = np.eye(4)
        T[:3, 3] = [q[0], q[1], 0.5]
        return T

    def follow_trajectory(self, times_s, q_txn):
        self.sent.append((times_s, q_txn))
        self.q = q_txn[-1]
        return self.state()

    def stop(self):
        pass


def _limits(**kw):
    base = dict(q_min=(-1.0, -1.0), q_max=(1.0, 1.0), qd_max=(1.0, 1.0), qdd_max=(5.0, 5.0),
                workspace_min=(-0.6, -0.6, 0.0), workspace_max=(0.6, 0.6, 1.0), speed_scale=0.5)
    base.update(kw)
    return SafetyLimits(**base)


def test_safe_arm_accepts_planned_motion_and_rejects_violations():
    arm = _FakeArm()
    safe = SafeArm(arm, _limits())
    lim = safe.limits
    t, q = chain_waypoints(np.zeros(2), np.array([[0.5, 0.2], [0.0, -0.4]]), lim.qd_max, lim.qdd_max, 0.5, dt=0.01)
    safe.follow_trajectory(t, q)
    assert len(arm.sent) == 1
    with pytest.raises(SafetyError, match="outside"):
        safe.follow_trajectory(np.array([1.0]), np.array([[1.5, 0.0]]))
    with pytest.raises(SafetyError, match="speed"):
        safe.follow_trajectory(np.array([0.01]), np.array([[0.3, 0.0]]))
    with pytest.raises(SafetyError, match="workspace box"):
        # Inside joint limits but the fake FK puts the TCP outside the 0.6 m box.
        safe.follow_trajectory(*chain_waypoints(arm.q, np.array([[0.9, 0.0]]), lim.qd_max, lim.qdd_max, 0.5))
    with pytest.raises(SafetyError, match="NaN"):
        safe.follow_trajectory(np.array([1.0]), np.array([[np.nan, 0.0]]))
    assert len(arm.sent) == 1  # nothing else reached the robot


def test_safety_limits_validation():
    with pytest.raises(ConfigError, match="speed_scale"):
        _limits(speed_scale=1.5)
    with pytest.raises(ConfigError, match="q_max has 1"):
        _limits(q_max=(1.0,))
    with pytest.raises(ConfigError, match="joints"):
        SafeArm(_FakeArm(), _limits(q_min=(-1.0,), q_max=(1.0,), qd_max=(1.0,), qdd_max=(1.0,)))
