"""Bad inputs, table-driven: every size bounded, every absurd value refused by name, before any work starts.

Two tables:

- every config field that carries a :class:`torm.config.Range` (derived, not listed by hand: a new bounded
  field is tested without editing this file) is refused above and below its range and, for floats, as NaN;
- command lines a careless user types (issue 59's list and more of our own), each a usage or config error:
  exit status 2 and a message naming the flag or key. None may reach the capture (a monkeypatched backend
  factory fails the test if one does).
"""

from __future__ import annotations

import math

import pytest

from torm.config import bounded_fields, from_dict
from torm.errors import ConfigError
from torm.pipeline import TrialConfig

BOUNDED = bounded_fields(TrialConfig)


def _outside(key: str) -> list[tuple[str, str]]:
    rng = BOUNDED[key]
    out = []
    if rng.hi is not None:
        out += [(key, str(rng.hi + 1)), (key, "1e12")]
    if rng.lo is not None:
        out += [(key, str(rng.lo - 1))]
    return out


CONFIG_CASES = [case for key in sorted(BOUNDED) for case in _outside(key)]


def test_the_size_knobs_of_issue_59_carry_bounds():
    for key in ("reconstruction.points_per_object", "grasp.n_samples", "grasp.n_approach_angles",
                "pick.ik.max_iters", "reconstruction.mask_res", "reconstruction.dmtet.iterations"):
        assert key in BOUNDED and BOUNDED[key].hi is not None, key
    assert len(CONFIG_CASES) >= 50


@pytest.mark.parametrize(("key", "value"), CONFIG_CASES, ids=[f"{k}={v}" for k, v in CONFIG_CASES])
def test_a_value_outside_a_bounded_field_is_refused_by_name(key, value):
    with pytest.raises(ConfigError, match=rf"{key.split('.')[-1]}=.*outside its valid range"):
        from_dict(TrialConfig, {}, [f"{key}={value}"])


def test_the_bound_holds_for_configs_built_in_python():
    from torm.grasp.planner import GraspPlannerConfig

    with pytest.raises(ConfigError, match="n_samples"):
        GraspPlannerConfig(n_samples=10**12)
    assert GraspPlannerConfig(n_samples=65_536).n_samples == 65_536  # the bound itself is valid


def test_a_carve_that_does_not_fit_is_refused_before_it_starts(monkeypatch):
    import numpy as np

    import torm.resources
    from torm.reconstruction.carve import carve_visual_hull

    monkeypatch.setattr(torm.resources, "available_memory_bytes", lambda: 16 << 30)  # whatever this machine has

    eye_k, eye_t = np.repeat(np.eye(3)[None], 2, 0), np.repeat(np.eye(4)[None], 2, 0)
    with pytest.raises(ConfigError, match=r"carve at 1024 voxels \(1024 x 1024 x 1024\) needs about 96 GiB.*carve_res"):
        carve_visual_hull(np.ones((2, 10, 10)), eye_k, eye_t, np.array([[0, 0, 0], [1, 1, 1.0]]), 1024)


def test_the_grasp_planner_refuses_a_plan_that_does_not_fit_before_sampling():
    import numpy as np

    from torm.grasp.planner import GraspPlannerConfig, plan_grasps
    from torm.resources import grasp_bytes
    from torm.types import ObjectPointCloud

    cloud = ObjectPointCloud(np.zeros((8, 3)), np.tile([1.0, 0.0, 0.0], (8, 1)), 0)
    cfg = GraspPlannerConfig(n_samples=65_536, n_approach_angles=360, use_meshes=False)
    assert grasp_bytes(20, 65_536, 360, 4) > 1 << 40  # a TiB: no machine here has it
    with pytest.raises(ConfigError, match=r"grasp.n_samples=65536 x grasp.n_approach_angles=360.*lower"):
        plan_grasps([cloud] * 20, config=cfg)


# ---------------------------------------------------------------------------------------------------------------
# Command lines
# ---------------------------------------------------------------------------------------------------------------
def _trial(*sets: str) -> list[str]:
    return ["trial", "--scenario", "rw1"] + [a for s in sets for a in ("--set", s)]


