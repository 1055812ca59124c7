"""The realism profile: seeded draws inside sourced ranges, recorded in the trial; what each factor changes in the
world, the cameras and the arm; a slipping negative control; ``ideal`` reproduces the world without realism."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

from sim.backend import SimBackend
from sim.cameras.rig import CameraRigConfig
from sim.realism import (
    FACTORS,
    MEASURED,
    PROFILES,
    SOURCES,
    ExecutionErrors,
    RealismRecord,
    perturb_capture,
    sample_realism,
)
from sim.world import build_world
from torm import config as cfgmod
from torm.errors import ConfigError, UnknownNameError
from torm.pipeline import REALISM_FACTORS, REALISM_PROFILES, TrialConfig, run_trial, trial_context

SMALL_CAPTURE = ["capture.n_views=3", "capture.scale=0.2"]


def _trial(scenario: str, seed: int, realism: str = "ideal", extra: tuple[str, ...] = (), backend=None) -> dict:
    cfg = cfgmod.from_dict(TrialConfig, {"scenario": scenario, "seed": seed, "method": "oracle"},
                           [*SMALL_CAPTURE, f"world.realism={realism}", *extra])
    return run_trial(cfg, backend=backend)


def test_names_match_the_pipeline():
    assert PROFILES == REALISM_PROFILES and FACTORS == REALISM_FACTORS


def test_draws_are_seeded_inside_their_ranges_and_factor_independent():
    hollow = [True, False]
    a = sample_realism("measured", 7, hollow)
    assert a == sample_realism("measured", 7, hollow)
    assert a != sample_realism("measured", 8, hollow)
    r = MEASURED
    assert r.pad_friction.contains(a.pad_friction) and r.object_friction.contains(a.object_friction)
    assert r.pad_torsion_lever.contains(a.pad_torsional / a.pad_friction)
    assert r.grip_force.contains(a.grip_force_n)
    assert r.hollow_mass_scale.contains(a.object_mass_scale[0]) and a.object_mass_scale[1] == 1.0
    assert r.hand_eye_rotation.contains(float(np.linalg.norm(a.hand_eye_rotvec)))
    assert r.hand_eye_translation.contains(float(np.linalg.norm(a.hand_eye_translation)))
    assert r.arm_repeatability.contains(a.arm_repeatability_m)
    assert r.focal_error.contains(a.focal_scale - 1.0)
    assert all(r.principal_point_error.contains(v) for v in a.principal_point_offset_px)
    assert r.latency.contains(a.latency_s)
    assert a.joint_error_std_rad == pytest.approx(a.arm_repeatability_m / 3 / 1.083)
    # one factor alone draws the same values as in the full profile; the others stay ideal
    c = sample_realism("measured", 7, hollow, factors=("contact",))
    assert (c.pad_friction, c.object_friction) == (a.pad_friction, a.object_friction)
    assert c.grip_force_n is None and c.hand_eye_rotvec is None and c.latency_s is None and c.factors == ("contact",)
    e = sample_realism("measured", 7, hollow, factors=("execution",))
    assert e.latency_s == a.latency_s and e.focal_scale is None
    assert sample_realism("ideal", 7, hollow).is_ideal


def test_every_range_is_sourced_and_documented():
    doc = (Path(__file__).resolve().parents[1] / "sim" / "REALISM.md").read_text()
    for row in MEASURED.table():
        assert row["source"] in SOURCES.values()
        assert f"`{row['parameter']}`" in doc, f"sim/REALISM.md does not list {row['parameter']}"


def test_bad_names_are_rejected():
    with pytest.raises(UnknownNameError, match="valid choices: ideal, measured"):
        cfgmod.from_dict(TrialConfig, {}, ["world.realism=lab"])
    with pytest.raises(UnknownNameError, match="world.factors entry"):
        cfgmod.from_dict(TrialConfig, {}, ["world.factors=[friction]"])
    with pytest.raises(ConfigError, match="twice"):
        cfgmod.from_dict(TrialConfig, {}, ["world.factors=[contact, contact]"])
    with pytest.raises(UnknownNameError):
        sample_realism("measured", 0, factors=("nope",))


def test_trial_context_names_the_factor_groups():
    cfg = cfgmod.from_dict(TrialConfig, {}, ["world.realism=measured", "world.factors=[contact, execution]"])
    assert trial_context(cfg)["realism"] == "measured[contact+execution]"


def test_bench_trials_default_to_measured():
    from torm.bench.spec import TrialSpec
    from torm.bench.trial import trial_config

    spec = TrialSpec("rw", "rw1", 0, "oracle", 5, "rw/rw1/0/oracle", ("cylinder",))
    assert trial_config(spec).world.realism == "measured"
    assert trial_config(spec, ("world.realism=ideal",)).world.realism == "ideal"
    assert cfgmod.from_dict(TrialConfig, {}).world.realism == "ideal"  # a single trial stays ideal


def test_physics_values_reach_the_model():
    rec = dataclasses.replace(sample_realism("measured", 3, [True, False]), object_mass_scale=(1.05, 1.0))
    w0 = build_world("rw5", seed=1)  # ball, opaque cup (hollow)
    w = build_world("rw5", seed=1, realism=rec)
    m = w.model
    assert len(w.robot_ids.pads) >= 2
    for g in w.robot_ids.pads:
        assert m.geom_friction[g, 0] == pytest.approx(rec.pad_friction)
        assert m.geom_friction[g, 1] == pytest.approx(rec.pad_torsional)
    for o in w.objects:
        for g in o.collision_geom_ids:
            assert m.geom_friction[g, 0] == pytest.approx(rec.object_friction)
    assert m.geom_friction[m.geom("table").id, 0] == pytest.approx(rec.object_friction)
    b1, b0 = w.objects[0].body_id, w0.objects[0].body_id
    assert m.body_mass[b1] == pytest.approx(1.05 * w0.model.body_mass[b0])
    assert np.allclose(m.body_inertia[b1], 1.05 * w0.model.body_inertia[b0])
    assert w.objects[0].mass == pytest.approx(1.05 * w0.objects[0].mass)


def test_ideal_record_builds_the_same_world():
    a = build_world("rw4", seed=2)
    b = build_world("rw4", seed=2, realism=sample_realism("ideal", 2))
    assert np.array_equal(a.data.qpos, b.data.qpos)
    assert np.array_equal(a.model.geom_friction, b.model.geom_friction)
    assert np.array_equal(a.model.body_mass, b.model.body_mass)


def test_reported_cameras_carry_the_calibration_error_and_the_images_do_not():
    from sim.cameras.rig import SimCameraRig

    w = build_world("rw1", seed=0, robot=None)
    with SimCameraRig.from_world(w, CameraRigConfig(n_views=4, scale=0.2)) as rig:
        cap = rig.capture()
    rec = sample_realism("measured", 11, [False], factors=("calibration",))
    rep, summary = perturb_capture(rec, cap, 0)
    T_err = rec.T_cam_err
    for v0, v1 in zip(cap.views, rep.views, strict=True):
        assert v1.rgb is v0.rgb and v1.mask is v0.mask  # same pixels, rendered with the true camera
        rel = np.linalg.inv(v0.T_world_cam @ T_err) @ v1.T_world_cam  # what is left is the per-view jitter
        assert np.linalg.norm(rel[:3, 3]) < 6 * rec.arm_repeatability_m
        assert v1.K[0, 0] == pytest.approx(v0.K[0, 0] * rec.focal_scale)
        assert v1.K[0, 2] - v0.K[0, 2] == pytest.approx(rec.principal_point_offset_px[0] * v0.width / 1280)
    err = np.linalg.inv(cap.views[0].T_world_cam) @ rep.views[0].T_world_cam
    assert 1e3 * np.linalg.norm(err[:3, 3]) == pytest.approx(1e3 * np.linalg.norm(rec.hand_eye_translation), abs=0.05)
    assert summary["views"] == 4 and 0 < summary["view_jitter_rms_mm"] < 0.2
    again, _ = perturb_capture(rec, cap, 0)
    assert np.array_equal(again.views[2].T_world_cam, rep.views[2].T_world_cam)  # seeded by (seed, capture)
    same, s = perturb_capture(sample_realism("ideal", 11), cap, 0)
    assert same is cap and s == {}


def _joint_move(backend, dq: float = 0.05, duration: float = 0.3):
    arm = backend.arm.inner
    q0 = arm.state().q
    goal = q0.copy()
    goal[0] += dq
    t = np.linspace(0.01, duration, 30)
    qs = q0 + np.outer(t / duration, goal - q0)
    return q0, goal, qs, t


def test_latency_delays_the_arm_and_joint_error_offsets_it():
    world = build_world("rw1", seed=0)
    rec = RealismRecord(profile="measured", seed=4, factors=("execution",), latency_s=0.02, joint_error_std_rad=0.0)
    b = SimBackend(world, realism=rec)
    assert isinstance(b._sim.execution, ExecutionErrors) and b._sim.execution.delay_ticks == 10
    arm = b.arm.inner
    q0, goal, qs, t = _joint_move(b)
    moved_at = []
    b.add_step_callback(lambda s: moved_at.append(s) if arm.state().q[0] - q0[0] > 0.025 else None)
    t0 = b.clock.now()
    arm.follow_trajectory(t, qs)
    delayed_half = moved_at[0] - t0  # when the arm is half way
    assert np.allclose(arm.target(), goal)  # the command, not what the servo tracks
    assert abs(arm.state().q[0] - goal[0]) < 2e-3
    plain = SimBackend(build_world("rw1", seed=0))
    arm2 = plain.arm.inner
    moved2 = []
    plain.add_step_callback(lambda s: moved2.append(s) if arm2.state().q[0] - q0[0] > 0.025 else None)
    t1 = plain.clock.now()
    arm2.follow_trajectory(t, qs)
    assert delayed_half - (moved2[0] - t1) == pytest.approx(0.02, abs=0.004)
    # a static joint error: the arm settles off the command by the drawn error
    rec2 = RealismRecord(profile="measured", seed=4, factors=("execution",), latency_s=0.0, joint_error_std_rad=0.01)
    b3 = SimBackend(build_world("rw1", seed=0), realism=rec2)
    arm3 = b3.arm.inner
    arm3.follow_trajectory(t, qs)
    e = b3._sim.execution._e_to
    assert np.linalg.norm(e) > 0.005
    assert np.allclose(arm3.state().q - goal, e, atol=2.5e-3)
    assert b3.realism_summary()["execution"]["motions"] == 1


def test_trial_record_holds_the_drawn_values_and_the_pick_uses_the_drawn_force():
    rec = _trial("rw1", 5, "measured")
    r = rec["realism"]
    drawn = sample_realism("measured", 5, [False])
    assert r["profile"] == "measured" and r["pad_friction"] == pytest.approx(drawn.pad_friction)
    assert r["grip_force_n"] == pytest.approx(drawn.grip_force_n)
    assert r["applied"]["captures"][0]["views"] == 3 and r["applied"]["execution"]["motions"] > 3
    assert rec["context"]["realism"] == "measured"
    # the saved config holds the force the pick used; config_used says what replaced what (issue 42)
    assert rec["config"]["pick"]["grip_force"] == pytest.approx(drawn.grip_force_n)
    used = rec["config_used"]["pick.grip_force"]
    assert used["configured"] == 130.0 and used["used"] == pytest.approx(drawn.grip_force_n)


def test_ideal_reproduces_the_world_without_realism():
    a = _trial("rw1", 3, "ideal")
    cfg = cfgmod.from_dict(TrialConfig, {"scenario": "rw1", "seed": 3, "method": "oracle"}, SMALL_CAPTURE)
    b = run_trial(cfg, backend=SimBackend(build_world("rw1", 3),
                                          camera_config=CameraRigConfig(n_views=3, scale=0.2)))
    ja, jb = a["objects"][0]["pick"]["judgement"], b["objects"][0]["pick"]["judgement"]
    assert a["objects"][0]["outcome"] == b["objects"][0]["outcome"] == "success"
    assert ja == jb  # identical physics: the same lift, translation and slip to the last digit


def _pick_with(record: RealismRecord, seed: int = 0) -> str:
    world = build_world("rw1", seed, realism=record)
    backend = SimBackend(world, camera_config=CameraRigConfig(n_views=3, scale=0.2), realism=record)
    cfg = cfgmod.from_dict(TrialConfig, {"scenario": "rw1", "seed": seed, "method": "oracle"}, SMALL_CAPTURE)
    return run_trial(cfg, backend=backend)["objects"][0]["outcome"]


def test_negative_control_slips_and_the_measured_range_holds_the_heavy_cylinder():
    from sim.scenes.objects import get_object

    assert get_object("cylinder").mass > 0.7  # solid soda-lime glass, r 30 mm, h 100 mm
    slippery = RealismRecord(profile="measured", seed=0, factors=("contact", "grip_force"), pad_friction=0.1,
                             pad_torsional=0.0005, object_friction=0.4, grip_force_n=20.0)
    assert _pick_with(slippery) in ("slipped_during_lift", "dropped_during_translation")
    held = [_pick_with(sample_realism("measured", s, [False], factors=("contact", "grip_force")), s) for s in range(5)]
    assert sum(o == "success" for o in held) >= 4, held


def test_record_validation():
    with pytest.raises(ConfigError):
        RealismRecord(profile="measured", pad_friction=-0.1)
    with pytest.raises(UnknownNameError):
        RealismRecord(profile="lab")
    assert RealismRecord().is_ideal and np.array_equal(RealismRecord().T_cam_err, np.eye(4))
    d = sample_realism("measured", 1, [True]).as_dict()
    assert math.isclose(d["hand_eye_rotation_deg"], math.degrees(np.linalg.norm(d["hand_eye_rotvec"])))
    assert mujoco is not None


def test_stress_profile_pushes_each_factor_beyond_the_worst_sourced_value():
    from sim.realism import MEASURED, sample_realism
    from torm.pipeline import WorldSettings

    x1, x2 = MEASURED.stressed(1), MEASURED.stressed(2)
    assert x1.pad_friction.lo == x1.pad_friction.hi == MEASURED.pad_friction.lo  # x1 = worst sourced end
    assert x2.pad_friction.lo == pytest.approx(MEASURED.pad_friction.lo / 2)  # lower is worse: halved
    assert x2.grip_force.lo == pytest.approx(10.0)
    assert x2.hand_eye_translation.lo == pytest.approx(2 * MEASURED.hand_eye_translation.hi)  # higher is worse
    assert x2.hollow_mass_scale.lo == pytest.approx(1.10)  # the deviation from 1 doubles
    rec = sample_realism("stress", 3, [True], ("contact",), stress=4.0)
    assert rec.profile == "stress" and rec.stress == 4.0 and rec.factors == ("contact",)
    assert rec.pad_friction == pytest.approx(0.075) and rec.object_friction == pytest.approx(0.10)
    assert rec.grip_force_n is None and rec.hand_eye_translation is None  # other groups stay ideal
    with pytest.raises(ConfigError, match=">= 1"):
        MEASURED.stressed(0.5)
    with pytest.raises(ConfigError, match="only applies with world.realism=stress"):
        WorldSettings(realism="measured", stress=2.0)
    with pytest.raises(ConfigError, match=">= 1"):
        WorldSettings(realism="stress", stress=0.0)


def test_declared_calibration_is_measured_with_a_sourced_error_under_measured_and_exact_under_ideal():
    """Under ``measured`` the table height and a fixture's pose the loop is told differ from the truth by the
    record's tape-measure draws (within their sourced ranges); under ``ideal`` they equal it. The trial record keeps
    declared, true and error."""
    from sim.realism import sample_scenario_realism

    r = MEASURED
    rec = sample_realism("measured", 4, [False])
    assert r.table_height_error.contains(rec.table_height_error_m) and rec.table_height_error_m != 0.0
    dx, dy, dyaw = rec.fixture_error
    assert r.fixture_position_error.contains(dx) and r.fixture_position_error.contains(dy)
    assert r.fixture_yaw_error.contains(dyaw)
    assert math.degrees(r.fixture_yaw_error.hi) == pytest.approx(1.1458, abs=1e-3)
    # the earlier calibration draws are unchanged by the new ones (their own stream)
    assert sample_realism("measured", 4, [False], factors=("calibration",)).focal_scale == rec.focal_scale

    def backend(realism: str, seed: int) -> SimBackend:
        rrec = sample_scenario_realism(realism, "lab4", seed)
        world = build_world("lab4", seed, realism=rrec)
        return SimBackend(world, camera_config=CameraRigConfig(n_views=2, scale=0.2), realism=rrec)

    for seed in (0, 1):
        b = backend("measured", seed)
        try:
            cal, truth = b.calibration(), b.calibration_record()
            rec = b.realism
            assert truth["table_height_m"]["error"] == pytest.approx(rec.table_height_error_m, abs=1e-12)
            assert cal.table_height == pytest.approx(truth["table_height_m"]["true"] + rec.table_height_error_m)
            assert cal.table_height_error == pytest.approx(1e-3)
            Td, Tt = cal.fixtures[0].T_world_fixture, b.world.fixture.T_world_fixture
            assert not np.allclose(Td, Tt)
            np.testing.assert_allclose(Td[:2, 3] - Tt[:2, 3], rec.fixture_error[:2], atol=1e-12)
            assert truth["fixture"]["error_yaw_rad"] == pytest.approx(rec.fixture_error[2], abs=1e-9)
        finally:
            b.close()
    b = backend("ideal", 0)
    try:
        cal, truth = b.calibration(), b.calibration_record()
        assert cal.table_height == truth["table_height_m"]["true"] and cal.table_height_error == 0.0
        np.testing.assert_array_equal(cal.fixtures[0].T_world_fixture, b.world.fixture.T_world_fixture)
    finally:
        b.close()
