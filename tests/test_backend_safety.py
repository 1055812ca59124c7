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


class _BowlArm(_FakeArm):
    """Two joints; the TCP height is a parabola in joint 0: z = 0.45 q0^2 - 0.1 + 0.5 q1 (m).

    Lever arms (m/rad) for |q0| <= 1: |dp/dq0| = |(0.3, 0, 0.9 q0)| <= 0.95, |dp/dq1| = 0.5.
    """

    LEVER_ARMS = (0.95, 0.5)

    def forward_kinematics(self, q):
        T = np.eye(4)
        T[:3, 3] = [0.3 * q[0], 0.0, 0.45 * q[0] ** 2 - 0.1 + 0.5 * q[1]]
        return T


@pytest.mark.parametrize("lever_arms", [_BowlArm.LEVER_ARMS, ()], ids=["proof", "dense-fallback"])
def test_path_dipping_below_the_table_between_waypoints_is_refused(lever_arms):
    arm = _BowlArm()
    arm.q = np.array([-0.6, 0.0])  # TCP 6.2 cm above the table
    safe = SafeArm(arm, _limits(workspace_min=(-0.6, -0.6, 0.0), tcp_lever_arms=lever_arms))
    end = np.array([[0.6, 0.0]])  # also 6.2 cm above; the straight joint path between dips to -10 cm
    assert arm.forward_kinematics(end[0])[2, 3] > 0.06
    with pytest.raises(SafetyError, match="between waypoints"):
        safe.follow_trajectory(np.array([3.0]), end)
    # the waypoints-only check the layer used to do would have let it through
    assert all(arm.forward_kinematics(q)[2, 3] > 0 for q in (arm.q, end[0]))
    # lifting joint 1 on the way keeps the whole path above the table: accepted
    times = np.linspace(0.5, 6.0, 12)
    up = np.stack([np.interp(times, [0, 3, 6], [-0.6, 0.0, 0.6]), np.interp(times, [0, 3, 6], [0.0, 0.3, 0.0])], 1)
    safe.follow_trajectory(times, up)
    assert len(arm.sent) == 1 and arm.sent[0][1][0, 1] != 0.0


def test_path_proof_accepts_only_paths_inside_and_every_path_with_margin():
    """Random segments near the table: an accepted one is inside everywhere (2001 samples); a refused one
    comes within path_resolution / 2 of the table (so every path keeping that margin is accepted)."""
    rng = np.random.default_rng(0)
    lim = _limits(workspace_min=(-0.6, -0.6, 0.0), tcp_lever_arms=_BowlArm.LEVER_ARMS, path_resolution=0.002)
    fk = _BowlArm().forward_kinematics
    n_acc = n_ref = 0
    for _ in range(300):
        qa, qb = rng.uniform([-0.8, 0.05], [0.8, 0.4]), rng.uniform([-0.8, 0.05], [0.8, 0.4])
        qa[1] = max(qa[1], 0.21 - 0.9 * qa[0] ** 2 + 0.002)  # both ends inside the box
        qb[1] = max(qb[1], 0.21 - 0.9 * qb[0] ** 2 + 0.002)
        if np.max(np.abs(qb - qa)) < 1e-3:
            continue
        qs = qa + (qb - qa) * np.linspace(0, 1, 2001)[:, None]
        z = 0.45 * qs[:, 0] ** 2 - 0.1 + 0.5 * qs[:, 1]  # _BowlArm's TCP height, vectorised
        try:
            lim.check_path_in_box(np.stack([qa, qb]), fk, np.asarray(_BowlArm.LEVER_ARMS))
            accepted = True
        except SafetyError:
            accepted = False
        if accepted:
            assert z.min() >= 0.0
            n_acc += 1
        else:
            assert z.min() < lim.path_resolution / 2
            n_ref += 1
    assert n_acc > 50 and n_ref > 20  # both cases were exercised


def test_path_check_starts_at_the_current_position():
    arm = _BowlArm()
    arm.q = np.array([0.0, 0.0])  # TCP at z = -0.1: outside the box already
    safe = SafeArm(arm, _limits(workspace_min=(-0.6, -0.6, 0.0), tcp_lever_arms=_BowlArm.LEVER_ARMS))
    with pytest.raises(SafetyError, match="outside the workspace box now"):
        safe.follow_trajectory(np.array([2.0]), np.array([[0.0, 0.4]]))


def test_lever_arms_bound_the_inovo_jacobian():
    """lever_arms_from_mujoco bounds every column of the TCP Jacobian over random configurations."""
    import mujoco

    from sim.robots.config import load_robot_config
    from torm.backend.safety import lever_arms_from_mujoco

    rcfg = load_robot_config("inovo_2f85")
    m = mujoco.MjModel.from_xml_path(str(rcfg.mjcf))
    r = lever_arms_from_mujoco(m, tuple(rcfg.arm.joints), rcfg.arm.tcp_site)
    assert r is not None and np.all(np.diff(r) <= 1e-12)  # the chain shortens towards the wrist
    d = mujoco.MjData(m)
    qadr = [m.jnt_qposadr[m.joint(j).id] for j in rcfg.arm.joints]
    dadr = [m.jnt_dofadr[m.joint(j).id] for j in rcfg.arm.joints]
    sid = m.site(rcfg.arm.tcp_site).id
    rng = np.random.default_rng(1)
    worst = np.zeros(len(r))
    for _ in range(300):
        d.qpos[qadr] = rng.uniform(-np.pi, np.pi, len(r))
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        jac = np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jac, None, sid)
        worst = np.maximum(worst, np.linalg.norm(jac[:, dadr], axis=0))
    assert np.all(worst <= r + 1e-9) and worst[0] > 0.5 * r[0]  # a bound, and not a vacuous one
    # not a serial hinge chain: no bound (the path check then falls back to dense sampling)
    assert lever_arms_from_mujoco(m, tuple(rcfg.arm.joints)[::-1], rcfg.arm.tcp_site) is None  # out of order
    assert lever_arms_from_mujoco(m, (*rcfg.arm.joints, "gripper_left_finger"), rcfg.arm.tcp_site) is None
