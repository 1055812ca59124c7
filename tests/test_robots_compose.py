"""Robot composition from YAML on tiny hand-built MJCFs: option merging, units, unnamed actuators, names, errors.

The arm and gripper here are one joint each (seconds to compile), written in opposite styles on purpose.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from sim.robots.compose import merge_options
from sim.robots.config import BasePose, load_robot_config
from sim.robots.force_map import ForceMap
from sim.world import build_world
from torm.errors import ConfigError, SceneError

ARM = """<mujoco model="tiny_arm">
  <compiler angle="radian"/>
  <option integrator="implicitfast" impratio="5"/>
  <worldbody>
    <body name="base">
      <geom type="cylinder" size="0.05 0.05" pos="0 0 0.05"/>
      <body name="link" pos="0 0 0.1">
        <joint name="j" axis="0 0 1" range="-3 3"/>
        <geom type="capsule" size="0.03" fromto="0 0 0 0.3 0 0"/>
        <site name="flange" pos="0.3 0 0" euler="0 1.5707963 0"/>
      </body>
    </body>
  </worldbody>
  <actuator>{arm_actuators}</actuator>
  <keyframe><key name="home" qpos="0.1"/></keyframe>
</mujoco>"""
GRIPPER = """<mujoco model="tiny_gripper">
  <compiler angle="degree"/>
  <option cone="elliptic" impratio="20" integrator="RK4"/>
  <worldbody>
    <body name="hand">
      <geom type="box" size="0.02 0.04 0.02" pos="0 0 0.02"/>
      <site name="tcp" pos="0 0 0.08"/>
      <body name="finger_l" pos="0 0.03 0.08">
        <joint name="f" type="slide" axis="0 -1 0" range="0 0.03"/>
        <geom name="pad_l" type="box" size="0.01 0.003 0.01"/>
        <geom name="pad_l2" type="box" size="0.01 0.003 0.01" pos="0 0 0.015"/>
      </body>
      <body name="finger_r" pos="0 -0.03 0.08">
        <joint name="f2" type="slide" axis="0 1 0" range="0 0.03"/>
        <geom name="pad_r" type="box" size="0.01 0.003 0.01"/>
      </body>
    </body>
  </worldbody>
  <equality><joint joint1="f2" joint2="f"/></equality>
  <actuator><position joint="f" kp="5000" forcerange="-20 20" ctrlrange="0 0.03"/></actuator>