#: (argv, a fragment the error must contain). ``{file}``: a plain file; ``{run}``: an empty folder.
CLI_CASES: list[tuple[list[str], str]] = [
    # issue 59's list
    (_trial("reconstruction.points_per_object=1e12"), "points_per_object"),
    (_trial("grasp.n_samples=1e12"), "n_samples"),
    (_trial("grasp.n_samples=1e8"), "n_samples"),
    (_trial("grasp.n_approach_angles=1e9"), "n_approach_angles"),
    (_trial("grasp.n_approach_angles=1e7"), "n_approach_angles"),
    (["scenes", "show", "--scenario", "rw1", "--views", "100000000", "--out", "{run}/v"], "--views"),
    (["report", "{run}", "--out", "{file}/sub"], "--out"),
    (_trial("pick.transit_height=0.95", "pick.ik.max_iters=1000000000000"), "max_iters"),
    (_trial("success.translation=1e9"), "success.translation"),
    (_trial("reconstruction.mask_res=1e6"), "mask_res"),
    (["reconstruct", "{run}", "--table-z", "nan"], "--table-z"),
    (["scenes", "check", "--seeds", "-1"], "--seeds"),
    # sizes and iteration counts
    (_trial("reconstruction.hull_mask_res=100000"), "hull_mask_res"),
    (_trial("reconstruction.refine_iters=1e9"), "refine_iters"),
    (_trial("reconstruction.dmtet.iterations=1e9"), "iterations"),
    (_trial("reconstruction.dmtet.views_per_batch=100000"), "views_per_batch"),
    (_trial("reconstruction.dmtet.mlp_hidden=1e6"), "mlp_hidden"),
    (_trial("reconstruction.dmtet.mlp_layers=1000"), "mlp_layers"),
    (_trial("reconstruction.dmtet.eikonal_points=1e9"), "eikonal_points"),
    (_trial("reconstruction.dmtet.mask_res=1e5"), "mask_res"),
    (_trial("reconstruction.grid_res=100000"), "grid_res"),
    (_trial("reconstruction.carve_res=1e6"), "carve_res"),
    (_trial("reconstruction.points_per_object=0"), "points_per_object"),
    (_trial("reconstruction.max_band_cells=1e12"), "max_band_cells"),
    (_trial("capture.n_views=1000000000"), "n_views"),
    (_trial("capture.pbr.spp=1e9"), "spp"),
    (_trial("capture.pbr.max_depth=1e9"), "max_depth"),
    (_trial("grasp.top_k=1e9"), "top_k"),
    (_trial("grasp.batch_size=1e12"), "batch_size"),
    (_trial("grasp.batch_size=0"), "batch_size"),
    (_trial("grasp.n_samples=0"), "n_samples"),
    (_trial("grasp.depths=[" + ", ".join(["0.01"] * 65) + "]"), "depths"),
    (_trial("pick.max_candidates=1e9"), "max_candidates"),
    (_trial("pick.ik.max_iters=0"), "max_iters"),
    # absurd values
    (_trial("success.lift_height=10"), "success.lift_height"),
    (_trial("success.translation=-1"), "SuccessCriteria"),
    (_trial("pick.speed_scale=2"), "speed_scale"),
    (_trial("pick.grip_speed=0"), "grip_speed"),
    (_trial("pick.transit_height=-1"), "transit_height"),
    (_trial("pick.control_dt=0"), "control_dt"),
    (_trial("pick.lift_height=inf"), "lift_height"),
    (_trial("grasp.friction_coef=nan"), "friction_coef"),
    (_trial("grasp.friction_coef=-1"), "friction_coef"),
    (_trial("grasp.max_tilt_deg=1000"), "max_tilt_deg"),
    (_trial("reconstruction.vote_tolerance=2"), "vote_tolerance"),
    (_trial("reconstruction.bounds=[[0, 0, 0], [-1, 1, 1]]"), "bounds"),
    (_trial("reconstruction.table_z=nan"), "table_z"),
    (_trial("capture.scale=nan"), "scale"),
    (_trial("seed=-1"), "seed"),
    # names that do not exist
    (_trial("reconstruction.mode=nonsense"), "mode"),
    (_trial("grasp.nonsense=1"), "nonsense"),
    (_trial("capture.renderer=nonsense"), "renderer"),
    (_trial("segmentation.segmenter=nonsense"), "segmenter"),
    (_trial("world.realism=nonsense"), "realism"),
    (["trial", "--scenario", "nonsense"], "nonsense"),
    (["trial", "--method", "nonsense"], "nonsense"),
    (["trial", "--seed", "-1"], "--seed"),
    (["trial", "--seed", "nan"], "--seed"),
    (["trial", "--views", "0"], "--views"),
    (["trial", "--views", "1e3"], "--views"),
    (["trial", "--set", "nonsense"], "nonsense"),
    # float flags: NaN, inf and negative values refused by the flag's type
    (["scenes", "check", "--seconds", "nan"], "--seconds"),
    (["scenes", "check", "--seconds", "-1"], "--seconds"),
    (["scenes", "check", "--seconds", "inf"], "--seconds"),
    (["scenes", "show", "--scenario", "rw1", "--width", "0", "--out", "{run}/v"], "--width"),
    (["scenes", "show", "--scenario", "rw1", "--height", "100000", "--out", "{run}/v"], "--height"),
    (["scenes", "show", "--scenario", "rw1", "--views", "0", "--out", "{run}/v"], "--views"),
    (["scenes", "show", "--scenario", "rw1", "--out", "{file}/v"], "--out"),
    (["reconstruct", "{run}", "--table-z", "inf"], "--table-z"),
    (["reconstruct", "{run}", "--table-z", "-inf"], "--table-z"),
    (["reconstruct", "{run}", "--bounds", "nan", "0", "0", "1", "1", "1"], "--bounds"),
    (["reconstruct", "{run}", "--out", "{file}/sub"], "--out"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--timeout", "nan"], "--timeout"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--timeout", "-5"], "--timeout"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--timeout", "0"], "--timeout"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--stop-grace", "inf"], "--stop-grace"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--workers", "0"], "--workers"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--workers", "100000"], "--workers"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--trials", "0"], "--trials"),
    (["bench", "--suite", "rw", "--out", "{run}/b", "--trials", "-3"], "--trials"),
    (["bench", "--suite", "nonsense", "--out", "{run}/b"], "nonsense"),
    (["bench", "--suite", "rw", "--out", "{file}/b"], "--out"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--scale", "nan"], "--scale"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--scale", "0"], "--scale"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--scale", "-0.5"], "--scale"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--width", "100000"], "--width"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--width", "0"], "--width"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--height", "-1"], "--height"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--views", "0"], "--views"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--spp", "0"], "--spp"),
    (["capture", "--scenario", "rw1", "--out", "{run}/c", "--seed", "-2"], "--seed"),
    (["capture", "--scenario", "rw1", "--out", "{file}/c"], "--out"),
    (["calibrate", "hand-eye", "--images", "{run}", "--poses", "{file}", "--intrinsics", "{file}", "--out",
      "{run}/h", "--square", "nan"], "--square"),
    (["calibrate", "hand-eye", "--images", "{run}", "--poses", "{file}", "--intrinsics", "{file}", "--out",
      "{run}/h", "--marker", "-0.02"], "--marker"),
    (["calibrate", "hand-eye", "--images", "{run}", "--poses", "{file}", "--intrinsics", "{file}", "--out",
      "{file}/he.yaml"], "--out"),
    (["train-segmenter", "--out", "{file}/seg.onnx", "--set", "train.steps=1"], "--out"),
    (["train-segmenter", "--work", "{file}/w", "--set", "train.steps=1"], "--out"),
    (["import", "colmap", "{run}", "--out", "{run}/i", "--scale", "nan"], "--scale"),
    (["import", "colmap", "{run}", "--out", "{run}/i", "--scale", "0"], "--scale"),
]


