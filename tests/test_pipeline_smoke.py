"""Closed-loop smoke trials through the pytest plugin (the same way a lab guards its own changes)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from torm.errors import ConfigError, UnknownNameError


@pytest.mark.torm_smoke(scenario="rw1", seed=0, method="oracle", min_success=1.0)
def test_oracle_picks_single_cylinder(torm_smoke_result):
    rec = torm_smoke_result
    assert rec["n_objects"] == 1 and rec["objects"][0]["name"] == "cylinder"
    pick = rec["objects"][0]["pick"]
    assert pick["judgement"]["lift_m"] >= 0.24 and pick["judgement"]["translation_m"] >= 0.18
    for stage in ("capture", "grasp_planning", "execution", "total"):
        assert rec["timings"][stage] >= 0


@pytest.mark.torm_smoke(scenario="rw3", seed=0, method="torm", min_success=1.0)
def test_torm_reconstruction_trial_picks_both_objects(torm_smoke_result):
    rec = torm_smoke_result
    per = rec["perception"]
    assert per["n_objects_found"] == per["n_objects_present"] == 2
    assert per["chamfer_mm_mean"] < 5.0


def test_torm_trial_factory_reports_not_reconstructed_for_blank_masks(torm_trial):
    # Every mask missing in every view: the reconstruction fails and is recorded, not raised.
    rec = torm_trial("rw1", method="torm", overrides=["segmentation.segmenter=noisy",
                                                       "segmentation.options={preset: none, overrides: "
                                                       "{p_missing_view: 1.0}}"])
    assert rec["objects"][0]["outcome"] == "not_reconstructed"
    assert rec["failure"] == "reconstruction_failed"


def test_bad_trial_configs_name_the_problem():
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig

    with pytest.raises(UnknownNameError, match="'magic'; valid choices: depth, depth_fusion, oracle, "
                                               "package.module:callable, torm"):
        cfgmod.from_dict(TrialConfig, {}, ["method=magic"])
    with pytest.raises(UnknownNameError, match="valid choices: difference, grounded_sam, gt, learned, noisy"):
        cfgmod.from_dict(TrialConfig, {}, ["segmentation.segmenter=sam3"])
    with pytest.raises(ConfigError, match="unknown key"):
        cfgmod.from_dict(TrialConfig, {}, ["reconstruction.grid_rez=3"])


@pytest.mark.torm_smoke(scenario="rw2", seed=0, method="depth", min_success=1.0)
def test_depth_baseline_grasps_the_opaque_cup(torm_smoke_result):
    assert torm_smoke_result["objects"][0]["name"] == "opaque_cup"


def test_depth_baseline_fails_on_glass_because_sensor_depth_sees_through_it(torm_trial):
    rec = torm_trial("rw1", method="depth")
    # The D455-like depth passes through the glass: the points lie on the table, far from the cylinder.
    assert rec["objects"][0]["outcome"] != "success"
    assert rec["perception"]["chamfer_mm_mean"] > 10.0


def test_symmetric_completion_recovers_the_back_of_a_cylinder():
    import numpy as np

    from torm.perception import complete_by_symmetry

    rng = np.random.default_rng(0)
    # Front half of a vertical cylinder (r 3 cm, axis at (0.5, 0)) seen from a camera at (0, 0, 0.3).
    a = rng.uniform(np.pi / 2, 3 * np.pi / 2, 2000)
    z = rng.uniform(0, 0.1, 2000)
    pts = np.stack([0.5 + 0.03 * np.cos(a), 0.03 * np.sin(a), z], axis=1)
    nrm = np.stack([np.cos(a), np.sin(a), 0 * a], axis=1)
    full, full_n = complete_by_symmetry(pts, nrm, np.array([0.0, 0.0, 0.3]))
    assert len(full) == 4000
    assert np.allclose(full[:, :2].mean(axis=0), [0.5, 0.0], atol=2e-3)
    back = full[2000:]
    assert np.all(back[:, 0] > 0.5 - 1e-9)  # the mirrored half lies behind the axis
    assert np.allclose(np.linalg.norm(full_n, axis=1), 1.0)


def test_re_perceive_captures_again_before_each_later_pick(torm_trial):
    rec = torm_trial("rw3", method="oracle", overrides=["re_perceive=true"])
    assert rec["n_perceptions"] == rec["n_objects"] == 2
    assert rec["success_rate"] == 1.0


def test_trial_writes_a_rerun_recording(tmp_path):
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig, run_trial
    from torm.testing.plugin import SMOKE_OVERRIDES

    cfg = cfgmod.from_dict(TrialConfig, {}, [*SMOKE_OVERRIDES, "scenario=rw1", "method=oracle"])
    rec = run_trial(cfg, record=str(tmp_path / "trial.rrd"))
    assert rec["success_rate"] == 1.0
    assert list(rec)[0] == "summary" and list(rec)[-1] == "config"  # headline first, resolved config last
    assert rec["summary"]["success"] == "1/1" and rec["summary"]["outcomes"] == {"1:cylinder": "success"}
    assert (tmp_path / "trial.rrd").stat().st_size > 10_000  # capture, meshes, grasps and the motion
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    temporal: dict[str, int] = {}
    for chunk in RrdReader(tmp_path / "trial.rrd").stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        if not chunk.is_static:
            temporal[chunk.entity_path] = temporal.get(chunk.entity_path, 0) + chunk.num_rows
    assert "/outcome" in rows and "/world/reconstruction/object_0" in rows and "/world/grasps/object_0" in rows
    assert temporal.get("/world/scene/object_1_cylinder", 0) > 50  # the true object moves with physics
    robot = [e for e in rows if e.startswith("/world/scene/") and "/geom_" in e]
    assert len(robot) > 5 and not any(e in temporal for e in robot)  # robot geometry logged once
    assert temporal.get("/world/scene/link1", 0) > 50 and "/world/scene/base" not in temporal  # fixed base: once
    # growing paths are logged once (static); per step only transforms and the TCP point
    assert rows["/world/motion/tcp_path"] == 1 and "/world/motion/tcp_path" not in temporal
    assert temporal["/world/motion/tcp"] > 50
    # docs/recordings.md's entity tree: every documented path exists, as documented static or temporal
    for pattern, kind in _documented_entities():
        hits = [e for e in rows if pattern.fullmatch(e)]
        assert hits, f"docs/recordings.md lists {pattern.pattern}, which the recording lacks"
        if kind == "temporal":
            assert any(e in temporal for e in hits), f"{pattern.pattern} is documented temporal"
        else:
            assert not any(e in temporal for e in hits), f"{pattern.pattern} is documented static"
    placeholders = {"<iii>": r"\d{3}", "<k>": r"\d+", "<g>": r"\d+", "<name>": r"[a-z0-9_]+", "<body>": r"[a-z0-9_]+"}
    logged = [e for e in rows if e.startswith(("/world/", "/signals/", "/events", "/outcome"))]
    documented = [p for p, _ in _documented_entities(placeholders)]
    missing = [e for e in logged if not any(p.fullmatch(e) for p in documented)]
    assert not missing, f"entities docs/recordings.md does not list: {missing}"


def _documented_entities(placeholders: dict[str, str] | None = None) -> list[tuple[re.Pattern, str]]:
    """(path pattern, 'static' | 'temporal') of each line of docs/recordings.md's entity tree."""
    placeholders = placeholders or {"<iii>": r"\d{3}", "<k>": r"\d+", "<g>": r"\d+", "<name>": r"[a-z0-9_]+",
                                    "<body>": r"(link\d|gripper_[a-z_]+)"}
    text = (Path(__file__).resolve().parents[1] / "docs" / "recordings.md").read_text()
    block = text.split("<!-- entity-tree")[1].split("```text\n", 1)[1].split("```", 1)[0]
    out = []
    for line in block.strip().splitlines():
        path, kind = line.split()[:2]
        rx = re.escape(path)
        for ph, sub in placeholders.items():
            rx = rx.replace(re.escape(ph), sub)
        out.append((re.compile(rx), kind))
    return out


@pytest.mark.torm_smoke(scenario="syn11", seed=0, method="oracle", min_success=1.0)
def test_dense_scene_places_every_object_on_free_table(torm_smoke_result):
    # Eight objects: each drop-off must avoid the objects still there and the ones already put down.
    picks = [o["pick"] for o in torm_smoke_result["objects"]]
    assert len(picks) == 8 and not any(p["neighbours_disturbed"] for p in picks)
