"""The full pick on the simulated robot: success on a glass cylinder, a gripper that never closes, unreachable
candidates and a physics blow-up. The pick runs blind; the judge (sim/judge.py) scores it with the paper's success
test from the physics."""

from __future__ import annotations

import numpy as np
import pytest

from sim.backend import SimBackend
from sim.judge import PickJudge
from sim.world import build_world
from torm.execution.ik import IKConfig
from torm.execution.pick import (
    PickConfig,
    ToolFrame,
    execute_pick,
    free_direction,
    make_ik_solver,
    plan_first_reachable,
)
from torm.execution.success import Outcome
from torm.types import Grasp

TOP_DOWN = np.column_stack([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # approach -z, closing along y


@pytest.fixture(scope="module")
def backend():
    return SimBackend(build_world("rw1", seed=0))


@pytest.fixture(autouse=True)
def _reset(backend):
    backend.reset()


def _grasp_at(p, width=0.08, object_id=1) -> Grasp:
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = TOP_DOWN, p
    return Grasp(G, width=width, score=1.0, object_id=object_id, depth=0.01875)


def _cylinder_grasp(backend) -> Grasp:
    """Top-down grasp from the true pose: centre at 60 % of the cylinder's height, closing horizontally."""
    obj = backend.world.objects[0]
    T = obj.T_world_obj
    h = float(obj.mesh.bounds[1, 2])
    return _grasp_at(T[:3, 3] + [0.0, 0.0, 0.6 * h], object_id=obj.instance_id)


def judged_pick(backend, candidates, direction, **kw):
    """``execute_pick`` watched by the judge: the judged result (the loop's own when nothing moved)."""
    judge = PickJudge(backend)
    try:
        res = execute_pick(backend, candidates, direction, observer=judge, **kw)
    finally:
        judge.close()
    return judge.verdicts.get(id(res), res)


def _direction(backend) -> np.ndarray:
    p = backend.ground_truth.object_poses()[1][:2, 3]
    return free_direction(p, [], backend.world.workspace_bounds)


def test_pick_of_the_glass_cylinder_succeeds_after_skipping_unreachable_candidates(backend):
    assert backend.world.objects[0].name == "cylinder" and backend.world.objects[0].mass > 0.6
    rest = backend.ground_truth.object_poses()[1][:3, 3]
    far = _grasp_at([3.0, 0.0, 0.3])  # outside the safety box and the arm's reach
    edge = _grasp_at([0.98, 0.58, 0.05])  # inside the box, beyond the arm's reach
    direction = _direction(backend)
    res = judged_pick(backend, [far, edge, _cylinder_grasp(backend)], direction)
    assert res.outcome is Outcome.SUCCESS, res.as_dict()
    assert res.candidate_index == 2 and [i for i, _ in res.unreachable] == [0, 1]
    j = res.judgement
    assert j.lift >= 0.25 - 0.01 and j.translation >= 0.19 and abs(j.final_height_change) < 0.005
    assert j.slip_lift < 0.005 and j.slip_translate < 0.005
    assert len(res.trace.lift) > 50 and len(res.trace.translate) > 50  # sampled during the motion
    assert res.gripper_width is not None and 0.055 < res.gripper_width < 0.065  # stalled on the 60 mm glass
    # the glass really ended 20 cm away, upright, back on the table
    T = backend.ground_truth.object_poses()[1]
    assert abs(np.linalg.norm((T[:3, 3] - rest)[:2]) - 0.20) < 0.01 and T[2, 2] > 0.99
    assert np.dot(T[:2, 3] - rest[:2], direction) > 0.19
    names = [p.name for p in res.phases]
    assert names == ["open", "pre_grasp", "approach", "close", "lift", "translate", "lower", "release", "retreat"]
    assert res.sim_time > 5.0 and res.as_dict()["outcome"] == "success"


def test_gripper_that_never_closes_slips(backend, monkeypatch):
    g = backend.gripper
    real_move = g.move

    def open_only(width_m, speed_mps=0.1, force_n=100.0):
        return real_move(max(width_m, g.width()), speed_mps, force_n)  # ignores every closing command

    monkeypatch.setattr(g, "move", open_only)
    rest = backend.ground_truth.object_poses()[1][:3, 3]
    res = judged_pick(backend, [_cylinder_grasp(backend)], _direction(backend))
    assert res.outcome is Outcome.SLIPPED and res.loop_outcome is Outcome.SLIPPED, res.as_dict()
    assert res.target_id == 1 and res.judgement.lift < 0.01  # the glass stayed on the table
    assert np.linalg.norm(backend.ground_truth.object_poses()[1][:3, 3] - rest) < 0.01
    assert "translate" not in [p.name for p in res.phases]  # aborted after the failed lift


def test_only_unreachable_candidates(backend):
    q0 = backend.arm.state().q
    t0 = backend.clock.now()
    res = execute_pick(backend, [_grasp_at([0.98, 0.58, 0.05]), _grasp_at([3.0, 0.0, 0.3])], np.array([0.0, -1.0]))
    assert res.outcome is Outcome.UNREACHABLE and len(res.unreachable) == 2
    assert "unreachable" in res.unreachable[0][1] and "safety box" in res.unreachable[1][1]
    assert backend.clock.now() == t0 and np.array_equal(backend.arm.state().q, q0)  # nothing moved
    assert execute_pick(backend, [], np.array([0.0, 1.0])).outcome is Outcome.NO_GRASP


def test_plan_prefers_the_wrist_orientation_closer_to_the_current_one(backend):
    rc = backend.robot_config
    ik, tool = make_ik_solver(rc, IKConfig()), ToolFrame.from_robot_config(rc)
    g = _cylinder_grasp(backend)
    q0 = backend.arm.state().q
    plan, idx, failed = plan_first_reachable([g], ik, tool, q0, np.array([0.0, 1.0]), PickConfig())
    assert idx == 0 and not failed
    flipped = Grasp(g.T_world_grasp @ np.diag([1.0, -1.0, -1.0, 1.0]), g.width, g.score, g.object_id, depth=g.depth)
    plan_f, _, _ = plan_first_reachable([flipped], ik, tool, q0, np.array([0.0, 1.0]), PickConfig())
    assert plan.flipped != plan_f.flipped  # both resolve to the same wrist orientation
    assert np.allclose(plan.poses["grasp"], plan_f.poses["grasp"], atol=1e-9)
    # an unreachable translation direction falls through to the next one
    box = (np.array([-0.2, -0.3, -0.005]), np.array([1.0, 0.6, 1.0]))
    assert g.T_world_grasp[1, 3] - 0.2 < -0.3 < g.T_world_grasp[1, 3]  # moving by -y leaves this box
    p2, _, _ = plan_first_reachable([g], ik, tool, q0, np.array([[0.0, -1.0], [0.0, 1.0]]), PickConfig(), box)
    assert np.allclose(p2.direction, [0.0, 1.0])
    # every line is a straight Cartesian segment: waypoints lie on it within the IK tolerance
    for name in ("approach", "lift", "translate", "lower", "retreat"):
        qs, length = plan.lines[name]
        ps = np.array([ik.forward(q)[:3, 3] for q in qs])
        a, b = ps[0], ps[-1]
        u = (b - a) / np.linalg.norm(b - a)
        off = np.linalg.norm((ps - a) - np.outer((ps - a) @ u, u), axis=1)
        assert off.max() < 2e-3, name
        assert abs(np.linalg.norm(b - a) - length) < 3e-3


def test_physics_blow_up_is_reported(backend):
    def explode(t: float) -> None:
        if t > 1.0:
            backend.world.data.qvel[-1] = 1e12  # an object suddenly at absurd speed

    backend.add_step_callback(explode)
    try:
        res = judged_pick(backend, [_cylinder_grasp(backend)], _direction(backend))
    finally:
        backend.remove_step_callback(explode)
    assert res.outcome is Outcome.PHYSICS, res.as_dict()


def test_fingers_driven_into_the_glass_is_a_collision(backend):
    """A side approach with the jaws opened only 3 cm shoves the 6 cm glass: the robot cannot tell and goes on;
    the judge saw the glass move before the fingers closed."""
    T = backend.ground_truth.object_poses()[1]
    G = np.eye(4)
    G[:3, 3] = T[:3, 3] + [0.0, 0.0, 0.09]  # approach along +x, closing along y, near the top (a lower side
    # grasp would drive the wrist into the table: the robot collision check rejects it)
    res = judged_pick(backend, [Grasp(G, width=0.02, score=1.0, object_id=1, depth=0.01875)], np.array([0.0, 1.0]))
    assert res.outcome is Outcome.COLLISION and res.target_id == 1, res.as_dict()
    assert "moved before the gripper closed" in res.message
    assert np.linalg.norm(backend.ground_truth.object_poses()[1][:3, 3] - T[:3, 3]) > 0.01


class _RealLike:
    """The simulated robot seen as the real one: no ground truth, no per-step hook."""

    name = "real_like"

    def __init__(self, sim: SimBackend) -> None:
        self.arm, self.gripper, self.clock, self.robot_config = sim.arm, sim.gripper, sim.clock, sim.robot_config
        self.ground_truth = None

    def capture(self, n_views=None):
        raise AssertionError("this fake real-robot backend has no camera; the test must not capture")

    def close(self) -> None:
        pass


def test_without_ground_truth_success_comes_from_the_gripper_and_the_operator(backend):
    real = _RealLike(backend)
    rest = backend.ground_truth.object_poses()[1][:3, 3]
    asked = []
    res = execute_pick(real, [_cylinder_grasp(backend)], _direction(backend),
                       operator_confirm=lambda r: asked.append(r.outcome) or False)
    assert asked == [Outcome.SUCCESS]  # the gripper held the glass through lift and translation
    assert res.outcome is Outcome.NOT_RELEASED and "operator" in res.message  # ... but the operator said no
    assert res.trace is None and res.judgement is None
    assert np.linalg.norm((backend.ground_truth.object_poses()[1][:3, 3] - rest)[:2]) > 0.19
    backend.reset()
    res = execute_pick(real, [_cylinder_grasp(backend)], _direction(backend), operator_confirm=lambda r: True)
    assert res.outcome is Outcome.SUCCESS


def test_without_ground_truth_an_empty_gripper_is_a_slip(backend, monkeypatch):
    g = backend.gripper
    real_move = g.move
    monkeypatch.setattr(g, "move", lambda width_m, speed_mps=0.1, force_n=100.0: real_move(
        max(width_m, g.width()), speed_mps, force_n))  # never closes
    res = execute_pick(_RealLike(backend), [_cylinder_grasp(backend)], _direction(backend))
    assert res.outcome is Outcome.SLIPPED and "lift" in res.message


def test_a_motion_the_safety_layer_refuses_is_a_safety_stop(backend, monkeypatch):
    """A SafetyError (joint, speed or box limit: nothing was sent) is its own outcome, not ``other``."""
    from torm.backend import SafetyError

    def refuse(*args, **kwargs):
        raise SafetyError("joint 'j2' target 3.2 rad outside [-3.1, 3.1]")

    monkeypatch.setattr(backend.arm, "follow_trajectory", refuse)
    res = judged_pick(backend, [_cylinder_grasp(backend)], _direction(backend))
    assert res.outcome is Outcome.SAFETY_STOP and "SafetyError" in res.message, res.as_dict()
