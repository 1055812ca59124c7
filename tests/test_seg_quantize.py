"""Int8 copies of a learned-segmenter model (torm.segmentation.quantize): the copy reads the same foreground as the
fp32 model on a committed render, its card names its source, and bad calibration input is refused by name."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from torm.errors import ConfigError

DATA = Path(__file__).resolve().parent / "data"


def _views() -> list[np.ndarray]:
    """Four calibration images: the committed renders, downscaled to keep the test short."""
    out = []
    for name in ("rw5_pbr_view.png", "learned_seg_view.png", "v4_distractors_view.png"):
        rgb = cv2.imread(str(DATA / name), cv2.IMREAD_COLOR)[:, :, ::-1]
        out.append(np.ascontiguousarray(cv2.resize(rgb, (320, 180), interpolation=cv2.INTER_AREA)))
    return out + [np.ascontiguousarray(out[0][:, ::-1])]


def test_an_int8_copy_reads_the_same_foreground_and_names_its_source(tmp_path):
    pytest.importorskip("onnx")
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter, model_fingerprint
    from torm.segmentation.quantize import quantize_model

    views = _views()
    out = quantize_model("v7", tmp_path / "v7q.onnx", views, "four committed renders", threads=1)
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["model"] == "v7q.onnx" and card["quantized"]["from"] == model_fingerprint("v7")
    assert card["quantized"]["reduce_range"] is True and card["postprocess"]["grouping"] == "centre"
    fp = LearnedSegmenter(LearnedConfig(model="v7", threads=1, input_width=320))
    q = LearnedSegmenter(LearnedConfig(model=str(out), threads=1, input_width=320))
    rgb = cv2.imread(str(DATA / "rw5_pbr_view.png"), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
    a, b = fp.maps(rgb)[0] > 0.5, q.maps(rgb)[0] > 0.5
    # int8 rounding moves a border pixel here and there; the object's silhouette stays (measured 0.98-0.99 on
    # renders: benchmarks/results/seg_quantize.md)
    assert a.sum() > 500 and (a & b).sum() / (a | b).sum() > 0.9


def test_quantize_refuses_bad_calibration_input(tmp_path):
    pytest.importorskip("onnx")
    from torm.segmentation.quantize import quantize_model

    views = _views()
    with pytest.raises(ConfigError, match="calibration images; pass 4 to 512"):
        quantize_model("v7", tmp_path / "q.onnx", views[:2], "too few")
    with pytest.raises(ConfigError, match="must be an .onnx file"):
        quantize_model("v7", tmp_path / "q.bin", views, "x")
    with pytest.raises(ConfigError, match=r"\(H, W, 3\) uint8"):
        quantize_model("v7", tmp_path / "q.onnx", [v.astype(np.float32) for v in views], "x")
