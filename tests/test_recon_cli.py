"""``torm reconstruct`` on a simulated capture folder."""

from __future__ import annotations

import json
import shutil

import pytest

from torm.cli import main


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "rw3"
    assert main(["capture", "--scenario", "rw3", "--views", "16", "--scale", "0.25", "--no-occlusion",
                 "--out", str(out)]) == 0
    return out


def test_reconstruct_writes_meshes_points_and_metrics(capture_dir, tmp_path, capsys):
    capsys.readouterr()
    out = tmp_path / "rec"
    assert main(["reconstruct", str(capture_dir), "--out", str(out), "--set", "grid_res=32",
                 "--set", "refine_iters=0", "--set", "points_per_object=512", "--rrd", str(tmp_path / "r.rrd")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_objects"] == 2
    for k in range(2):
        for name in (f"object_{k}.ply", f"object_{k}.obj", f"object_{k}.glb", f"object_{k}_points.ply"):
            assert (out / name).stat().st_size > 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["n_objects_found"] == m["n_objects_present"] == 2
    assert m["silhouette_iou_mean"] > 0.9
    assert m["depth"]["delta_1.05"] > 0.9 and m["depth"]["coverage"] > 0.9
    assert (tmp_path / "r.rrd").stat().st_size > 0


def test_reconstruct_without_masks_says_how_to_fix(capture_dir, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(capture_dir, bare)
    doc = json.loads((bare / "transforms.json").read_text())
    for f in doc["frames"]:
        f.pop("mask_path", None)
    (bare / "transforms.json").write_text(json.dumps(doc))
    assert main(["reconstruct", str(bare), "--out", str(tmp_path / "x")]) == 2
    assert "has no masks" in capsys.readouterr().err


def test_reconstruct_with_noisy_segmenter(capture_dir, tmp_path, capsys):
    capsys.readouterr()
    assert main(["reconstruct", str(capture_dir), "--out", str(tmp_path / "n"), "--segmenter", "noisy",
                 "--preset", "mild", "--set", "grid_res=32", "--set", "refine_iters=0"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["segmentation"] is not None and summary["n_objects"] >= 2


def test_spurious_blobs_in_few_views_are_carved_not_fatal(capture_dir):
    from torm.capture.io import load_capture
    from torm.reconstruction import ReconstructionConfig, reconstruct

    cap = load_capture(capture_dir)
    masks = cap.masks().copy()
    for i in (2, 9):  # a segmenter's false positive in 2 of 16 views, in the image corner
        masks[i, :12, :12] = 9
    rec = reconstruct(cap.with_masks(masks), ReconstructionConfig(grid_res=32, refine_iters=0,
                                                                  points_per_object=256))
    assert rec.n_objects == 2 and not rec.info["rejected_objects"]
    # The same blob in every view's corner: the views disagree about it (no 3-D point projects into every
    # corner), so it is carved, the two objects are still reconstructed and every checked view reports a
    # silhouette region that no object explains.
    masks[:, :12, :12] = 9
    rec = reconstruct(cap.with_masks(masks), ReconstructionConfig(grid_res=32, refine_iters=0))
    assert rec.n_objects == 2 and len(rec.info["unexplained_views"]) == 8


def test_views_with_entirely_empty_masks_are_ignored_not_carved(capture_dir):
    from torm.capture.io import load_capture
    from torm.errors import ReconstructionError
    from torm.reconstruction import ReconstructionConfig, reconstruct

    cap = load_capture(capture_dir)
    masks = cap.masks().copy()
    masks[::3] = 0  # the segmenter found nothing in a third of the views (far beyond the vote tolerance)
    cfg = ReconstructionConfig(grid_res=32, refine_iters=0, points_per_object=256)
    rec = reconstruct(cap.with_masks(masks), cfg)
    assert rec.n_objects == 2 and rec.info["ignored_empty_views"] == list(range(0, 16, 3))
    with pytest.raises(ReconstructionError, match="empty"):
        reconstruct(cap.with_masks(masks), ReconstructionConfig(grid_res=32, refine_iters=0, ignore_empty_views=False))


def test_segmenter_settings_go_under_segmentation_in_config_and_set(capture_dir, tmp_path, capsys):
    """One vocabulary: --config/--set configure the reconstruction and, under ``segmentation``, the segmenter."""
    cfg = tmp_path / "rec.yaml"
    cfg.write_text("grid_res: 32\nrefine_iters: 0\nsegmentation: {preset: mild, seed: 3}\n")
    capsys.readouterr()
    assert main(["reconstruct", str(capture_dir), "--out", str(tmp_path / "a"), "--segmenter", "noisy",
                 "--config", str(cfg)]) == 0
    assert json.loads(capsys.readouterr().out)["n_objects"] >= 2
    seg_yaml = tmp_path / "noisy.yaml"
    seg_yaml.write_text("preset: no_such_preset\n")
    for extra in (["--set", "segmentation.preset=no_such_preset"], ["--set", f"segmentation={seg_yaml}"]):
        assert main(["reconstruct", str(capture_dir), "--out", str(tmp_path / "b"), "--segmenter", "noisy",
                     "--config", str(cfg), *extra]) == 2  # reached the segmenter's config: its error
        assert "noisy.preset 'no_such_preset' is unknown" in capsys.readouterr().err
    assert main(["reconstruct", str(capture_dir), "--out", str(tmp_path / "c"), "--config", str(cfg)]) == 2
    assert "no --segmenter" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the old flag is gone (argparse: unrecognized arguments)
        main(["reconstruct", str(capture_dir), "--out", str(tmp_path / "d"), "--seg-config", str(seg_yaml)])
