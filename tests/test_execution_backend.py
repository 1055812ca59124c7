"""The simulated backend: trajectory tracking, the safety layer, the gripper and physics blow-up detection."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from sim.backend import SimBackend
from sim.world import build_world
from torm.backend import Backend, SafeArm, SafetyError
from torm.execution.errors import PhysicsError
from torm.execution.trajectory import chain_waypoints


@pytest.fixture(scope="module")
def backend():
    b = SimBackend(build_world("rw1", seed=0))
    yield b
    b.close()


@pytest.fixture(autouse=True)
def _reset(backend):
    backend.reset()


def test_backend_implements_the_protocol(backend):
    assert isinstance(backend, Backend)
    assert isinstance(backend.arm, SafeArm)
    assert backend.ground_truth.table_height() == 0.0
    poses = backend.ground_truth.object_poses()
    assert set(poses) == {1} and poses[1].shape == (4, 4)
    if hasattr(backend.ground_truth, "object_meshes"):
        mesh = backend.ground_truth.object_meshes()[1]
        lo, hi = mesh.verts_vx3.min(axis=0), mesh.verts_vx3.max(axis=0)
        assert np.allclose((lo + hi)[:2] / 2, poses[1][:2, 3], atol=2e-3) and abs(hi[2] - 0.1) < 2e-3
    st = backend.arm.state()
    assert np.allclose(st.T_world_tcp[:3, 3], [0.5, 0.0, 0.35], atol=2e-3)  # home
    assert np.allclose(backend.arm.forward_kinematics(st.q), st.T_world_tcp, atol=1e-6)


def test_follow_trajectory_tracks_a_min_jerk_move(backend):
    st0 = backend.arm.state()
    q1 = st0.q + np.array([0.3, -0.2, 0.25, 0.1, -0.2, 0.4])
    lim = backend.limits
    t, q = chain_waypoints(st0.q, [q1], lim.qd_max, lim.qdd_max, 0.5, 0.01)
    t_sim0 = backend.clock.now()
    seen = []
    cb = backend.add_step_callback(lambda now: seen.append(backend.arm.state().q.copy()))
    try:
        st = backend.arm.follow_trajectory(t, q)
    finally:
        backend.remove_step_callback(cb)
    target = backend.arm.forward_kinematics(q1)[:3, 3]
    assert np.linalg.norm(st.T_world_tcp[:3, 3] - target) < 3e-3
    assert np.linalg.norm(st.T_world_tcp[:3, 3] - st0.T_world_tcp[:3, 3]) > 0.1  # it really moved
    assert backend.clock.now() - t_sim0 >= t[-1] - 1e-9
    # tracking error during the motion stays small: compare the sampled joints to the commanded profile
    per_sample = int(round(0.01 / backend.config.control_dt))  # control ticks per trajectory sample
    seen_q = np.array(seen)[per_sample - 1 :: per_sample][: len(q)]
    assert len(seen_q) == len(q)
    lag = np.max(np.abs(seen_q - q))
    assert lag < 0.03, lag  # a position servo lags ~15 ms behind a 0.9 rad/s move


def test_safety_refuses_an_out_of_box_target_with_nothing_moved(backend):
    q_bad = backend.arm.state().q.copy()
    q_bad[1] -= 0.8  # leans the arm forward: the TCP goes into the table top (below z = -0.005)
    assert backend.arm.forward_kinematics(q_bad)[2, 3] < -0.005
    lim = backend.limits
    t, q = chain_waypoints(backend.arm.state().q, [q_bad], lim.qd_max, lim.qdd_max, 0.5, 0.01)
    q_before, time_before = backend.arm.state().q, backend.clock.now()
    with pytest.raises(SafetyError, match="workspace box"):
        backend.arm.follow_trajectory(t, q)
    assert backend.clock.now() == time_before
    assert np.array_equal(backend.arm.state().q, q_before)
    with pytest.raises(SafetyError, match="speed"):  # too fast: the same move in 0.1 s
        backend.arm.follow_trajectory(np.array([0.1]), q_bad[None])
    assert backend.clock.now() == time_before


def test_gripper_width_map_and_object_detection(backend):
    g = backend.gripper
    st = g.move(0.04, speed_mps=0.1, force_n=100)
    assert abs(st.width - 0.04) < 2e-3 and not st.object_detected
    st = g.move(0.0, speed_mps=0.15, force_n=100)
    assert st.width < 2e-3 and not st.object_detected and st.command == 255
    st = g.move(g.max_width, speed_mps=0.15)
    assert st.width > 0.08 and not st.object_detected


def test_physics_blow_up_raises(backend):
    backend.world.data.qvel[-1] = np.nan  # MuJoCo flags it (mjWARN_BADQVEL) and resets; the backend must abort
    with pytest.raises(PhysicsError, match="BADQVEL|NaN"):
        backend.clock.sleep(0.01)


def test_exploding_contact_force_raises():
    from sim.backend import SimBackendConfig

    # a 0.7 kg cylinder resting on the table presses with ~7 N: a 1 N "explosion" threshold must trip
    b = SimBackend(build_world("rw1", seed=0), SimBackendConfig(max_contact_force=1.0))
    with pytest.raises(PhysicsError, match="contact force"):
        b.clock.sleep(0.02)
    ok = SimBackend(build_world("rw1", seed=0))
    ok.clock.sleep(0.02)  # the default threshold leaves a resting object alone


def test_capture_through_the_backend_sees_the_glass():
    from sim.cameras.rig import CameraRigConfig

    b = SimBackend(build_world("rw1", seed=0), camera_config=CameraRigConfig(scale=0.1, channels=("mask",)))
    try:
        cap = b.capture(2)
        assert len(cap.views) == 2 and cap.object_ids == (1,)
        masks = [v.mask for v in cap.views]
        assert all(m is not None and (m == 1).sum() > 5 for m in masks)  # the glass cylinder is seen
    finally:
        b.close()


def _outcome(fn) -> str:
    try:
        fn()
    except PhysicsError as exc:
        return str(exc).split(" at t =")[0]
    return "ok"


def test_the_per_tick_health_check_agrees_with_its_reference_form():
    from sim.backend import SimBackendConfig

    for cfg in (SimBackendConfig(), SimBackendConfig(max_contact_force=1.0), SimBackendConfig(max_object_speed=0.01)):
        b = SimBackend(build_world("rw1", seed=0), cfg)
        sim, d = b._sim, b.world.data
        mujoco.mj_step(b.world.model, d, nstep=20)  # the object rests on the table: contacts are active
        assert d.nefc > 0
        assert _outcome(sim.check) == _outcome(sim.check_reference)
        lin = sim._obj_lin[0]
        for index, value in ((lin[0], 0.3), (lin[2], -0.02), (lin[1], np.nan), (lin[0], np.inf)):
            saved = d.qvel[index]
            d.qvel[index] = value
            want = _outcome(sim.check_reference)
            assert _outcome(sim.check) == want, (cfg, index, value)
            d.qvel[index] = saved
    # each kind of failure is reached: NaN state, contact force, object speed
    b = SimBackend(build_world("rw1", seed=0), SimBackendConfig(max_object_speed=0.01))
    b.world.data.qvel[b._sim._obj_lin[0][0]] = 0.3
    assert "moves at 0.3 m/s" in _outcome(b._sim.check)
    b.world.data.qacc[0] = np.nan
    assert "NaN/inf" in _outcome(b._sim.check)