</mujoco>"""
GEOMETRY = {"approach_axis": "z", "closing_axis": "y", "pad_size": [0.02, 0.006, 0.02],
            "finger_size": [0.02, 0.006, 0.04], "finger_center_approach": -0.01, "palm_size": [0.04, 0.08, 0.04],
            "palm_center_approach": -0.06, "max_opening": 0.054, "finger_depth": 0.04, "tip_approach": 0.01}


def _robot(tmp_path: Path, arm_actuators: str = '<position joint="j" kp="50"/>', **changes) -> Path:
    (tmp_path / "arm.xml").write_text(ARM.format(arm_actuators=arm_actuators))
    (tmp_path / "gripper.xml").write_text(GRIPPER)
    data = {
        "name": "tiny",
        "base_pose": {"position": [-0.3, -0.2, 0.0], "orientation": [0.0, 0.0, 0.5]},
        "arm": {"mjcf": "arm.xml", "joints": ["j"], "flange_site": "flange", "tcp_site": "hand_tcp",
                "position_limits": [[-3.0, 3.0]], "velocity_limits": [1.0], "acceleration_limits": [2.0],
                "home": [0.0]},
        "gripper": {"mjcf": "gripper.xml", "prefix": "hand_", "joints": ["hand_f"],
                    "pad_geoms": [["hand_pad_l", "hand_pad_l2"], ["hand_pad_r"]], "command_range": [0.0, 0.03],
                    "command_to_width": [[0.0, 0.054], [0.03, 0.0]], "geometry": GEOMETRY},
    }
    for key, value in changes.items():
        d = data
        *parents, last = key.split(".")
        for k in parents:
            d = d[k]
        if value is None:
            d.pop(last, None)
        else:
            d[last] = value
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_options_merge_units_keyframes_and_unnamed_actuators(tmp_path):
    cfg = load_robot_config(_robot(tmp_path))
    m = cfg.robot_model()
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST  # arm wins on non-contact settings
    assert m.opt.impratio == 20 and m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC  # gripper wins on contact
    assert m.nkey == 0  # keyframes dropped (home comes from the YAML)
    np.testing.assert_allclose(m.jnt_range[m.joint("j").id], [-3, 3])  # radians file
    np.testing.assert_allclose(m.jnt_range[m.joint("hand_f").id], [0, 0.03])  # slide: metres either way
    ids = cfg.resolve(m)
    assert m.actuator_trnid[ids.arm_actuators[0], 0] == m.joint("j").id
    assert m.actuator_trnid[ids.gripper_actuator, 0] == m.joint("hand_f").id
    assert len(ids.left_pads) == 2 and len(ids.right_pads) == 1
    # the base sits at base_pose: position, and yaw 0.5 rad from the roll-pitch-yaw form
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(d.xpos[m.body("base").id], [-0.3, -0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(d.xmat[m.body("base").id].reshape(3, 3)[:, 0], [np.cos(0.5), np.sin(0.5), 0], atol=1e-9)


def test_world_keeps_the_robots_explicit_options_and_adds_glass_defaults_elsewhere(tmp_path):
    w = build_world("rw1", seed=0, robot=load_robot_config(_robot(tmp_path)))
    assert w.model.opt.impratio == 20  # the robot set it: kept (the world's own default is 10)
    assert w.model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert w.model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    np.testing.assert_allclose(w.model.jnt_range[w.model.joint("j").id], [-3, 3])
    # geoms authored in group 0 (rendered environment!) moved to the robot group
    assert set(w.model.geom_group[w.robot_geom_ids]) == {1}


def test_merge_options_rules():
    parent, child = mujoco.MjSpec().option, mujoco.MjSpec().option
    parent.integrator, parent.impratio, parent.timestep = 3, 5.0, 0.001
    child.integrator, child.impratio, child.cone, child.noslip_iterations = 1, 20.0, 1, 3
    notes = merge_options(parent, child)
    assert (parent.integrator, parent.impratio, parent.cone, parent.noslip_iterations) == (3, 20.0, 1, 3)
    assert parent.timestep == 0.001
    assert any("impratio" in n for n in notes) and any("integrator" in n for n in notes)


def test_name_errors_are_clear(tmp_path):
    with pytest.raises(SceneError, match=r"site 'tcp' \(the composed model calls it 'hand_tcp'"):
        load_robot_config(_robot(tmp_path, **{"arm.tcp_site": "tcp"}))
    two = '<position joint="j" kp="50"/><motor joint="j"/>'
    with pytest.raises(SceneError, match=r"2 actuators .* driving joint 'j'; name the one to use in arm.actuators"):
        load_robot_config(_robot(tmp_path, arm_actuators=two))
    with pytest.raises(SceneError, match=r"no site 'wrist'.*gripper.attach_site"):
        load_robot_config(_robot(tmp_path, **{"gripper.attach_site": "wrist"}))


def test_config_errors_name_the_key(tmp_path):
    path = _robot(tmp_path, mjcf="arm.xml")
    with pytest.raises(ConfigError, match="either a pre-combined mjcf or arm.mjcf"):
        load_robot_config(path)
    with pytest.raises(ConfigError, match="gripper.mjcf"):
        load_robot_config(_robot(tmp_path, **{"gripper.mjcf": None}))
    with pytest.raises(ConfigError, match="pad_geoms"):
        load_robot_config(_robot(tmp_path, **{"gripper.pad_geoms": [["hand_pad_l"], ["hand_pad_l"]]}))
    with pytest.raises(ConfigError, match="must not grow"):  # widths growing towards the closed command
        load_robot_config(_robot(tmp_path, **{"gripper.command_range": [0.03, 0.0]}))
    with pytest.raises(ConfigError, match="zero length"):
        BasePose(orientation=(0.0, 0.0, 0.0, 0.0))


def test_reversed_command_and_pad_list_forms(tmp_path):
    flat = load_robot_config(_robot(tmp_path, **{"gripper.pad_geoms": ["hand_pad_l", "hand_pad_r"]}))
    assert flat.gripper.pad_geoms == (("hand_pad_l",), ("hand_pad_r",))
    rev = load_robot_config(_robot(tmp_path, **{"gripper.command_range": [0.03, 0.0],
                                                "gripper.command_to_width": [[0.0, 0.0], [0.03, 0.054]]}),
                            validate=False)
    assert rev.gripper.open_command == 0.03 and rev.gripper.closed_command == 0.0
    for w in (0.0, 0.01, 0.054):
        assert rev.width_to_command(w) == pytest.approx(w / 0.054 * 0.03)
        assert rev.command_to_width(rev.width_to_command(w)) == pytest.approx(w)


def test_base_pose_forms_agree():
    yaw = BasePose((0.1, 0.2, 0.0), (0.0, 0.0, np.pi / 2))
    quat = BasePose((0.1, 0.2, 0.0), (np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)))
    np.testing.assert_allclose(yaw.T_world_base, quat.T_world_base, atol=1e-12)
    np.testing.assert_allclose(yaw.T_world_base[:3, 0], [0, 1, 0], atol=1e-12)
    assert BasePose().is_identity and not yaw.is_identity


def test_gravcomp_key_overrides_the_mjcf():
    on = load_robot_config("inovo_2f85").robot_model()  # the MJCF compensates gravity itself
    off = load_robot_config("inovo_2f85", ["gravcomp=false"]).robot_model()
    assert on.body_gravcomp[1:].max() == 1.0 and off.body_gravcomp.max() == 0.0


def test_force_map_interpolates_inverts_and_caps():
    fm = ForceMap(widths=(0.02, 0.06), settings=(1.0, 2.0, 4.0), pad_force=((10.0, 20.0, 25.0), (12.0, 24.0, 48.0)),
                  max_force=(25.0, 100.0))
    assert fm.pad_force_at(2.0, 0.04) == pytest.approx(22.0)
    for w in (0.02, 0.03, 0.05, 0.06):
        for s in (1.0, 1.5, 2.0):
            assert fm.setting_for(fm.pad_force_at(s, w), w) == pytest.approx(s)
    assert fm.force_range(0.02) == (10.0, 25.0)  # the narrow row levels off at its cap
    assert fm.setting_for(100.0, 0.06) == 4.0  # clamped to the measured range
    with pytest.raises(ConfigError, match="grow with the setting"):
        ForceMap(widths=(0.02,), settings=(1.0, 2.0), pad_force=((10.0, 5.0),))
    with pytest.raises(ConfigError, match="rows"):
        ForceMap(widths=(0.02, 0.04), settings=(1.0, 2.0), pad_force=((10.0, 20.0),))
