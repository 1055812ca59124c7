"""Every trial record names what produced it (method, mode, segmenter, renderer, depth model, realism)."""

from __future__ import annotations

import pytest

from torm import config
from torm.errors import UnknownNameError
from torm.pipeline import TrialConfig, trial_context


def test_context_names_every_choice():
    cfg = config.from_dict(TrialConfig, {"method": "torm"}, overrides=["segmentation.segmenter=noisy",
                                                                       "segmentation.preset=severe"])
    ctx = trial_context(cfg)
    assert ctx == {"method": "torm", "reconstruction_mode": "fast", "segmenter": "noisy:severe",
                   "renderer": "mujoco", "depth_model": "ideal", "realism": "ideal", "backend": "sim",
                   "table": "declared"}
    stressed = trial_context(config.from_dict(TrialConfig, {"method": "torm", "table": "capture"}, overrides=[
        "world.realism=stress", "world.stress=2", "world.factors=[contact]"]))
    assert stressed["realism"] == "stress[contact] x2" and stressed["table"] == "capture"
    ctx = trial_context(config.from_dict(TrialConfig, {"method": "oracle"}))
    assert ctx["reconstruction_mode"] is None and ctx["segmenter"] is None


@pytest.mark.parametrize("key", ["capture.renderer", "capture.depth_model", "world.realism"])
def test_unknown_choice_lists_the_valid_ones(key):
    with pytest.raises(UnknownNameError, match="valid choices"):
        config.from_dict(TrialConfig, {}, overrides=[f"{key}=nonsense"])


def test_learned_segmenter_context_names_the_model_file_and_its_hash(tmp_path):
    ctx = trial_context(config.from_dict(TrialConfig, {"method": "torm"},
                                         overrides=["segmentation.segmenter=learned"]))
    assert ctx["segmenter"] == "learned" and ctx["segmenter_model"].startswith("learned_seg.onnx@sha256:")
    other = tmp_path / "mine.onnx"
    other.write_bytes(b"not really a model")
    cfg = config.from_dict(TrialConfig, {"method": "torm", "segmentation": {"segmenter": "learned",
                                                                           "options": {"model": str(other)}}})
    assert trial_context(cfg)["segmenter_model"] == "mine.onnx@sha256:" + __import__("hashlib").sha256(
        b"not really a model").hexdigest()[:12]
    cfg = config.from_dict(TrialConfig, {"method": "torm", "segmentation": {"segmenter": "learned",
                                                                           "options": {"model": "/nope.onnx"}}})
    assert trial_context(cfg)["segmenter_model"] == "nope.onnx@missing"


def test_context_names_the_input_width_and_the_traced_scale():
    ctx = trial_context(config.from_dict(TrialConfig, {"method": "torm"}, overrides=[
        "segmentation.segmenter=learned", "segmentation.options.input_width=448", "capture.renderer=pbr",
        "capture.pbr.render_scale=0"]))
    assert ctx["segmenter_input_px"] == 448 and ctx["render_scale"] == pytest.approx(0.7)
    ctx = trial_context(config.from_dict(TrialConfig, {"method": "torm"}, overrides=[
        "segmentation.segmenter=learned", "capture.renderer=pbr"]))
    assert ctx["segmenter_input_px"] == 640 and ctx["render_scale"] == 1.0
    assert "render_scale" not in trial_context(config.from_dict(TrialConfig, {"method": "torm"}))  # mujoco
