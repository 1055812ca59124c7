"""The reconstruction and segmentation benchmark scripts run end to end in --quick mode and write their files.

Each script runs in a subprocess on one tiny scene (12 views at 320x180, grid 32, a few DMTet steps) with its
capture cache and results in a temporary folder; the test checks the JSON/Markdown files, their keys and that
the numbers are physically sensible (GT masks reconstruct every object, IoU in [0, 1], input IoU 1 for the
``none`` preset and < 1 for ``paper``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, tmp: Path, *extra: str) -> None:
    env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl")
    cmd = [sys.executable, str(ROOT / "benchmarks" / script), "--quick", "--out", str(tmp / "out"),
           "--cache", str(tmp / "cache"), "--threads", "1", *extra]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, f"{script} failed:\n{res.stderr[-3000:]}"


@pytest.fixture(scope="module")
def recon_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("bench_recon")
    _run("reconstruction.py", tmp)
    return tmp / "out"


def test_reconstruction_quick_writes_tables(recon_out: Path) -> None:
    for name in ("reconstruction.json", "reconstruction.md", "reconstruction_curves.png",
                 "reconstruction_fast.json", "reconstruction_paper.json", "reconstruction_table1.json"):
        assert (recon_out / name).is_file(), name
    doc = json.loads((recon_out / "reconstruction.json").read_text())
    assert doc["chamfer_points"] >= 30_000
    fast = doc["parts"]["fast"]
    ctx = fast["context"]
    for key in ("versions", "threads", "machine", "date_utc", "contended", "args"):
        assert key in ctx
    assert ctx["args"]["quick"] is True and ctx["threads"] == 1
    (scene,) = fast["scenes"].values()
    gt = scene["gt"]
    assert gt["n_found"] == gt["n_present"] == scene["n_objects"] == 3
    assert 0.8 < gt["silhouette_iou_mean"] <= 1.0 and gt["silhouette_iou_min"] <= gt["silhouette_iou_mean"]
    assert 0.0 < gt["chamfer_mm"] < 10.0 and 0.5 < gt["volume_iou"] <= 1.0
    d = gt["depth"]
    assert 0.0 <= d["mae"] <= d["rmse"] and 0.0 <= d["delta_1.05"] <= d["delta_1.10"] <= d["delta_1.25"] <= 1.0
    assert 0.5 < d["coverage"] <= 1.0
    assert scene["corrupted"]["input_iou_mean"] < 1.0
    assert "corrupted_union" in scene
    summ = doc["summary"]
    assert {"fast_gt", "fast_corrupted", "depth", "table1"} <= set(summ)
    assert set(summ["table1"]) == {f"{c}/{r}" for c in ("init_lr0.1", "init_lr1", "envelope_GT", "envelope_Seg")
                                   for r in ("rescue", "no_rescue")}
    paper = doc["parts"]["paper"]["runs"]
    assert len(paper) == 1 and paper[0]["mode"] == "TORM-paper (DMTet-Multi)"
    assert paper[0]["config"]["rescue"] is False and paper[0]["config"]["param"] == "mlp"
    assert paper[0]["time_s"] > 0 and paper[0]["timings"]["total_cpu_s"] > 0
    runs = doc["parts"]["table1"]["runs"]
    assert len(runs) == 8 and {r["rescue"] for r in runs} == {True, False}
    for r in runs:
        assert r["ms_per_step"] > 0 and 0.0 <= r["silhouette_iou_mean"] <= 1.0 and r["config"]["param"] == "mlp"
        assert {"collapsed_at", "rescued_steps", "iou_last5_vs_supervision", "band_misses"} <= set(r)
        assert r["iou_last5_vs_supervision"] == 0.0 or r["collapsed_at"] < 0  # a collapse scores 0
    md = (recon_out / "reconstruction.md").read_text()
    for heading in ("Table I", "Table II", "Fast mode", "Timing", "TORM-paper (DMTet-Multi)", "TORM-fast"):
        assert heading in md


def test_segmentation_quick_writes_tables(tmp_path: Path) -> None:
    _run("segmentation.py", tmp_path)
    out = tmp_path / "out"
    doc = json.loads((out / "segmentation.json").read_text())
    assert (out / "segmentation.md").read_text().startswith("# Segmentation errors")
    assert {"context", "scenes", "summary", "chamfer_points"} <= set(doc)
    summ = doc["summary"]
    assert {"none", "paper", "none (union)", "paper (union)"} <= set(summ)
    assert summ["none"]["input_iou_mean"] == pytest.approx(1.0)
    assert summ["paper"]["input_iou_mean"] < 0.95
    assert summ["none"]["failed"] == 0 and summ["none"]["objects_found"] == "3/3"
    (scene,) = doc["scenes"].values()
    for r in scene["presets"].values():
        assert {"input_iou_mean", "input_iou_min", "n_present", "union"} <= set(r)


def test_recon_vs_carve_quick_writes_tables(tmp_path: Path) -> None:
    _run("recon_vs_carve.py", tmp_path, "--parts", "sim", "--carve-res", "32", "--open3d-res", "--ablation-scenes",
         "--corrupt-preset", "")
    out = tmp_path / "out"
    doc = json.loads((out / "recon_vs_carve.json").read_text())
    (scene,) = doc["scenes"].values()
    fast, carve = scene["methods"]["TORM-fast"], scene["methods"]["carve 32^3"]
    assert scene["n_heldout_views"] == 3 and scene["n_input_views"] == 12
    for m in (fast, carve):
        assert m["n_found"] == scene["n_objects"] and 0.5 < m["heldout_iou_mean"] <= 1.0 and m["time_s"] > 0
    assert fast["chamfer_mm"] < carve["chamfer_mm"]  # 32^3 voxels are coarse; the projective hull is not
    assert scene["best_carve"] == "carve 32^3" and doc["summary"]["scenes"] == 1
    md = (out / "recon_vs_carve.md").read_text()
    assert "TORM-fast (consensus + narrow-band projective hull)" in md and "best carve" in md


def test_seg_postprocess_quick_chooses_on_val_and_reports_test(tmp_path: Path) -> None:
    _run("seg_postprocess.py", tmp_path)
    out = tmp_path / "out"
    doc = json.loads((out / "seg_postprocess.json").read_text())
    # the shipped model's training run selected on val_rig (the rig's full frames), so its choices are made there
    assert doc["val_split"] == "val_rig" and set(doc["views"]) == {"val_rig", "test_layouts", "test_shapes"}
    assert {r["split"] for r in doc["val_grid"]} == {"val_rig"}
    # the grid holds the default, so the setting chosen on val scores at least as well there
    assert doc["val_best"]["object_iou"] >= doc["val_default"]["object_iou"]
    assert doc["chosen"] == {k: doc["val_best"][k] for k in doc["default"]}
    assert [(r["split"], r["setting"]) for r in doc["test"]] == [
        ("test_layouts", "default"), ("test_layouts", "chosen on val"), ("test_shapes", "default"),
        ("test_shapes", "chosen on val")]
    for r in doc["test"]:
        assert 0.0 <= r["object_iou"] <= 1.0 and 0.0 <= r["silhouette_iou"] <= 1.0
    assert (out / "seg_postprocess.md").read_text().startswith("# Learned segmenter: post-processing calibrated on "
                                                               "val_rig")


def test_seg_miss_causes_quick_classifies_every_object_and_sweeps_the_neck_split(tmp_path: Path) -> None:
    _run("seg_miss_causes.py", tmp_path)
    out = tmp_path / "out"
    doc = json.loads((out / "seg_miss_causes.json").read_text())
    assert set(doc["causes"]) == {"val_rig", "test_layouts", "test_shapes"} and doc["val_split"] == "val_rig"
    for c in doc["causes"].values():
        assert set(c) == {"ok", "background", "merged", "split", "other"}
        assert sum(v["n"] for v in c.values()) > 0
    # the shipped model groups by centre votes: there are no boundary cores to split, only depth 0 runs
    assert doc["postprocess"]["grouping"] == "centre"
    assert [r["core_split_px"] for r in doc["neck_split_sweep"]] == [0.0, 0.0, 0.0]
    md = (out / "seg_miss_causes.md").read_text()
    assert md.startswith("# Learned segmenter: why objects are missed") and "only depth 0" in md
    # the boundary-only model sweeps the neck split and chooses its depth on val
    boundary_model = ROOT / "torm" / "segmentation" / "models" / "learned_seg_boundary.onnx"
    _run("seg_miss_causes.py", tmp_path / "b", "--model", str(boundary_model), "--cache", str(tmp_path / "cache"))
    doc = json.loads((tmp_path / "b" / "out" / "seg_miss_causes.json").read_text())
    sweep = doc["neck_split_sweep"]
    assert {r["core_split_px"] for r in sweep} == {0.0, 2.0} and len(sweep) == 6
    assert doc["val_split"] == "val" and {r["split"] for r in sweep} == {"val", "test_layouts", "test_shapes"}
    assert doc["neck_split_chosen_on_val"] in (0.0, 2.0)


def test_learned_segmentation_benchmark_reports_the_fixture_split(tmp_path: Path) -> None:
    """``segmentation.py --learned --fixture-shards N`` renders and scores ``test_fixtures`` beside the two test splits
    (tiny MuJoCo-rendered shards of one scene each)."""
    env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl")
    cmd = [sys.executable, str(ROOT / "benchmarks" / "segmentation.py"), "--learned", "--renderer", "mujoco",
           "--test-shards", "1", "--test-scenes", "1", "--fixture-shards", "1", "--data", str(tmp_path / "data"),
           "--out", str(tmp_path / "out"), "--threads", "1"]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads((tmp_path / "out" / "segmentation_learned_mujoco.json").read_text())
    assert list(doc["splits"]) == ["test_layouts", "test_shapes", "test_fixtures"]
    assert doc["test_recipe"]["shards"]["test_fixtures"] == 1 and doc["splits"]["test_fixtures"]["views"] == 12
    assert "| test_fixtures |" in (tmp_path / "out" / "segmentation_learned_mujoco.md").read_text()


def test_recon_degraded_quick_scores_exact_and_degraded_cases_against_the_truth(tmp_path: Path) -> None:
    _run("recon_degraded.py", tmp_path)
    doc = json.loads((tmp_path / "out" / "recon_degraded.json").read_text())
    exact, real = doc["rows"]["glass10/exact10"], doc["rows"]["glass10/real10"]
    assert exact["degradations"] == [] and real["degradations"] == ["pose", "lens", "masks"]
    assert 0.3 <= real["pose_error"]["reprojection_px_mean"] <= 1.0 and 0.9 < real["input_mask_iou_mean"] < 1.0
    for row in (exact, real):
        m = row["methods"]
        assert 0.8 < m["default"]["heldout_iou_mean"] <= 1.0 and m["voxel hull 128^3"]["heldout_iou_mean"] > 0.8
        assert row["best_tuned"] in m
    md = (tmp_path / "out" / "recon_degraded.md").read_text()
    assert "defaults >= the 128^3 voxel hull in" in md and "glass10/real10" in md


def test_perception_speed_scores_each_render_and_reads_auto_width(tmp_path: Path) -> None:
    env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl")
    cmd = [sys.executable, str(ROOT / "benchmarks" / "perception_speed.py"), "--suites", "rw", "--limit", "1",
           "--views", "2", "--renders", "4x1.0,4x0.5", "--rows", "learned_seg_v4@auto,learned_seg_v4@640:notta",
           "--workers", "1", "--cache", str(tmp_path / "cache"), "--results", str(tmp_path / "out")]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads((tmp_path / "out" / "perception_speed.json").read_text())
    rows = doc["results"]
    assert len(rows) == 4 and {r["render"] for r in rows} == {"4x1.0", "4x0.5"}
    # @auto reads the traced width: 640 px at render scale 1, 320 px at 0.5 (v4's card adds mirror TTA: " +tta")
    width = {r["segmenter"]: r["segmenter"].split(" @")[1].split()[0] for r in rows}
    assert {width[r["segmenter"]] for r in rows if r["render"] == "4x0.5"} == {"320", "640"}
    assert {width[r["segmenter"]] for r in rows if r["render"] == "4x1.0"} == {"640"}
    assert any(r["segmenter"].endswith("+tta") for r in rows) and any(not r["segmenter"].endswith("+tta")
                                                                      for r in rows)
    for r in rows:
        assert 0.0 <= r["glass_iou"] <= 1.0 and r["render_s_per_view"] > 0 and r["seg_s_per_view"] > 0
        assert r["glass_iou"] > 0.3, r  # rw1's glass is found at either resolution
    assert "capture s / 50 views" in (tmp_path / "out" / "perception_speed.md").read_text()


def test_grasping_names_one_column_per_learned_model(tmp_path):
    from benchmarks import grasping

    assert grasping.model_tag("v4fast") == "v4fast" and grasping.model_tag("runs/x/my_seg.onnx") == "my_seg"
    with pytest.raises(SystemExit, match="--models needs --segmenter learned"):
        grasping.main(["--models", "v4", "--segmenter", "noisy"])
    with pytest.raises(SystemExit, match="--no-baselines needs --segmenter"):
        grasping.main(["--no-baselines"])
    cell = {"k": 3, "n": 4, "trials_ok": 0, "trials": 1, "phantom_attempts": 0, "spurious": 1}
    cols = ("torm_learned-v4fast", "torm_learned-v4")
    result = {"config": {"suite": "lab", "segmenter": "learned", "models": ["v4fast", "v4"], "trials": 1,
                         "workers": 2, "renderer": "pbr"},
              "rows": [{"scenario": "lab1", "occ": 0.1, "objects": ["a", "b", "c", "d"], "paper_torm": None,
                        **{c: cell for c in cols}}],
              "totals": {c: {"objects": "3/4", "trials": "0/1", "spurious": 1} for c in cols},
              "timings": {c: {"perception_s": 1.0} for c in cols}, "outcomes": {c: {"success": 3} for c in cols},
              "contexts": {}, "date": "2026-12-06", "loadavg_before": [0, 0, 0], "contended": False, "versions": {}}
    grasping.write_markdown(result, tmp_path / "g.md")
    text = (tmp_path / "g.md").read_text()
    assert "segmenter learned model v4fast | TORM-fast (consensus + narrow-band projective hull), segmenter learned " \
           "model v4 |" in text and "| LAB1 | 10% | a, b, c, d | 3/4 (0/1) | 3/4 (0/1) |" in text


def test_seg_compare_view_subset_indexes_per_view_arrays_and_keeps_the_scene_meta() -> None:
    import numpy as np

    from benchmarks.seg_compare import view_subset

    views = {"rgb": np.zeros((5, 2, 2, 3)), "mask": np.arange(5)[:, None, None] * np.ones((5, 2, 2)),
             "scene": np.array([0, 0, 1, 1, 2]), "meta": [{"renderer": "pbr"}, {"renderer": "mujoco"}, {}]}
    sub = view_subset(views, np.array([1, 4]))
    assert sub["rgb"].shape[0] == 2 and sub["mask"][:, 0, 0].tolist() == [1, 4] and sub["scene"].tolist() == [0, 2]
    assert sub["meta"] is views["meta"]


def test_seg_compare_scores_every_model_on_the_same_views(tmp_path: Path) -> None:
    data = tmp_path / "data"
    env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl")
    # rendered in a subprocess: generating registers procedural shapes in this process's object library
    make = ("from torm.segmentation.training.dataset import DataRecipe, generate; "
            "generate(DataRecipe(renderer='mujoco', shards={'test_layouts': 1, 'test_fixtures': 1}, "
            f"scenes_per_shard=1, test_views=4), {str(data)!r}, splits=('test_layouts', 'test_fixtures'))")
    res = subprocess.run([sys.executable, "-c", make], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    cmd = [sys.executable, str(ROOT / "benchmarks" / "seg_compare.py"), "--data", str(data), "--models", "v3,v4",
           "--tag", "t", "--threads", "1", "--out", str(tmp_path / "out")]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads((tmp_path / "out" / "seg_compare_t.json").read_text())
    assert [m["model"].split("@")[0] for m in doc["models"]] == ["learned_seg.onnx", "learned_seg_v4.onnx"]
    for m in doc["models"]:
        assert set(m["splits"]) == {"test_layouts", "test_fixtures"}  # test_shapes was not rendered: skipped
        for r in m["splits"].values():
            assert r["views"] == 4 and 0.0 <= r["silhouette_iou"] <= 1.0 and 0.0 <= r["object_iou"] <= 1.0
    assert doc["models"][1]["postprocess"]["flip_tta"] is True  # each model reads with its own card's setting
    assert "| `learned_seg_v4.onnx@" in (tmp_path / "out" / "seg_compare_t.md").read_text()
    (tmp_path / "empty").mkdir()
    res = subprocess.run([*cmd[:3], str(tmp_path / "empty"), *cmd[4:]], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode != 0 and "no test split" in res.stderr


def test_segmentation_reference_development_seeds_and_difference_rows():
    from benchmarks.segmentation_reference import make_row, scenarios

    report, dev = scenarios(["rw", "lab"]), scenarios(["rw", "lab"], 100)
    assert [s for _, _, s in report] == list(range(len(report))) and len(report) > 8
    assert [n for _, n, _ in dev] == [n for _, n, _ in report] and [s for _, _, s in dev][0] == 100
    assert not {s for *_, s in dev} & {s for *_, s in report}  # the development layouts are other layouts
    label, seg = make_row("difference:0")
    assert label == "difference, blur 0 px" and seg.config.blur_sigma_px == 0.0
    label, seg = make_row("difference")
    assert label.startswith("difference, blur auto") and seg.config.blur_sigma_px == "auto"  # the default is named
    assert make_row("difference:auto")[0] == label


def test_segmentation_reference_scores_views_without_glass_by_their_false_positives():
    import numpy as np

    from benchmarks.segmentation_reference import score

    empty = np.zeros((4, 5), bool)
    some = empty.copy()
    some[1:3, 1:3] = True
    assert score(empty, empty) == {"iou": 1.0, "precision": 1.0, "recall": 1.0}  # nothing there, nothing marked
    assert score(some, empty)["iou"] == 0.0 and score(empty, some)["recall"] == 0.0
    half = some.copy()
    half[1, 1:3] = False
    assert score(half, some) == {"iou": 0.5, "precision": 1.0, "recall": 0.5}


def test_reference_background_counts_false_refusals_and_acceptances(tmp_path: Path) -> None:
    import numpy as np

    from benchmarks import reference_background as rb
    from torm.capture.io import save_capture
    from torm.types import CameraView, Capture

    rng = np.random.default_rng(0)
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    disc = ((yy - 24) ** 2 + (xx - 32) ** 2 < 8**2).astype(np.int32)

    def table(period: float) -> np.ndarray:
        return np.clip(120 + 40 * np.sin(xx / period)[..., None] + np.zeros((h, w, 3)), 0, 255)

    def noisy(img: np.ndarray) -> np.ndarray:
        return np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)

    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    for seed, period in ((0, 3.0), (200, 7.0)):  # the stale reference shows another table
        bg = table(period)
        scene = bg.copy()
        scene[disc > 0] = 230
        cap = Capture(views=(CameraView(K, np.eye(4), rgb=noisy(scene), mask=disc, reference_rgb=noisy(bg)),))
        save_capture(cap, rb.folder(tmp_path / "cache", "rw1", seed, "pbr"))
    args = ["--suites", "rw", "--limit", "1", "--masks", "none,truth,difference", "--blur", "auto",
            "--cache", str(tmp_path / "cache"), "--results", str(tmp_path), "--out", "bg"]
    assert rb.main(args) == 0
    doc = json.loads((tmp_path / "bg.json").read_text())
    for r in doc["rows"]:
        assert (r["grey"] < doc["max_grey"]) == (r["pair"] == "valid"), r  # the stale one is caught by every mask
    assert "| difference | auto |" in (tmp_path / "bg.md").read_text()
    with pytest.raises(SystemExit, match="not cached"):
        rb.main([*args[:4], "--stale-offset", "300", *args[4:]])


def test_finetune_frames_from_captures_writes_glass_only_masks_the_finetune_reader_accepts(tmp_path: Path) -> None:
    import numpy as np

    from benchmarks.finetune_frames_from_captures import glass_instances, main
    from torm.capture.io import save_capture
    from torm.segmentation.training.finetune import load_labelled_frames
    from torm.types import CameraView, Capture

    mask = np.zeros((36, 64), np.int32)
    mask[5:15, 5:15], mask[20:30, 30:40], mask[5:15, 40:50] = 3, 7, 9  # 7 is an opaque cup
    np.testing.assert_array_equal(np.unique(glass_instances(mask, [3, 9])), [0, 1, 2])
    assert glass_instances(mask, [3, 9])[25, 35] == 0
    K = np.array([[40.0, 0, 32], [0, 40.0, 18], [0, 0, 1]])
    rgb = np.full((36, 64, 3), 90, np.uint8)
    cap = Capture(views=(CameraView(K, np.eye(4), rgb=rgb, mask=mask), CameraView(K, np.eye(4), rgb=rgb, mask=mask)),
                  metadata={"transparent_ids": [3, 9]})
    save_capture(cap, tmp_path / "caps" / "rw1_s300")
    assert main(["--captures", str(tmp_path / "caps" / "*"), "--out", str(tmp_path / "ft")]) == 0
    rgbs, masks, files = load_labelled_frames(tmp_path / "ft", input_width=64)
    assert rgbs.shape == (2, 36, 64, 3) and [f["image"] for f in files] == ["rw1_s300_0.png", "rw1_s300_1.png"]
    assert set(np.unique(masks[0])) == {0, 1, 2}  # two glass instances, the opaque one is background
    with pytest.raises(SystemExit, match="no capture folder"):
        main(["--captures", str(tmp_path / "none*"), "--out", str(tmp_path / "x")])
