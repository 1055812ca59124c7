"""IK on the robot-only model, grasp -> TCP frame conversion, translation direction and line timing."""

from __future__ import annotations

import numpy as np
import pytest

from sim.robots.config import load_robot_config
from torm.errors import ExecutionError
from torm.execution.ik import UnreachableError
from torm.execution.pick import ToolFrame, free_direction, grasp_to_tcp, make_ik_solver, time_line
from torm.types import Grasp


@pytest.fixture(scope="module")
def robot():
    return load_robot_config("inovo_2f85")


@pytest.fixture(scope="module")
def ik(robot):
    return make_ik_solver(robot)


def _pose(p, R=None):
    T = np.eye(4)
    T[:3, :3] = np.diag([-1.0, 1.0, -1.0]) if R is None else R  # TCP pointing down, closing along world y
    T[:3, 3] = p
    return T


def test_ik_reaches_a_pose_above_the_workspace(robot, ik):
    home = robot.arm.home_q
    target = _pose([0.6, 0.1, 0.30])
    res = ik.solve(target, home)
    assert res.converged
    assert res.pos_err < 1e-3 and res.rot_err < 1e-2
    T = ik.forward(res.q)  # independent check of the residual through forward kinematics
    assert np.linalg.norm(T[:3, 3] - target[:3, 3]) < 1e-3
    assert np.allclose(T[:3, :3], target[:3, :3], atol=2e-2)
    assert np.all(res.q >= robot.arm.lower) and np.all(res.q <= robot.arm.upper)


def test_ik_fails_cleanly_for_a_point_3m_away(robot, ik):
    far = _pose([3.0, 0.0, 0.3])
    res = ik.solve(far, robot.arm.home_q)
    assert not res.converged and res.pos_err > 1.0
    with pytest.raises(UnreachableError, match="unreachable"):
        ik.solve_or_raise(far, robot.arm.home_q, what="far target")


def test_grasp_frame_maps_onto_the_tcp_axes(robot):
    tool = ToolFrame.from_robot_config(robot)
    assert (tool.approach_axis, tool.closing_axis) == ("z", "y")
    R = np.column_stack([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # top-down, closing along y
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = R, [0.5, 0.0, 0.06]
    g = Grasp(G, width=0.08, score=1.0, object_id=1, depth=tool.tip_approach + 0.01)
    T = grasp_to_tcp(g, tool)
    assert np.allclose(T[:3, 2], [0, 0, -1]) and np.allclose(T[:3, 1], [0, 1, 0])
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    assert np.allclose(T[:3, 3], [0.5, 0.0, 0.05])  # 1 cm deeper along the approach (down)
    # The home pose is exactly this orientation (robot.yaml: approach down, closing along world y).
    assert np.allclose(make_ik_solver(robot).forward(robot.arm.home_q)[:3, :3], T[:3, :3], atol=1e-3)
    Tf = grasp_to_tcp(g, tool, flip=True)
    assert np.allclose(Tf[:3, 2], T[:3, 2]) and np.allclose(Tf[:3, 1], -T[:3, 1])
    assert np.isclose(np.linalg.det(Tf[:3, :3]), 1.0)


def test_free_direction_avoids_neighbours_and_stays_in_the_workspace():
    ws = np.array([[0.33, -0.22], [0.77, 0.22]])
    d = free_direction([0.55, 0.0], [[0.55, 0.15]], ws)
    assert np.isclose(np.linalg.norm(d), 1.0)
    assert d[1] < -0.9  # away from the neighbour at +y
    d = free_direction([0.40, 0.0], [], ws)  # near the x_min edge: must go towards +x
    tgt = np.array([0.40, 0.0]) + 0.2 * d
    assert np.all(tgt >= ws[0]) and np.all(tgt <= ws[1])
    with pytest.raises(ExecutionError, match="workspace"):
        free_direction([0.55, 0.0], [], np.array([[0.5, -0.05], [0.6, 0.05]]))


def test_line_timing_respects_joint_limits():
    q = np.linspace([0.0, 0.0], [1.0, -0.5], 11)
    vmax, amax = np.array([1.0, 1.0]), np.array([2.0, 2.0])
    t, qs = time_line(q, length=0.2, speed=10.0, qd_max=vmax, qdd_max=amax, speed_scale=0.5, dt=0.01)
    assert np.allclose(qs[-1], q[-1]) and t[0] > 0 and np.all(np.diff(t) > 0)
    qd = np.diff(np.vstack([q[0], qs]), axis=0) / np.diff(np.concatenate([[0], t]))[:, None]
    assert np.max(np.abs(qd)) <= 0.5 * 1.0 + 1e-9  # a 10 m/s request is slowed to the joint limit
    assert np.max(np.abs(qd[:, 0])) > 0.4  # ... but not much more than needed


def test_robot_collision_checker_flags_folded_wrists_and_the_table(robot):
    from torm.execution.pick import PickConfig, plan_first_reachable
    from torm.execution.robot_collision import RobotCollisionChecker

    chk = RobotCollisionChecker.from_robot_config(robot, table_height=0.0)
    assert chk.collisions(robot.arm.home_q) == []
    folded = np.array([-1.79, -1.1, 1.41, -0.26, 2.14, 1.42])  # wrist folded back onto the forearm, low
    hits = chk.collisions(folded)
    pairs = {frozenset(h[:2]) for h in hits}
    assert frozenset({"link4", "link6"}) in pairs and any("table" in p for p in pairs)
    with pytest.raises(UnreachableError, match="collide"):
        chk.check(folded, "folded")
    # a horizontal side grasp 5 cm above the table needs the wrist in the table: rejected at plan time
    G = np.eye(4)
    G[:3, 3] = [0.5, -0.15, 0.05]
    g = Grasp(G, width=0.07, score=1.0, object_id=1, depth=0.01875)
    ik = make_ik_solver(robot)
    tool = ToolFrame.from_robot_config(robot)
    plan, idx, failed = plan_first_reachable([g], ik, tool, robot.arm.home_q, np.array([0.0, 1.0]), PickConfig(),
                                             collision=chk)
    assert plan is None and idx == -1 and "table" in failed[0][1]
    plan, _, _ = plan_first_reachable([g], ik, tool, robot.arm.home_q, np.array([0.0, 1.0]), PickConfig())
    assert plan is not None  # without the check IK alone accepts it


def test_ik_solutions_stay_inside_the_joint_limits_by_the_margin():
    """A target whose exact solution puts joint 2 on its limit: the solution stays IK_LIMIT_MARGIN_RAD / 2 inside
    (the safety layer refuses any joint beyond its limit, by any amount), and the residual says how far the TCP is."""
    from torm.execution.ik import IK_LIMIT_MARGIN_RAD, IKSolver

    rcfg = load_robot_config("inovo_2f85")
    ik = IKSolver(rcfg.robot_model(), tuple(rcfg.arm.joints), rcfg.arm.tcp_site)
    lo, hi = ik.joint_ranges()
    q_edge = np.array(rcfg.arm.home_q, float)
    q_edge[1] = hi[1]  # on the upper limit of j2
    target = ik.forward(q_edge)
    res = ik.solve(target, np.array(rcfg.arm.home_q, float))
    assert np.all(res.q <= hi - 0.5 * IK_LIMIT_MARGIN_RAD + 1e-12) and np.all(res.q >= lo + 0.5 * IK_LIMIT_MARGIN_RAD)
    np.testing.assert_allclose(ik.forward(res.q)[:3, 3], target[:3, 3], atol=res.pos_err + 1e-9)