def test_the_table_holds_more_than_a_hundred_bad_inputs():
    assert len(CLI_CASES) + len(CONFIG_CASES) >= 146


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test when a command gets as far as opening a backend (the refusal came too late)."""
    import torm.pipeline

    def refuse(*a, **k):
        raise AssertionError("the command started work before refusing its input")

    monkeypatch.setattr(torm.pipeline, "make_backend", refuse)


@pytest.mark.parametrize(("argv", "fragment"), CLI_CASES, ids=[" ".join(a[:6]) + f" [{i}]"
                                                               for i, (a, _) in enumerate(CLI_CASES)])
def test_a_bad_command_line_is_a_usage_error_naming_the_input(tmp_path, capsys, no_work, argv, fragment):
    from torm.cli import main

    afile = tmp_path / "afile"
    afile.write_text("x")
    run = tmp_path / "run"
    run.mkdir()
    argv = [a.replace("{file}", str(afile)).replace("{run}", str(run)) for a in argv]
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's own usage errors
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2, err[-1500:]
    assert "Traceback" not in err
    assert fragment in err, err[-1500:]


def test_a_transit_height_the_arm_cannot_reach_is_a_config_error_not_unreachable_objects():
    from sim.robots.config import load_robot_config
    from sim.robots.reach import check_transit_height

    rcfg = load_robot_config("inovo_2f85")
    box = [[0.33, -0.22, 0.0], [0.77, 0.22, 0.3]]
    with pytest.raises(ConfigError, match=r"pick.transit_height=1e\+06 m.*reaches no point"):
        check_transit_height(rcfg, box, 1e6)
    assert check_transit_height(rcfg, box, 0.0) == 1.0  # 0 disables the transit
    assert math.isclose(check_transit_height(rcfg, box, 0.25), 1.0)  # the default is reached everywhere


def test_a_base_inside_the_workspace_box_is_named():
    from sim.robots.reach import base_in_box

    box = [[0.33, -0.22, 0.0], [0.77, 0.22, 0.3]]
    assert base_in_box((0.0, 0.0, 0.0), box) == ""  # the Inovo cell: the base beside the box
    assert "x 0.33..0.77 m" in base_in_box((0.5, 0.0, 0.0), box)
