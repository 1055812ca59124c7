"""``torm segment`` on saved synthetic captures: noisy, gt with view checks, and grounded_sam with fake models."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from torm.capture.io import load_capture, save_capture
from torm.cli import main
from torm.segmentation import make_segmenter
from torm.segmentation.sphere_capture import sphere_capture


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    cap = sphere_capture(n_views=12, size_px=96, seed=3, with_rgb=True)
    d = tmp_path_factory.mktemp("cap") / "scene"
    save_capture(cap, d)
    return d, cap


def _run(capsys, argv) -> dict:
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_noisy_segment_writes_a_loadable_capture(capture_dir, capsys, tmp_path):
    d, cap = capture_dir
    out = tmp_path / "noisy"
    summary = _run(capsys, ["segment", str(d), "--segmenter", "noisy", "--preset", "severe", "--seed", "2",
                            "--out", str(out)])
    assert summary["views"] == 12 and summary["quality"]["silhouette_iou_mean"] < 0.95
    seg = load_capture(out)
    expected = make_segmenter("noisy", {"preset": "severe", "seed": 2}).segment(load_capture(d)).masks_vxhxw
    np.testing.assert_array_equal(seg.masks(), expected)
    np.testing.assert_array_equal(seg.views[0].rgb, cap.views[0].rgb)
    doc = json.loads((out / "transforms.json").read_text())
    assert doc["metadata"]["gt_object_ids"] == [1, 2, 3]
    gt0 = (out / doc["frames"][0]["gt_mask_path"])
    assert gt0.is_file()
    assert (load_capture(d).masks() == cap.masks()).all()  # the input folder is untouched


def test_gt_segment_with_view_checks_and_errors(capture_dir, capsys, tmp_path):
    d, _ = capture_dir
    summary = _run(capsys, ["segment", str(d), "--segmenter", "gt", "--check-views", "drop",
                            "--out", str(tmp_path / "gt")])
    assert summary["quality"]["silhouette_iou_mean"] == 1.0 and summary["consistency"]["flagged"] == {}
    assert main(["segment", str(d), "--segmenter", "noisy", "--set", "bogus=1", "--out", str(tmp_path / "x")]) == 2
    assert "bogus" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # argparse's usage error: exit 2, the valid choices listed
        main(["segment", str(d), "--segmenter", "nope", "--out", str(tmp_path / "y")])
    assert exc.value.code == 2
    assert "invalid choice: 'nope' (choose from 'gt', 'noisy'" in capsys.readouterr().err
    assert main(["segment", str(d), "--segmenter", "gt", "--out", str(d)]) == 2


def test_grounded_sam_segment_from_a_yaml_config(capture_dir, capsys, tmp_path):
    from test_seg_grounded_sam import PROMPT, VOCAB, build_gdino, build_sam_decoder, build_sam_encoder

    from torm.segmentation.grounded_sam import gdino_resize_hw

    d, _ = capture_dir
    (tmp_path / "vocab.txt").write_text("\n".join(VOCAB))
    gd = build_gdino(tmp_path / "g.onnx", None, 0.0, gdino_resize_hw(96, 96), 0.0, check=False)
    cfg = {"grounded_sam": {
        "gdino_model": str(gd), "bert_vocab": str(tmp_path / "vocab.txt"),
        "sam_encoder": str(build_sam_encoder(tmp_path / "e.onnx")),
        "sam_decoder": str(build_sam_decoder(tmp_path / "d.onnx")), "threads": 1, "prompt": "unused",
    }}
    cfg_path = tmp_path / "gsam.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "gsam"
    summary = _run(capsys, ["segment", str(d), "--segmenter", "grounded_sam", "--config", str(cfg_path),
                            "--prompt", PROMPT, "--set", "min_blob_area_px=16", "--out", str(out)])
    assert summary["detections_per_view"] == [2] * 12
    meta = json.loads((out / "transforms.json").read_text())["metadata"]["segmentation"]
    assert meta["prompt"] == PROMPT
    seg = load_capture(out)
    expected = np.zeros((96, 96), np.int32)
    expected[36:60, 18:30] = 1  # box (18, 36, 30, 60): q0 of the fake detector scaled to 96 x 96
    expected[24:48, 60:78] = 2  # box (60, 24, 78, 48): q2
    for m in seg.masks():
        np.testing.assert_array_equal(m, expected)
    assert seg.object_ids == (1, 2) and seg.object_names == ("instance1", "instance2")
    assert Path(out / "gt_masks").is_dir()
