"""The memory bound of Grounding DINO + SAM: above every measured peak, refused before anything loads."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from torm.errors import ConfigError

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def test_the_estimate_stays_above_every_measured_peak_and_near_it():
    """Every committed gsam_cpu run (4 configurations x memory arena on/off): the estimate the segmenter refuses
    against is at least the measured peak and at most 1.6x it (a bound, not a guess twice too large)."""
    from benchmarks.gsam_cpu import CONFIGS, estimate_gb

    seen = 0
    for stem, boxes, kind in CONFIGS:
        for suffix in ("", "_no_arena"):
            path = RESULTS / f"{stem}{suffix}.json"
            doc = json.loads(path.read_text())
            peak = doc["memory"]["peak_rss_gb"]
            est = estimate_gb(doc, boxes, kind)
            assert peak <= est <= 1.6 * peak, (path.name, peak, est)
            seen += 1
    assert seen == 8


def test_the_parts_add_with_the_arena_and_the_larger_bounds_without_it():
    import torm.resources as res
    from torm.resources import GDINO_REFERENCE_PX, GDINO_WORK_BYTES, GSAM_BASE_BYTES, SAM_WORK_BYTES, grounded_sam_bytes

    fixed = GSAM_BASE_BYTES + res.ONNX_LOADED_BYTES_PER_FILE_BYTE * 1e9
    with_arena = grounded_sam_bytes(int(1e9), GDINO_REFERENCE_PX, "sam", memory_arena=True)
    assert with_arena == pytest.approx(fixed + GDINO_WORK_BYTES[True] + SAM_WORK_BYTES[("sam", True)])
    without = grounded_sam_bytes(int(1e9), GDINO_REFERENCE_PX, "sam", memory_arena=False)
    assert without == pytest.approx(fixed + max(GDINO_WORK_BYTES[False], SAM_WORK_BYTES[("sam", False)]))
    half = grounded_sam_bytes(0, GDINO_REFERENCE_PX // 2, "sam2", memory_arena=True)
    expected = GSAM_BASE_BYTES + GDINO_WORK_BYTES[True] / 2 + SAM_WORK_BYTES[("sam2", True)]
    assert half == pytest.approx(expected, rel=1e-5)
    big = grounded_sam_bytes(0, 0, "sam", sam_image_size=2048, memory_arena=False)
    assert big == pytest.approx(GSAM_BASE_BYTES + 16 * SAM_WORK_BYTES[("sam", False)])  # ViT attention: tokens^2
    with pytest.raises(ConfigError, match="valid choices: sam, sam2"):
        grounded_sam_bytes(0, 0, "sam3")


def _files(tmp_path: Path, sam_card: dict, gdino_card: dict) -> dict:
    paths = {}
    for key, name, card in (("sam_encoder", "enc.onnx", sam_card), ("sam_decoder", "dec.onnx", {}),
                            ("gdino_model", "gdino.onnx", gdino_card)):
        p = tmp_path / name
        p.write_bytes(b"\0" * 1000)
        if card:
            p.with_suffix(".onnx.json").write_text(json.dumps(card))
        paths[key] = str(p)
    return paths


def test_grounded_sam_refuses_before_loading_when_the_estimate_exceeds_free_memory(tmp_path, monkeypatch):
    """The estimate reads the files' sizes and cards (SAM kind, Grounding DINO's input size); with too little free
    memory the error names the configuration, the estimate, what is free and the fixes, before onnxruntime opens
    anything (the files here are not ONNX models: with enough memory the loader's own error comes next)."""
    import torm.resources as res
    from torm.errors import ModelFileError
    from torm.segmentation.grounded_sam import GroundedSAMConfig, GroundedSAMSegmenter

    paths = _files(tmp_path, {"model": "sam2_image_encoder", "sam_kind": "sam2"}, {"image_hw": [400, 666]})
    monkeypatch.setattr(res, "available_memory_bytes", lambda: int(1e9))
    with pytest.raises(ConfigError, match=r"grounded_sam \(Grounding DINO boxes, sam2 at 1024 px, memory_arena "
                                          r"false\) needs about .* GiB of memory but 0.931 GiB is free; .*box_source"):
        GroundedSAMSegmenter(GroundedSAMConfig(**paths, bert_vocab="v.txt"))
    monkeypatch.setattr(res, "available_memory_bytes", lambda: int(1e12))
    with pytest.raises(ModelFileError):
        GroundedSAMSegmenter(GroundedSAMConfig(**paths, bert_vocab="v.txt"))
    seg = GroundedSAMSegmenter.__new__(GroundedSAMSegmenter)
    seg.config = GroundedSAMConfig(**paths)
    assert seg._declared_sam_kind() == "sam2" and seg._declared_gdino_px() == 400 * 666
    seg.config = GroundedSAMConfig(**{**paths, "gdino_model": ""}, box_source="learned")
    assert seg._declared_gdino_px() == 0
