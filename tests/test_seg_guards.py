"""Segmenter guards: a model warns once where it was not validated; segmenter masks are never called ground truth;
``torm segment`` defaults to a segmenter that needs no downloaded weights."""

from __future__ import annotations

import json
import logging

import numpy as np

from torm.capture.io import load_capture, save_capture
from torm.cli import main
from torm.segmentation import make_segmenter
from torm.segmentation.base import MASK_SOURCE_KEY, mask_reference, masks_are_ground_truth
from torm.segmentation.learned import _DOMAIN_WARNED, capture_domain
from torm.segmentation.synthetic import sphere_capture
from torm.types import Capture


def _cap(renderer: str | None) -> Capture:
    cap = sphere_capture(n_views=2, size_px=64, seed=1, with_rgb=True)
    meta = dict(cap.metadata)
    if renderer is not None:
        meta["renderer"] = renderer
    return Capture(views=cap.views, metadata=meta)


def test_capture_domains_from_the_renderer_metadata():
    assert capture_domain(_cap("mujoco 3.17.0 offscreen")) == "mujoco"
    assert capture_domain(_cap("pbr mitsuba 3.9.1 llvm_ad_rgb spp 16")) == "pbr:llvm_ad_rgb"
    assert capture_domain(_cap("pbr mitsuba 3.9.1 scalar_rgb spp 16")) == "pbr:scalar_rgb"
    assert capture_domain(_cap(None)) == "recorded"


def test_the_domain_warning_fires_once_where_the_model_was_not_validated(caplog):
    seg = make_segmenter("learned", {"threads": 1, "input_width": 64})
    _DOMAIN_WARNED.clear()
    with caplog.at_level(logging.WARNING, logger="torm.segmentation.learned"):
        res = seg.segment(_cap(None))
        seg.segment(_cap(None))
    warned = [r for r in caplog.records if "not validated on" in r.getMessage()]
    assert len(warned) == 1  # once per model and domain
    msg = warned[0].getMessage()
    assert "recorded" in msg and "0.318" in msg and "pbr:llvm_ad_rgb" in msg  # the score measured there, and where
    assert res.info["domain"] == {"domain": "recorded", "validated": False, "measured": 0.318}
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="torm.segmentation.learned"):
        ok = seg.segment(_cap("pbr mitsuba 3.9.1 llvm_ad_rgb spp 16"))
    assert ok.info["domain"]["validated"] and not [r for r in caplog.records if "not validated" in r.getMessage()]


def test_segmenter_masks_are_never_called_ground_truth(tmp_path, capsys):
    cap = sphere_capture(n_views=6, size_px=64, seed=2, with_rgb=True)
    assert masks_are_ground_truth(cap) and mask_reference(cap).startswith("ground truth")
    noisy = make_segmenter("noisy", {"preset": "severe", "seed": 1}).segment(cap).apply(cap)
    assert noisy.metadata[MASK_SOURCE_KEY] == "segmenter noisy" and not masks_are_ground_truth(noisy)
    assert "not" in mask_reference(Capture(views=cap.views)) and "ground truth" in mask_reference(Capture(
        views=cap.views))  # "source unknown, not ground truth"
    # a segmented capture saved and segmented again: its masks travel as the first segmenter's, not as GT
    first = tmp_path / "first"
    assert main(["segment", str(_saved(cap, tmp_path)), "--segmenter", "noisy", "--out", str(first)]) == 0
    capsys.readouterr()
    second = tmp_path / "second"
    assert main(["segment", str(first), "--segmenter", "gt", "--out", str(second)]) == 0
    capsys.readouterr()
    meta = json.loads((second / "transforms.json").read_text())["metadata"]
    assert meta["input_mask_source"] == "segmenter noisy" and meta[MASK_SOURCE_KEY] == "segmenter noisy"
    assert not (second / "gt_masks").exists()
    assert not masks_are_ground_truth(load_capture(second))


def _saved(cap: Capture, tmp_path) -> object:
    d = tmp_path / "scene"
    save_capture(cap, d)
    return d


def test_torm_segment_defaults_to_the_shipped_learned_model(tmp_path, capsys):
    d = _saved(sphere_capture(n_views=2, size_px=64, seed=3, with_rgb=True), tmp_path)
    assert main(["segment", str(d), "--out", str(tmp_path / "out")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["segmenter"] == "learned"
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())["metadata"]
    assert meta[MASK_SOURCE_KEY].startswith("segmenter learned (learned_seg.onnx@sha256:")
    assert np.asarray(load_capture(tmp_path / "out").masks()).shape == (2, 64, 64)
