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
from torm.segmentation.sphere_capture import sphere_capture
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
    # every renderer the model can be used on has a measured score in the card, the scalar fallback included
    for domain, meta in (("pbr:scalar_rgb", "pbr mitsuba 3.9.1 scalar_rgb spp 16"), ("mujoco", "mujoco 3.17.0")):
        info = seg.segment(_cap(meta)).info["domain"]
        assert info["domain"] == domain and 0.0 < info["measured"] <= 1.0


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


def _rig_view_capture(width: int = 640, height: int = 360, hfov_deg: float = 91.5) -> Capture:
    from torm.types import CameraView

    f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    rgb = np.full((height, width, 3), 90, np.uint8)
    return Capture(views=(CameraView(K=K, T_world_cam=np.eye(4), rgb=rgb, name="v0"),),
                   metadata={"renderer": "pbr mitsuba 3.9.1 llvm_ad_rgb spp 16"})


def test_the_pixel_scale_warning_names_the_width_that_reads_at_the_trained_scale(caplog):
    cap = _rig_view_capture()  # the rig's 640 x 360 frame, the shipped model's training scale
    _DOMAIN_WARNED.clear()
    with caplog.at_level(logging.WARNING, logger="torm.segmentation.learned"):
        at_scale = make_segmenter("learned", {"threads": 1}).segment(cap)
    assert at_scale.info["input_width"] == 640 and abs(at_scale.info["pixel_scale"]["ratio"] - 1) < 1e-9
    assert at_scale.info["pixel_scale"]["within"] and not [r for r in caplog.records if "trained scale" in
                                                             r.getMessage()]
    with caplog.at_level(logging.WARNING, logger="torm.segmentation.learned"):
        half = make_segmenter("learned", {"threads": 1, "input_width": 320}).segment(cap)
    assert abs(half.info["pixel_scale"]["ratio"] - 0.5) < 1e-9 and not half.info["pixel_scale"]["within"]
    warned = [r.getMessage() for r in caplog.records if "trained scale" in r.getMessage()]
    assert len(warned) == 1 and "0.50x" in warned[0] and "input_width=640" in warned[0]


def test_the_input_width_defaults_to_the_width_of_the_models_training_frames(tmp_path):
    import shutil

    from torm import config
    from torm.pipeline import TrialConfig, learned_input_width
    from torm.segmentation.learned import DEFAULT_MODEL, LearnedConfig, card_input_width, model_fingerprint

    assert card_input_width(DEFAULT_MODEL) == 640 and LearnedConfig().resolved_input_width() == 640
    assert LearnedConfig(model="v4").model_path.name == "learned_seg_v4.onnx"  # a shipped model's short name
    assert LearnedConfig(model="learned_seg_v4").model_path == LearnedConfig(model="v4").model_path  # or file stem
    assert model_fingerprint("v4").startswith("learned_seg_v4.onnx@sha256:")  # what a trial context names
    small = tmp_path / "small.onnx"
    shutil.copy(DEFAULT_MODEL, small)
    assert card_input_width(small) == 640  # no card: the pipeline's frame width
    small.with_suffix(".json").write_text(json.dumps({"data": {"full_width": 320, "hfov_deg": 91.5}}))
    assert card_input_width(small) == 320
    seg = make_segmenter("learned", {"threads": 1, "model": str(small)})
    assert seg.input_width == 320
    assert make_segmenter("learned", {"threads": 1, "model": str(small), "input_width": 0}).input_width == 0
    cfg = config.from_dict(TrialConfig, {"scenario": "rw1"}, overrides=[
        "segmentation.segmenter=learned", f"segmentation.options.model={small}"])
    assert learned_input_width(cfg) == 320
    small.with_suffix(".json").write_text(json.dumps({"data": {"full_width": 320}, "finetune": {"input_width": 512}}))
    assert card_input_width(small) == 512  # fine-tuned on a user's frames: the width it was tuned at


def test_a_result_names_the_post_processing_from_the_card_or_the_config(tmp_path):
    """The model hash stays when a card's calibration changes, so the trial context names the post-processing too."""
    import shutil

    from torm import config
    from torm.pipeline import TrialConfig, trial_context
    from torm.segmentation.learned import DEFAULT_MODEL, postprocess_label

    model = tmp_path / "m.onnx"
    shutil.copy(DEFAULT_MODEL, model)
    assert postprocess_label(model).startswith("default: ")  # no card
    model.with_suffix(".json").write_text(json.dumps({"postprocess": {
        "grouping": "centre", "fg_threshold": 0.3, "centre_threshold": 0.1, "nms_px": 15, "max_vote_px": 40.0}}))
    assert postprocess_label(model) == "card: centre fg 0.3 centre 0.1 nms 15 vote 40"
    assert postprocess_label(model, {"flip_tta": True, "grouping": "boundary", "threads": 1}) == \
        "config: boundary fg 0.3 boundary 0.5 core 8 flip"  # the config's values over the card's
    cfg = config.from_dict(TrialConfig, {"segmentation": {"segmenter": "learned", "options": {"model": str(model)}}})
    assert trial_context(cfg)["segmenter_postprocess"] == postprocess_label(model)
