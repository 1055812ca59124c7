"""The second robot fixture (mini6 arm + lg90 linkage gripper) works through its robot.yaml alone.

It is written unlike inovo_2f85 on purpose: separate arm and gripper files, angles in degrees, unnamed
actuators, no gravity compensation in the MJCF, visual geoms in group 2, a four-bar gripper whose command runs
255 = open and whose pads advance along the approach as they close, and a base moved off the origin by
``base_pose``. These tests check the composition, the base pose everywhere the robot is modelled, the reach
check, the pad-force map on fixed blocks, the TCP tracking check, and full trials on rw1 and rw3.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from sim.backend import SimBackend
from sim.robots.config import ROBOTS_DIR, load_robot_config
from sim.robots.measure_gripper import check_force, measure_tcp_offset
from sim.world import GROUP_COLLISION, GROUP_ROBOT, build_world
from torm.errors import SceneError
from torm.execution.pick import make_ik_solver
from torm.execution.robot_collision import RobotCollisionChecker

YAML = ROBOTS_DIR / "mini6_lg90" / "robot.yaml"


@pytest.fixture(scope="module")
def cfg():
    return load_robot_config(YAML)


@pytest.fixture(scope="module")
def backend(cfg):
    b = SimBackend(build_world("rw1", seed=0, robot=cfg))
    yield b
    b.close()


def test_the_fixture_is_written_in_a_different_style(cfg):
    assert cfg.composed and cfg.mjcf is None and cfg.scene is None
    arm, grip = (mujoco.MjSpec.from_file(str(p)) for p in (cfg.arm.mjcf, cfg.gripper.mjcf))
    assert arm.compiler.degree and grip.compiler.degree  # angles in degrees in both files
    assert all(not a.name for a in [*arm.actuators, *grip.actuators])  # unnamed actuators
    assert cfg.arm.actuators is None and cfg.gripper.actuator is None
    assert all(b.gravcomp == 0 for b in [*arm.bodies, *grip.bodies])  # no gravity compensation in the MJCF
    assert cfg.gripper.command_range == (255, 0)  # 255 = open
    assert not cfg.base_pose.is_identity
    offsets = [o for _, o in cfg.gripper.tcp_offset]
    assert max(offsets) - min(offsets) > 0.010  # the pads move > 10 mm along the approach as they close


def test_composition_keeps_units_options_integrator_and_hides_the_robot(cfg, backend):
    w = backend.world
    m = w.model
    ids = w.robot_ids
    # degrees in the files, radians in the model: the world did not force compiler.degree off; the arm joints carry
    # the YAML's position_limits (one set of limits for IK, simulation and safety), converted from degrees right
    np.testing.assert_allclose(m.jnt_range[ids.arm_joints[1]], cfg.arm.position_limits[1])
    np.testing.assert_allclose(m.jnt_range[ids.gripper_joints[0]], np.radians([-10, 40]))
    # the arm's own integrator, the gripper's contact options (attach alone drops them), multiccd on
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 10
    assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_MULTICCD
    # unnamed actuators found from their joints, in joint order
    assert list(m.actuator_trnid[ids.arm_actuators, 0]) == list(ids.arm_joints)
    assert m.actuator_trnid[ids.gripper_actuator, 0] == ids.gripper_joints[0]
    # gravcomp: true in robot.yaml reaches every robot body, and only those
    robot_bodies = np.unique(m.geom_bodyid[w.robot_geom_ids])
    assert np.all(m.body_gravcomp[robot_bodies[robot_bodies > 0]] == 1.0)
    assert all(m.body_gravcomp[o.body_id] == 0.0 for o in w.objects)
    # visual geoms authored in group 2 (the glass group!) now sit in the robot group, hidden from captures
    assert set(m.geom_group[w.robot_geom_ids]) <= {GROUP_ROBOT, GROUP_COLLISION}
    assert not w.geom_to_instance[w.robot_geom_ids].any()


def test_robot_is_absent_from_the_capture_images(backend):
    """Depth straight down onto the arm base: the table (1.5 m away), not the robot, unless it is made visible."""
    from sim.cameras.rig import CameraRigConfig, SimCameraRig

    w = backend.world
    base = np.asarray(w.robot_config.base_pose.position)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[1, 0, 0], [0, -1, 0], [0, 0, -1]])  # OpenCV: looking down
    T[:3, 3] = base + [0, 0, 1.5]
    with SimCameraRig.from_world(w, CameraRigConfig(width=64, height=48)) as rig:
        depth = rig.render_arrays(T, channels=["depth"])["depth"]
        groups = w.model.geom_group.copy()
        try:
            w.model.geom_group[w.robot_geom_ids] = 2  # negative control: as authored, in a rendered group
            depth_shown = rig.render_arrays(T, channels=["depth"])["depth"]
        finally:
            w.model.geom_group[:] = groups
    assert abs(float(depth[24, 32]) - 1.5) < 0.01
    assert float(depth_shown[24, 32]) < 1.45


def test_base_pose_is_the_same_in_the_world_ik_collision_and_fk_models(cfg, backend):
    w = backend.world
    m, d = w.model, w.data
    T_wb = cfg.base_pose.T_world_base
    base_body = m.geom_bodyid[w.robot_geom_ids].min()
    np.testing.assert_allclose(d.xpos[base_body], T_wb[:3, 3], atol=1e-9)
    np.testing.assert_allclose(d.xmat[base_body].reshape(3, 3), T_wb[:3, :3], atol=1e-9)
    st = backend.arm.state()
    home = cfg.arm.home_q
    T_world = st.T_world_tcp
    np.testing.assert_allclose(T_world[:3, 3], [0.55, 0.0, 0.30], atol=2e-3)  # home, in the world frame
    T_fk = backend.arm.forward_kinematics(home)
    T_ik = make_ik_solver(cfg).forward(home)
    chk = RobotCollisionChecker.from_robot_config(cfg)
    chk.data.qpos[chk.model.jnt_qposadr[[chk.model.joint(j).id for j in cfg.arm.joints]]] = home
    mujoco.mj_kinematics(chk.model, chk.data)
    p_chk = chk.data.site(cfg.arm.tcp_site).xpos
    for p in (T_fk[:3, 3], T_ik[:3, 3], p_chk):
        np.testing.assert_allclose(p, T_fk[:3, 3], atol=1e-9)
    np.testing.assert_allclose(T_world[:3, 3], T_fk[:3, 3], atol=1e-3)  # only servo error between them
    assert chk.collisions(home) == []  # the home pose is collision-free against the table
    # a world target is solved in the world frame: IK -> FK round trip at a pose above the box
    target = T_fk.copy()
    target[:3, 3] = [0.45, 0.10, 0.20]
    res = make_ik_solver(cfg).solve(target, home)
    assert res.converged and np.allclose(backend.arm.forward_kinematics(res.q)[:3, 3], target[:3, 3], atol=1e-3)


def test_safety_box_is_checked_with_the_moved_base(backend):
    """The safety layer's TCP box (world frame) sees the arm where it is: turning the shoulder by 180 deg swings the
    TCP behind the base (y < -0.6 m, outside the box); the same turn from an arm at the origin would stay inside."""
    from torm.backend.safety import SafetyError

    q = backend.arm.state().q
    turned = q + np.array([np.pi, 0, 0, 0, 0, 0])
    assert backend.arm.forward_kinematics(turned)[1, 3] < -0.6
    with pytest.raises(SafetyError, match="workspace box"):
        backend.arm.follow_trajectory(np.array([3.0]), turned[None])
    assert np.allclose(backend.arm.state().q, q, atol=1e-3)  # refused before anything moved


def test_reach_check_refuses_an_arm_that_cannot_reach_the_box():
    far = load_robot_config(YAML, ["base_pose.position=[-1.5, 0.0, 0.0]"])
    world = build_world("rw1", seed=0, robot=far)
    with pytest.raises(SceneError, match=r"reaches 0 % of the workspace.*`base_pose`"):
        SimBackend(world)


def test_reach_report_of_the_fixture(backend):
    rep = backend.reach
    assert rep is not None and rep.share >= 0.85 and len(rep.reached) == 32


@pytest.mark.parametrize("name", ["mini6_lg90", "inovo_2f85"])
def test_pad_force_map_reproduces_the_requested_force_on_a_fixed_block(name):
    """Requested pad force vs MuJoCo's contact forces on a fixed block, at widths between the map's grid points."""
    rcfg = load_robot_config(name)
    fmap = rcfg.gripper.force_map
    rows = check_force(rcfg, [30.0, 130.0, 235.0], [0.036, 0.066])
    for r in rows:
        reach = fmap.force_range(r["width_m"])[1]  # the 2F-85 model's servo cannot give 235 N at 36 mm
        assert r["applied_n"] == pytest.approx(min(r["requested_n"], reach)), r
        assert abs(r["rel_error"]) < 0.10, r
    assert sum(r["applied_n"] == pytest.approx(r["requested_n"]) for r in rows) >= 5


def test_linkage_tcp_offset_matches_the_yaml(cfg):
    measured = measure_tcp_offset(cfg, [0, 128, 255], duration_s=0.6)
    for gap, off in measured:
        assert off == pytest.approx(cfg.gripper.tcp_offset_m(gap), abs=5e-4)


def test_sag_without_gravcomp_is_measured_by_the_tracking_check():
    """Without gravity compensation the held arm sags by millimetres; the TCP check sees it, gravcomp removes it."""
    errs = {}
    for on in (True, False):
        rcfg = load_robot_config(YAML, [f"gravcomp={str(on).lower()}"])
        b = SimBackend(build_world("rw1", seed=0, robot=rcfg))
        b.clock.sleep(0.6)
        st = b.arm.state()
        errs[on] = float(np.linalg.norm(st.T_world_tcp[:3, 3] - b.arm.forward_kinematics(b.arm.inner.target())[:3, 3]))
        b.close()
    assert errs[True] < 2e-4 and errs[False] > 3e-3, errs


@pytest.mark.parametrize("scenario", ["rw1", "rw3"])
def test_trial_with_the_fixture_succeeds_through_its_yaml_alone(scenario):
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    trial = config.from_dict(TrialConfig, {"scenario": scenario, "method": "oracle", "robot": str(YAML)},
                             overrides=["capture.n_views=6", "capture.scale=0.25"])
    rec = run_trial(trial)
    assert rec["objects"] and all(o["outcome"] == "success" for o in rec["objects"]), rec["objects"]
    for o in rec["objects"]:
        pick = o["pick"]
        g = pick["grip_force"]
        assert g["requested_n"] == 130.0 and abs(g["measured_n"] / g["applied_n"] - 1.0) < 0.10, g
        phases = {e["phase"] for e in pick["tcp_errors"]}  # the tracking check ran after every motion
        assert {"pre_grasp", "approach", "lift", "translate", "lower", "retreat"} <= phases
        assert pick["tcp_error_max_m"] < 0.005
        assert pick["judgement"]["tcp_lift_m"] > 0.24
