"""RobotConfig loading: names, limits, the command <-> width map and validation against the MJCF."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from sim.robots.config import ROBOTS_DIR, available_robots, load_robot_config
from torm.errors import ConfigError, SceneError, UnknownNameError

YAML = ROBOTS_DIR / "inovo_2f85" / "robot.yaml"


def _write(tmp_path: Path, data: dict) -> Path:
    """A copy of the robot.yaml with ``data`` changes, MJCF paths made absolute."""
    p = tmp_path / "robot.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _base() -> dict:
    data = yaml.safe_load(YAML.read_text())
    data["mjcf"] = str(YAML.parent / data["mjcf"])
    data["scene"] = str(YAML.parent / data["scene"])
    return data


def test_load_by_name_and_by_path_agree() -> None:
    by_name = load_robot_config("inovo_2f85")
    by_path = load_robot_config(YAML)
    assert by_name == by_path
    assert by_name.mjcf.is_absolute() and by_name.mjcf.is_file()
    assert by_name.arm.joints == ("j1", "j2", "j3", "j4", "j5", "j6")
    assert by_name.arm.velocity_limits == (1.8, 1.8, 2.5, 2.6, 3.3, 3.3)
    np.testing.assert_allclose(by_name.arm.upper, np.deg2rad([355, 170, 170, 355, 170, 355]), atol=1e-5)
    assert "inovo_2f85" in available_robots()


def test_home_pose_puts_tcp_over_the_workspace_pointing_down() -> None:
    cfg = load_robot_config("inovo_2f85")
    model = mujoco.MjModel.from_xml_path(str(cfg.mjcf))
    data = mujoco.MjData(model)
    data.qpos[[model.joint(j).qposadr[0] for j in cfg.arm.joints]] = cfg.arm.home_q
    mujoco.mj_forward(model, data)
    np.testing.assert_allclose(data.site(cfg.arm.tcp_site).xpos, (0.5, 0.0, 0.35), atol=1e-3)
    R = data.site(cfg.arm.tcp_site).xmat.reshape(3, 3)
    np.testing.assert_allclose(R[:, 2], (0, 0, -1), atol=1e-3)  # approach axis z points down
    # Flange to TCP along the approach axis: palm + half the pad length.
    d = data.site(cfg.arm.flange_site).xpos - data.site(cfg.arm.tcp_site).xpos
    assert np.linalg.norm(d) == pytest.approx(0.1425, abs=1e-6)


def test_unknown_robot_name_lists_valid_choices() -> None:
    with pytest.raises(UnknownNameError, match="inovo_2f85"):
        load_robot_config("no_such_robot")


def test_unknown_key_is_rejected_and_named(tmp_path: Path) -> None:
    data = _base()
    data["arm"]["max_payload"] = 3.0
    with pytest.raises(ConfigError, match="max_payload"):
        load_robot_config(_write(tmp_path, data))


def test_missing_field_is_named(tmp_path: Path) -> None:
    data = _base()
    del data["arm"]["tcp_site"]
    with pytest.raises(ConfigError, match="tcp_site"):
        load_robot_config(_write(tmp_path, data))


def test_missing_joint_in_model_is_named(tmp_path: Path) -> None:
    data = _base()
    data["arm"]["joints"][2] = "elbow_joint"
    data["gripper"]["pad_geoms"][0] = "left_pad_typo"
    with pytest.raises(SceneError, match="elbow_joint") as info:
        load_robot_config(_write(tmp_path, data))
    assert "left_pad_typo" in str(info.value)


def test_limits_wider_than_the_mjcf_are_rejected(tmp_path: Path) -> None:
    data = _base()
    data["arm"]["position_limits"][1] = [-3.1, 3.1]
    with pytest.raises(SceneError, match="j2"):
        load_robot_config(_write(tmp_path, data))


def test_actuators_out_of_joint_order_are_rejected(tmp_path: Path) -> None:
    data = _base()
    acts = data["arm"]["actuators"]
    acts[0], acts[1] = acts[1], acts[0]
    with pytest.raises(SceneError, match="act_j2.*j1"):
        load_robot_config(_write(tmp_path, data))


def test_inconsistent_lengths_and_non_monotone_map_are_rejected(tmp_path: Path) -> None:
    data = _base()
    data["arm"]["velocity_limits"] = [1.0] * 5
    with pytest.raises(ConfigError, match="velocity_limits"):
        load_robot_config(_write(tmp_path, data))
    data = _base()
    data["gripper"]["command_to_width"] = [[0, 0.085], [128, 0.02], [255, 0.03]]
    with pytest.raises(ConfigError, match="command_to_width"):
        load_robot_config(_write(tmp_path, data))


def test_command_width_map_interpolates_and_inverts() -> None:
    cfg = load_robot_config("inovo_2f85")
    assert cfg.command_to_width(0) == pytest.approx(0.085)
    assert cfg.command_to_width(255) == pytest.approx(0.0, abs=1e-4)
    for cmd in (10.0, 77.0, 128.0, 200.0, 250.0):
        assert cfg.width_to_command(cfg.command_to_width(cmd)) == pytest.approx(cmd, abs=1e-6)
    widths = [cfg.command_to_width(c) for c in np.linspace(0, 255, 52)]
    assert np.all(np.diff(widths) < 0)
    assert cfg.width_to_command(0.5) == 0.0  # wider than the stroke: fully open
    assert cfg.width_to_command(-0.01) == 255.0


def test_third_party_robot_plugs_in_with_only_a_yaml(tmp_path: Path) -> None:
    """Another MJCF (here: the same parts attached with other names) works given a YAML naming its parts."""
    arm = mujoco.MjSpec.from_file(str(ROBOTS_DIR / "inovo_arm" / "inovo_arm.xml"))
    hand = mujoco.MjSpec.from_file(str(ROBOTS_DIR / "robotiq_2f85" / "2f85.xml"))
    arm.site("flange").attach_body(hand.body("base"), "hand_", "")
    arm.compile()
    (tmp_path / "other.xml").write_text(arm.to_xml())
    data = yaml.safe_load(YAML.read_text())
    data.update(name="other", mjcf="other.xml", scene="other.xml")
    data["arm"]["tcp_site"] = "hand_tcp"
    data["gripper"].update(actuator="hand_fingers", joints=["hand_left_finger", "hand_right_finger"],
                           pad_geoms=["hand_left_pad", "hand_right_pad"])
    cfg = load_robot_config(_write(tmp_path, data))
    assert cfg.name == "other" and cfg.mjcf == tmp_path / "other.xml"
    arm_only = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / "inovo_arm" / "inovo_arm.xml"))
    with pytest.raises(SceneError, match="hand_tcp"):
        cfg.validate_against(arm_only)
