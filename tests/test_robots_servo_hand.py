"""A hand driven by a weak position servo (issue 59): built like MuJoCo Menagerie's Panda hand (slide fingers, a
tendon, ``biastype="affine"`` servo; unnamed pads, no TCP site), brought by YAML alone
(``tests/data/robots/servo_hand``). Its servo presses with stiffness x remaining travel, not its force limit: torm
refuses it without a measured force map, measures one without crashing, refuses a grip force above what it squeezes,
and with the YAML's gain scale the pads press the planned force within 10 %."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim.robots.config import load_robot_config
from torm.errors import ConfigError, SceneError

HAND = Path(__file__).resolve().parent / "data" / "robots" / "servo_hand" / "robot.yaml"


def test_the_menagerie_style_servo_without_a_force_map_is_refused_with_what_it_pulls():
    with pytest.raises(SceneError, match=r"position servo that pulls only 2 N half-way closed.*measure_gripper.*"
                                         r"--force.*servo_gain_scale"):
        load_robot_config(HAND, ["gripper.servo_gain_scale=1", "gripper.force_map=null"])


def test_the_force_map_of_a_weak_servo_is_measured_not_a_crash():
    """The MJCF's own gains (25 N/m x gap per finger): every row levels off at the servo's pull."""
    from sim.robots.measure_gripper import measure_force_map

    cfg = load_robot_config(HAND, ["gripper.servo_gain_scale=1", "gripper.force_map=null"], require_force_map=False)
    fmap = measure_force_map(cfg, widths=[0.02, 0.06])
    most = dict(zip(fmap.widths, fmap.max_force, strict=True))
    # the servo's static pull: 100 N/m x (gap / 2) on the tendon, half of it on each finger = 25 N/m x gap
    assert most[0.02] == pytest.approx(25.0 * 0.02, rel=0.1) and most[0.06] == pytest.approx(25.0 * 0.06, rel=0.1)
    assert max(max(r) for r in fmap.pad_force) <= max(fmap.max_force) * 1.01


def test_with_its_gain_scale_the_pads_press_the_planned_force_within_ten_percent():
    from sim.robots.measure_gripper import check_force

    cfg = load_robot_config(HAND)
    rows = check_force(cfg, [20.0, 60.0, 130.0], [0.03, 0.065])
    for r in rows:
        assert abs(r["rel_error"]) < 0.10, r
    # where the servo cannot reach the request the applied force is the most it squeezes, and that is what it presses
    narrow = next(r for r in rows if r["width_m"] == 0.03 and r["requested_n"] == 130.0)
    assert narrow["applied_n"] < 80.0 and narrow["measured_n"] == pytest.approx(narrow["applied_n"], rel=0.1)


def test_a_grip_force_above_what_the_servo_squeezes_is_refused_by_name():
    from types import SimpleNamespace

    from torm.execution.pick_config import check_grip_force

    cfg = load_robot_config(HAND)
    fmap = cfg.gripper.force_map
    gripper = SimpleNamespace(force_range_n=(20.0, 235.0), max_pad_force=(fmap.widths, fmap.max_force))
    check_grip_force(130.0, gripper)  # reached from a 55 mm opening up
    with pytest.raises(ConfigError, match=r"pick.grip_force=200 N is more than this gripper squeezes at any opening: "
                                          r"at most 178 N.*servo_gain_scale"):
        check_grip_force(200.0, gripper)


def test_gain_scale_multiplies_the_servo_gains_and_refuses_nonsense():
    with pytest.raises(ConfigError, match="servo_gain_scale must be in"):
        load_robot_config(HAND, ["gripper.servo_gain_scale=0"], validate=False)
    base = load_robot_config(HAND, ["gripper.servo_gain_scale=1", "gripper.force_map=null"], require_force_map=False)
    m1 = base.robot_model()
    a1 = base.resolve(m1).gripper_actuator
    m4 = load_robot_config(HAND, ["gripper.servo_gain_scale=4", "gripper.force_map=null"],
                           require_force_map=False).robot_model()
    assert m4.actuator_gainprm[a1, 0] == pytest.approx(4 * m1.actuator_gainprm[a1, 0])
    assert m4.actuator_biasprm[a1, 1] == pytest.approx(4 * m1.actuator_biasprm[a1, 1])  # stiffness x s
    assert m4.actuator_biasprm[a1, 2] == pytest.approx(2 * m1.actuator_biasprm[a1, 2])  # damping x sqrt(s)
