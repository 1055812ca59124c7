"""The decision loop never sees ground truth; the judge scores afterwards; phantoms are attempted and reported."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from torm.backend.blind import LOOP_API, GroundTruthAccessError, LoopBackend
from torm.backend.calibration import Calibration, FixtureDeclaration
from torm.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
#: Modules of the decision loop: perception, planning, execution and the loop itself.
LOOP_MODULES = ["torm/loop.py", "torm/perception.py", "torm/execution", "torm/grasp", "torm/reconstruction",
                "torm/segmentation", "torm/backend/blind.py", "torm/backend/calibration.py"]


def _py_files(rel: str) -> list[Path]:
    """The module files under ``rel``; training code (offline, renders its data in the simulator) is not loop code."""
    p = ROOT / rel
    return [p] if p.is_file() else sorted(f for f in p.rglob("*.py") if "training" not in f.parts)


@pytest.mark.parametrize("rel", LOOP_MODULES)
def test_loop_modules_neither_import_the_judge_nor_read_ground_truth(rel):
    for path in _py_files(rel):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert node.module.split(".")[0] != "sim", f"{path}: imports {node.module} (the simulator)"
            if isinstance(node, ast.Import):
                assert all(a.name.split(".")[0] != "sim" for a in node.names), f"{path} imports the simulator"
            if isinstance(node, ast.Attribute) and node.attr in ("ground_truth", "known_obstacles", "world"):
                pytest.fail(f"{path}:{node.lineno} reads .{node.attr}")


class _Sim:
    name = "sim"
    arm = gripper = clock = robot_config = object()
    ground_truth = world = realism = object()

    def capture(self, n_views=None):
        return "capture"


def test_the_loop_view_refuses_every_ground_truth_accessor():
    b = LoopBackend(_Sim(), Calibration(0.01, 0.001, "test"))
    assert b.capture() == "capture" and b.name == "sim" and b.calibration.table_height == 0.01
    for name in ("ground_truth", "world", "realism", "known_obstacles", "occlusion_ratio"):
        with pytest.raises(GroundTruthAccessError, match=f"may not read backend.{name}"):
            getattr(b, name)
    with pytest.raises(GroundTruthAccessError):  # not an AttributeError: no silent fallback through hasattr
        hasattr(b, "ground_truth")
    assert not hasattr(b, "capture_views")  # a real-robot name the wrapped backend lacks: plainly absent
    with pytest.raises(GroundTruthAccessError):
        b.ground_truth = None
    assert "ground_truth" not in dir(b) and set(dir(b)) <= LOOP_API | {"calibration"}


def test_default_calibration_when_the_backend_declares_none():
    b = LoopBackend(_Sim())
    assert b.calibration.table_height == 0.0 and "default" in b.calibration.source


def test_fixture_declarations_from_yaml_and_their_surface():
    f = FixtureDeclaration.from_dict({"name": "tray", "pose": [0.5, 0.1, 0.0, 90.0],
                                      "boxes": [[[0, 0, 0.002], [0.10, 0.07, 0.002]]]})
    p = f.surface_points(0.01)
    assert p.shape[1] == 3
    # turned 90 deg: the 0.2 m side now runs along y
    assert np.ptp(p[:, 1]) == pytest.approx(0.20, abs=1e-6) and np.ptp(p[:, 0]) == pytest.approx(0.14, abs=1e-6)
    assert p[:, 2].min() == pytest.approx(0.0) and p[:, 2].max() == pytest.approx(0.004)
    with pytest.raises(ConfigError, match="unknown keys"):
        FixtureDeclaration.from_dict({"name": "x", "colour": "red", "boxes": [[[0, 0, 0], [1, 1, 1]]]})
    with pytest.raises(ConfigError, match="exactly one"):
        FixtureDeclaration("x", np.eye(4))
    with pytest.raises(ConfigError, match="not a file"):
        FixtureDeclaration("x", np.eye(4), mesh_path="/nonexistent.stl")
    with pytest.raises(ConfigError, match="rigid"):
        FixtureDeclaration("x", np.zeros((4, 4)), boxes=(((0, 0, 0), (1, 1, 1)),))


def test_sim_declares_the_lab_fixture_it_placed():
    from sim.backend import SimBackend
    from sim.world import build_world

    b = SimBackend(build_world("lab4", 0, robot="inovo_2f85"))
    try:
        cal = b.calibration()
        assert [f.name for f in cal.fixtures] == [b.world.fixture.name]
        assert np.allclose(cal.obstacle_points(), b.world.fixture.surface_points())
        assert cal.table_height == 0.0
    finally:
        b.close()


def _free_spot(gt_positions, candidates, clearance):
    for xy in candidates:
        if all(np.linalg.norm(np.asarray(xy) - p[:2]) > clearance for p in gt_positions):
            return xy
    raise AssertionError("no free spot for the phantom")


def test_a_forced_false_positive_is_attempted_as_a_phantom_and_the_real_objects_are_still_picked():
    from sim.backend import SimBackend
    from sim.world import build_world
    from torm.pipeline import CaptureSettings, SegmentationSettings, TrialConfig, run_trial

    world = build_world("rw3", 0, robot="inovo_2f85")
    real = [world.object_pose(o.instance_id)[:3, 3] for o in world.objects]
    x, y = _free_spot(real, [(0.55, 0.15), (0.55, -0.15), (0.45, 0.12), (0.65, -0.12)], clearance=0.12)
    config = TrialConfig(scenario="rw3", seed=0, method="torm", capture=CaptureSettings(n_views=24),
                         segmentation=SegmentationSettings("gt", options={"phantoms": [[x, y, 0.03, 0.03]]}))
    rec = run_trial(config, backend=SimBackend(world))
    assert rec["n_objects"] == 2 and rec["n_success"] == 2, rec["summary"]
    assert rec["n_spurious"] == 1 and rec["n_phantom_attempts"] == 1, rec["attempts"]
    (ph,) = [a for a in rec["attempts"] if a["outcome"] == "phantom_attempt"]
    assert ph["matched_object"] is None and ph["target_object"] is None
    assert ph["loop_outcome"] != "phantom_attempt"  # the robot itself cannot know
    assert "not there" in ph["message"] and "disturbed_m" in ph["pick"]
    assert rec["spurious_objects"][0]["label"] == ph["label"]
    assert rec["summary"]["phantom_attempts"] == 1


def test_table_height_from_the_capture_is_used_and_recorded():
    from torm.pipeline import CaptureSettings, TrialConfig, run_trial

    rec = run_trial(TrialConfig(scenario="rw1", seed=0, method="oracle", table="capture",
                                capture=CaptureSettings(n_views=8, depth_model="statistical")))
    table = rec["perception"]["table"]
    assert table["source"] == "capture" and abs(table["height_m"]) < 0.002, table
    assert rec["n_success"] == 1


def test_the_real_backend_declares_table_and_fixtures_from_its_hardware_config():
    from torm.hardware.config import HardwareConfig, RealCaptureSettings

    hw = HardwareConfig(host="10.0.0.2", capture=RealCaptureSettings(table_height=0.012, table_height_error=0.0005),
                        fixtures=({"name": "rack", "pose": [0.5, 0.0, 0.012, 0.0],
                                   "boxes": [[[0, 0, 0.03], [0.1, 0.02, 0.03]]]},))
    cal = hw.calibration()
    assert cal.table_height == 0.012 and cal.table_height_error == 0.0005 and cal.source == "hardware config"
    assert [f.name for f in cal.fixtures] == ["rack"] and cal.obstacle_points()[:, 2].max() == pytest.approx(0.072)
    with pytest.raises(ConfigError, match="unknown keys"):
        HardwareConfig(host="10.0.0.2", fixtures=({"name": "rack", "mesh_file": "x.stl"},))


def test_observer_group_forwards_each_event_to_every_observer_that_has_it():
    from torm.execution.observer import ObserverGroup

    seen: list[tuple[str, str]] = []

    class Judge:
        def phase_started(self, name):
            seen.append(("judge", name))

        def perceived(self, clouds):
            seen.append(("judge", "perceived"))

    class Logger:
        def phase_started(self, name):
            seen.append(("logger", name))

    group = ObserverGroup(Judge(), None, Logger())
    group.phase_started("lift")
    group.perceived([])
    assert seen == [("judge", "lift"), ("logger", "lift"), ("judge", "perceived")]
    assert not hasattr(group, "attempt_ended") and not hasattr(group, "ground_truth")
