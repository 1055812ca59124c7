"""Third-party robots from YAML alone (issue 42): unnamed pad geoms and a missing TCP site declared in the YAML,
a home pose solved when absent, lamps stripped, the geometry rule and the force-map rule checked at load, one set
of joint limits, and a reach gate that uses execution's IK with restarts and a configurable threshold."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from sim.robots.config import load_robot_config
from sim.robots.reach import reach_report, require_reach
from sim.world import WORKSPACE_BOUNDS
from torm.errors import ConfigError, SceneError
from torm.execution.ik import IKSolver

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "data" / "robots" / "unnamed_pads" / "robot.yaml"
REFERENCE = "mini6_lg90"  # the same parts with named pads, a TCP site and an authored home


def _site_pose(model: mujoco.MjModel, q: np.ndarray, rcfg) -> np.ndarray:
    ids = rcfg.resolve(model)
    d = mujoco.MjData(model)
    d.qpos[ids.arm_qadr] = q
    mujoco.mj_kinematics(model, d)
    T = np.eye(4)
    T[:3, :3] = d.site_xmat[ids.tcp_site].reshape(3, 3)
    T[:3, 3] = d.site_xpos[ids.tcp_site]
    return T


def test_unnamed_pads_tcp_site_and_lamp_are_handled_from_the_yaml(caplog):
    with caplog.at_level(logging.WARNING):
        cfg = load_robot_config(FIXTURE)
    ref = load_robot_config(REFERENCE)
    model, ref_model = cfg.robot_model(), ref.robot_model()
    assert model.nlight == 0 and "removed 1 <light>" in caplog.text  # the palm lamp never reaches a capture
    ids, ref_ids = cfg.resolve(model), ref.resolve(ref_model)
    # body:gripper_left_finger#4 selects the finger's 5th geom: the same pad as the named one
    assert len(ids.left_pads) == len(ids.right_pads) == 1
    q = ref.arm.home_q
    d, rd = mujoco.MjData(model), mujoco.MjData(ref_model)
    d.qpos[ids.arm_qadr], rd.qpos[ref_ids.arm_qadr] = q, q
    mujoco.mj_kinematics(model, d)
    mujoco.mj_kinematics(ref_model, rd)
    np.testing.assert_allclose(d.geom_xpos[list(ids.pads)], rd.geom_xpos[list(ref_ids.pads)], atol=1e-9)
    # the declared TCP site is where lg90.xml's own site is
    np.testing.assert_allclose(_site_pose(model, q, cfg), _site_pose(ref_model, q, ref), atol=1e-6)


def test_home_is_solved_when_absent_and_points_the_tcp_down():
    cfg = load_robot_config(FIXTURE)
    assert cfg.arm.home is not None
    T = _site_pose(cfg.robot_model(), cfg.arm.home_q, cfg)
    approach = T[:3, "xyz".index(cfg.gripper.geometry.approach_axis)]
    np.testing.assert_allclose(approach, [0, 0, -1], atol=0.02)
    lo, hi = WORKSPACE_BOUNDS
    assert np.all(T[:2, 3] >= lo[:2] - 1e-6) and np.all(T[:2, 3] <= hi[:2] + 1e-6)


def _write(tmp_path: Path, data: dict) -> Path:
    p = tmp_path / "robot.yaml"
    for part in ("arm", "gripper"):  # keep the fixture's files where they are
        data[part]["mjcf"] = str((FIXTURE.parent / data[part]["mjcf"]).resolve())
    p.write_text(yaml.safe_dump(data))
    return p


def test_a_pad_that_matches_nothing_lists_the_candidates(tmp_path):
    data = yaml.safe_load(FIXTURE.read_text())
    data["gripper"]["pad_geoms"] = [["body:gripper_left_fingr"], ["body:gripper_right_finger#4"]]
    with pytest.raises(SceneError, match=r"pad geom 'body:gripper_left_fingr' \(candidates: .*"
                                         r"body:gripper_left_finger#4"):
        load_robot_config(_write(tmp_path, data))
    data["gripper"]["pad_geoms"] = [["body:gripper_left_finger"], ["body:gripper_right_finger"]]  # every collision
    model = (cfg := load_robot_config(_write(tmp_path, data))).robot_model()                     # geom of the body
    assert len(cfg.resolve(model).left_pads) == 2


def test_geometry_rule_is_checked_when_the_yaml_loads(tmp_path):
    data = yaml.safe_load(FIXTURE.read_text())
    data["gripper"]["geometry"]["palm_center_approach"] = 0.2  # the palm in front of the fingers
    with pytest.raises(ConfigError, match="palm box"):
        load_robot_config(_write(tmp_path, data), validate=False)


def test_a_linkage_gripper_without_a_force_map_is_refused_with_the_command_to_measure_one(tmp_path):
    data = yaml.safe_load(FIXTURE.read_text())
    data["gripper"].pop("force_map")
    path = _write(tmp_path, data)
    with pytest.raises(SceneError, match=r"drives a hinge .*measure_gripper .* --force"):
        load_robot_config(path)
    assert load_robot_config(path, require_force_map=False).gripper.force_map is None  # what measuring needs


def test_one_set_of_joint_limits_for_ik_simulation_and_safety(tmp_path):
    data = yaml.safe_load(FIXTURE.read_text())
    data["arm"]["position_limits"][0] = [-1.0, 1.0]
    cfg = load_robot_config(_write(tmp_path, data))
    model = cfg.robot_model()
    ids = cfg.resolve(model)
    np.testing.assert_allclose(model.jnt_range[ids.arm_joints], np.asarray(cfg.arm.position_limits), atol=1e-9)
    ik = IKSolver(model, tuple(cfg.arm.joints), cfg.arm.tcp_site)
    np.testing.assert_allclose(np.column_stack(ik.joint_ranges()), np.asarray(cfg.arm.position_limits), atol=1e-9)


def small_arm(out: Path, factor: float = 0.6) -> Path:
    """The mini6 arm scaled to ``factor`` of its size (a Lite-6-sized arm: 0.24 + 0.21 m links) with the lg90
    hand, as a robot YAML without home."""
    text = (ROOT / "sim/robots/mini6_arm/mini6.xml").read_text()

    def scale(m: re.Match) -> str:
        return f'{m.group(1)}="{" ".join(f"{float(v) * factor:.6g}" for v in m.group(2).split())}"'

    (out / "small6.xml").write_text(re.sub(r'\b(pos|fromto|size)="([^"]*)"', scale, text))
    data = yaml.safe_load((ROOT / "sim/robots/mini6_lg90/robot.yaml").read_text())
    data["name"] = "small6_lg90"
    data["arm"]["mjcf"] = str(out / "small6.xml")
    data["gripper"]["mjcf"] = str(ROOT / "sim/robots/lg90_gripper/lg90.xml")
    data["arm"].pop("home")
    data["base_pose"]["position"] = [0.55, -0.25, 0.0]  # at the box edge, facing it
    data["reach_min_share"] = 0.5  # a small arm meant to cover half the box
    p = out / "robot.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.slow
def test_small_arm_at_a_reachable_pose_passes_the_reach_gate(tmp_path):
    cfg = load_robot_config(small_arm(tmp_path))
    rep = require_reach(cfg, WORKSPACE_BOUNDS, cfg.reach_min_share)  # passes at its configured threshold
    assert 0.5 <= rep.share < 0.75
    with pytest.raises(SceneError, match=r"below the 75 % needed.*move it closer.*reach_min_share"):
        require_reach(cfg, WORKSPACE_BOUNDS, 0.75)  # the default threshold, with advice that fits


def test_advice_when_the_base_stands_inside_the_box():
    cfg = load_robot_config(REFERENCE, ["base_pose.position=[0.55, 0.0, 0.0]"])
    rep = reach_report(cfg, WORKSPACE_BOUNDS, n_xy=2, heights=(0.05,))
    assert "inside the workspace box" in rep.advice() and "closer" not in rep.advice()


@pytest.mark.slow
def test_trial_from_the_yaml_alone_picks_the_object():
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    trial = config.from_dict(TrialConfig, {"scenario": "rw1", "method": "oracle", "robot": str(FIXTURE)},
                             overrides=["capture.n_views=6", "capture.scale=0.25"])
    rec = run_trial(trial)
    assert rec["objects"] and all(o["outcome"] == "success" for o in rec["objects"]), rec["objects"]
