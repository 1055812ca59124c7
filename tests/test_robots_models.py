"""The robot MJCFs: compile, step cleanly, match the public kinematics/masses, and the gripper's stroke.

Every shipped robot is covered: each folder's scene.xml, and every robot.yaml composed (arm + gripper through
MjSpec.attach, base at its base_pose) into a scene with a floor and a light, the way a Menagerie-style
"every scene compiles and steps" test does.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from sim.robots.config import ROBOTS_DIR, available_robots, load_robot_config
from sim.robots.inovo_2f85.build_model import OUT_XML, build_xml
from sim.robots.measure_gripper import measure_command_to_width, pad_gap

ROBOT_DIRS = sorted(p for p in ROBOTS_DIR.iterdir() if (p / "scene.xml").is_file())
MODEL_DIRS = sorted(p for p in ROBOTS_DIR.iterdir() if any(p.glob("*.xml")) or any(p.glob("robot.yaml")))


def test_every_robot_folder_has_a_readme() -> None:
    names = {p.name for p in ROBOT_DIRS}
    assert {"inovo_arm", "robotiq_2f85", "inovo_2f85"} <= names
    assert {"inovo_2f85", "mini6_lg90"} <= set(available_robots())
    for p in MODEL_DIRS:
        assert (p / "README.md").is_file(), p


def _steps_cleanly(model: mujoco.MjModel, data: mujoco.MjData, visual_group: int) -> None:
    """Step 1 s: no warning, finite, nothing drifts (position actuators + gravity compensation hold it);
    visual geoms never collide and there are collision geoms in group 3."""
    mujoco.mj_forward(model, data)
    q0 = data.qpos.copy()
    for _ in range(int(round(1.0 / model.opt.timestep))):
        mujoco.mj_step(model, data)
    assert all(int(w.number) == 0 for w in data.warning), [int(w.number) for w in data.warning]
    assert np.all(np.isfinite(data.qpos))
    assert np.max(np.abs(data.qpos - q0)) < 2e-3
    vis = model.geom_group == visual_group
    assert vis.any() and np.all(model.geom_contype[vis] == 0) and np.all(model.geom_conaffinity[vis] == 0)
    assert np.any(model.geom_group == 3)


@pytest.mark.parametrize("folder", ROBOT_DIRS, ids=lambda p: p.name)
def test_scene_compiles_and_steps_one_second_without_warnings(folder: Path) -> None:
    model = mujoco.MjModel.from_xml_path(str(folder / "scene.xml"))
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    _steps_cleanly(model, data, visual_group=1)


@pytest.mark.parametrize("name", available_robots())
def test_composed_robot_scene_compiles_and_steps_one_second_without_warnings(name: str) -> None:
    """Each robot.yaml, composed as the harness does, in a scene with a floor and a light, held at home."""
    cfg = load_robot_config(name)
    spec = cfg.robot_spec()
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], group=0)
    spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1])
    model = spec.compile()
    data = mujoco.MjData(model)
    ids = cfg.resolve(model)
    data.qpos[ids.arm_qadr] = cfg.arm.home_q
    data.ctrl[ids.arm_actuators] = cfg.arm.home_q
    data.ctrl[ids.gripper_actuator] = cfg.gripper.open_command
    mujoco.mj_forward(model, data)
    for _ in range(250):  # let the fingers open to their commanded start before measuring drift
        mujoco.mj_step(model, data)
    visual = 2 if cfg.composed else 1  # the mini6 / lg90 files keep visuals in group 2 (Menagerie style)
    _steps_cleanly(model, data, visual_group=visual)


def test_combined_model_file_is_up_to_date() -> None:
    assert OUT_XML.read_text() == build_xml(), "run python sim/robots/inovo_2f85/build_model.py"


def test_arm_kinematics_match_the_medium_preset_table() -> None:
    model = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / "inovo_arm" / "inovo_arm.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    expected = {"j1": ((0, 0, 0.26022), (0, 0, 1)), "j2": ((0.1335, 0, 0.26022), (1, 0, 0)),
                "j3": ((0.1335, 0, 0.73062), (-1, 0, 0)), "j4": ((0, 0, 0.73062), (0, 0, 1)),
                "j5": ((0, 0, 1.25022), (-1, 0, 0)), "j6": ((0, 0, 1.25022), (0, 0, 1))}
    for name, (pos, axis) in expected.items():
        np.testing.assert_allclose(data.joint(name).xanchor, pos, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(data.joint(name).xaxis, axis, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(data.site("flange").xpos, (0, 0, 1.25022 + 0.0926), atol=1e-9)
    assert model.body_subtreemass[model.body("base").id] == pytest.approx(24.445, abs=1e-6)  # medium total 24.4
    # Horizontal reach to the flange (j1 axis to flange, arm stretched at j2 = 90 deg): ~1.083 m computed.
    data.qpos[model.joint("j2").qposadr[0]] = np.pi / 2
    mujoco.mj_forward(model, data)
    assert np.linalg.norm(data.site("flange").xpos[:2]) == pytest.approx(1.0826, abs=2e-3)


def test_gripper_mass_and_tcp_between_pads() -> None:
    model = mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / "robotiq_2f85" / "2f85.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert model.body_subtreemass[model.body("base").id] == pytest.approx(0.925, abs=1e-6)
    mid = 0.5 * (data.geom("left_pad").xpos + data.geom("right_pad").xpos)
    np.testing.assert_allclose(data.site("tcp").xpos, mid, atol=1e-9)
    assert data.geom("left_pad").xpos[1] > 0 > data.geom("right_pad").xpos[1]  # closing axis = y
    assert data.site("tcp").xpos[2] > 0.1  # approach = +z, fingers beyond the palm


def test_gripper_open_width_and_full_close() -> None:
    cfg = load_robot_config("inovo_2f85")
    (_, open_w), (_, closed_w) = measure_command_to_width(cfg, [0, 255], duration_s=0.8)
    assert open_w == pytest.approx(0.085, abs=1e-3)
    assert abs(closed_w) < 1e-3


@pytest.mark.parametrize("name", ["inovo_2f85", "mini6_lg90"])
def test_measured_width_map_matches_robot_yaml(name: str) -> None:
    cfg = load_robot_config(name)
    cmds = [c for c, _ in cfg.gripper.command_to_width]
    measured = measure_command_to_width(cfg, cmds, duration_s=0.8)
    for (c, w_yaml), (_, w_sim) in zip(cfg.gripper.command_to_width, measured, strict=True):
        assert w_sim == pytest.approx(w_yaml, abs=1e-3), c
    # the gap shrinks towards the closed command, whichever end that is (mini6_lg90: 255 = open)
    widths = [w for _, w in measured]
    towards_closed = np.diff(widths) * np.sign(cfg.gripper.closed_command - cfg.gripper.open_command)
    assert np.all(towards_closed < 0)


def test_gripper_squeezes_with_its_force_limit() -> None:
    """Clamping a fixed block: the pad force settles at the actuator's force limit (20-235 N range)."""
    cfg = load_robot_config("inovo_2f85")
    spec = mujoco.MjSpec.from_file(str(cfg.scene))
    spec.option.gravity = (0, 0, 0)
    body = spec.worldbody.add_body(name="block", pos=(0.5, 0, 0.35))
    body.add_geom(name="block", type=mujoco.mjtGeom.mjGEOM_BOX, size=(0.01, 0.025, 0.01))
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_forward(model, data)
    data.ctrl[model.actuator(cfg.gripper.actuator).id] = 255
    for _ in range(600):
        mujoco.mj_step(model, data)
    assert pad_gap(model, data, cfg.gripper.pad_geoms) == pytest.approx(0.05, abs=2e-3)
    force = np.zeros(6)
    total = 0.0
    pad_ids = {model.geom(n).id for n in cfg.gripper.left_pads + cfg.gripper.right_pads}
    for i, c in enumerate(data.contact[: data.ncon]):
        if {c.geom1, c.geom2} & pad_ids:
            mujoco.mj_contactForce(model, data, i, force)
            total += force[0]
    assert 20.0 <= total / 2 <= 235.0
    assert total / 2 == pytest.approx(cfg.gripper.force, rel=0.05)
