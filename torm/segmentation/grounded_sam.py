"""Grounded-SAM on onnxruntime: Grounding DINO boxes from a text prompt, SAM masks from the boxes.

The paper's silhouette extractor (Sec. III-A): Grounding DINO finds boxes for prompts such as
"clear glass" in every RGB view; each box prompts SAM, whose mask becomes one instance. Expected
ONNX signatures (export recipes in ``torm/segmentation/README.md``):

Grounding DINO (``gdino_model``)
    inputs  ``img`` (or ``samples``) (1, 3, H, W) float32, RGB/255 normalised with ImageNet mean/std,
            resized so the short side is 800 px (longest <= 1333), or, for an export with a static size,
            letterboxed into it (aspect kept, padded right/bottom: :func:`gdino_letterbox`; never stretched);
            ``input_ids``, ``attention_mask``, ``position_ids``, ``token_type_ids`` (1, T);
            ``text_token_mask`` (or ``text_self_attention_masks``) (1, T, T) phrase-block mask.
            Integer/bool dtypes are taken from the model. T = the token count, or the export's static T.
    outputs ``logits`` (or ``pred_logits``) (1, Q, L) raw token logits (Q = 900 queries, L = 256);
            ``boxes`` (or ``pred_boxes``) (1, Q, 4) normalised cx, cy, w, h.

SAM image encoder (``sam_encoder``)
    input   one tensor (1, 3, 1024, 1024) float32: longest side resized to 1024, (RGB - mean) / std with
            SAM's pixel mean (123.675, 116.28, 103.53) and std (58.395, 57.12, 57.375), zero-padded
            bottom/right;
    output  ``image_embeddings`` (or its only output) (1, 256, 64, 64) float32.

SAM 2 (``torm export-models --sam-kind sam2``: SAM 2.1 Hiera-Tiny, the small SAM-family model for CPUs), told
apart by its encoder's outputs
    encoder input (1, 3, 1024, 1024): the image resized to the square (no padding), RGB/255 normalised with the
            ImageNet mean/std; outputs ``image_embeddings`` (1, 256, 64, 64), ``high_res_feats_0`` (1, 32, 256, 256),
            ``high_res_feats_1`` (1, 64, 128, 128);
    decoder the SAM decoder's inputs plus ``high_res_feats_0`` / ``high_res_feats_1``; point coordinates in the
            square 1024 frame (x * 1024 / W, y * 1024 / H); the same outputs.

SAM mask decoder (``sam_decoder``; segment-anything ``scripts/export_onnx_model.py``)
    inputs  ``image_embeddings`` (1, 256, 64, 64); ``point_coords`` (1, N, 2) in the 1024-resized frame;
            ``point_labels`` (1, N) (box corners: 2 = top-left, 3 = bottom-right); ``mask_input``
            (1, 1, 256, 256); ``has_mask_input`` (1,); ``orig_im_size`` (2,) = (H, W) float32;
    outputs ``masks`` (1, C, H, W) logits (C = 1 with ``--return-single-mask``, else 4),
            ``iou_predictions`` (1, C), ``low_res_masks`` (1, C, 256, 256).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torm.errors import CaptureError, ConfigError, ModelFileError
from torm.resources import check_fits, grounded_sam_bytes
from torm.segmentation.base import Detection, SegmentationResult, Segmenter, score_against_capture
from torm.segmentation.boxes import DecodedBoxes, decode_grounding
from torm.segmentation.onnx_models import BoundSession, TensorSpec, open_session, static_dims
from torm.segmentation.postprocess import clean_mask, compose_instances
from torm.segmentation.tokenizer import (
    GROUNDING_SPECIAL_IDS,
    TextInputs,
    WordPieceTokenizer,
    check_vocabulary,
    grounding_text_inputs,
)
from torm.types import Capture

log = logging.getLogger(__name__)

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
SAM_PIXEL_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
SAM_PIXEL_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)

GDINO_INPUTS = (
    TensorSpec("img", ("img", "samples", "image", "pixel_values"), (1, 3, None, None)),
    TensorSpec("input_ids", ("input_ids",), (1, None)),
    TensorSpec("attention_mask", ("attention_mask",), (1, None)),
    TensorSpec("position_ids", ("position_ids",), (1, None)),
    TensorSpec("token_type_ids", ("token_type_ids",), (1, None)),
    TensorSpec("text_token_mask", ("text_token_mask", "text_self_attention_masks"), (1, None, None)),
)
GDINO_OUTPUTS = (
    TensorSpec("logits", ("logits", "pred_logits"), (1, None, None)),
    TensorSpec("boxes", ("boxes", "pred_boxes"), (1, None, 4)),
)
SAM_DECODER_INPUTS = (
    TensorSpec("image_embeddings", ("image_embeddings",), (1, 256, 64, 64)),
    TensorSpec("point_coords", ("point_coords",), (1, None, 2)),
    TensorSpec("point_labels", ("point_labels",), (1, None)),
    TensorSpec("mask_input", ("mask_input",), (1, 1, 256, 256)),
    TensorSpec("has_mask_input", ("has_mask_input",), (1,)),
    TensorSpec("orig_im_size", ("orig_im_size",), (2,)),
)
#: SAM 2's decoder also reads the encoder's two high-resolution feature maps
SAM2_DECODER_INPUTS = (
    TensorSpec("high_res_0", ("high_res_feats_0",), (1, None, 256, 256), required=False),
    TensorSpec("high_res_1", ("high_res_feats_1",), (1, None, 128, 128), required=False),
)
SAM_DECODER_OUTPUTS = (
    TensorSpec("masks", ("masks",), (1, None, None, None)),
    TensorSpec("iou_predictions", ("iou_predictions", "scores"), (1, None)),
    TensorSpec("low_res_masks", ("low_res_masks",), (1, None, 256, 256), required=False),
)


#: Where SAM's box prompts come from (``GroundedSAMConfig.box_source``).
BOX_SOURCES = ("gdino", "learned")


def sam_encoder_specs(image_size: int) -> tuple[tuple[TensorSpec, ...], tuple[TensorSpec, ...]]:
    """The SAM (or SAM 2) image encoder's signature at ``image_size`` px (SAM 2's feature maps are optional)."""
    side = image_size // 16
    return ((TensorSpec("image", ("image", "input_image", "x", "images", "*"), (1, 3, image_size, image_size)),),
            (TensorSpec("image_embeddings", ("image_embeddings", "*"), (1, 256, side, side)),
             TensorSpec("high_res_0", ("high_res_feats_0",), (1, None, 4 * side, 4 * side), required=False),
             TensorSpec("high_res_1", ("high_res_feats_1",), (1, None, 2 * side, 2 * side), required=False)))


def _fraction(name: str, v: float) -> None:
    if not 0.0 <= v <= 1.0:
        raise ConfigError(f"grounded_sam.{name} = {v} must be in [0, 1]")


@dataclass(frozen=True)
class GroundedSAMConfig:
    """Settings of the Grounding DINO + SAM segmenter (paths to ONNX files, thresholds, clean-up).

    Pixel sizes refer to the original capture images. ``gdino_image_size`` (H, W) forces a fixed input
    size (needed when the export has static image dims; read from the model when it does).
    ``providers`` empty = CUDA when available, else CPU. ``threads`` 0 = onnxruntime's default.
    ``box_source``: ``gdino`` (the paper: Grounding DINO boxes from ``prompt``) or ``learned`` (hybrid prompting for
    users with SAM weights but no Grounding DINO: each instance of torm's learned segmenter, configured by
    ``learned`` (a :class:`torm.segmentation.learned.LearnedConfig` mapping), prompts SAM with its box; then
    ``gdino_model`` and ``bert_vocab`` are not needed).
    ``memory_arena``: onnxruntime's CPU memory arena (its default) keeps each session's largest working set; off
    (torm's default) tensors are freed as they die: Grounding DINO + SAM ViT-B peaked at 5.2 GB instead of 12.8 GB
    and ran a view in 18.8 s instead of 22.0 s (``benchmarks/results/gsam_cpu*.md``, 2026-12-07). The segmenter
    refuses a configuration whose estimated peak (:func:`torm.resources.grounded_sam_bytes`) exceeds the free memory
    before loading anything.
    """

    gdino_model: str = ""
    bert_vocab: str = ""
    sam_encoder: str = ""
    sam_decoder: str = ""
    prompt: str = "clear glass. transparent object."
    box_threshold: float = 0.35
    text_threshold: float = 0.25
    nms_iou: float = 0.5
    max_detections: int = 20
    max_box_fraction: float = 0.9
    min_box_px: float = 2.0
    gdino_short_side: int = 800
    gdino_max_size: int = 1333
    gdino_image_size: tuple[int, int] | None = None
    max_text_len: int = 256
    logits_are_probabilities: bool = False
    sam_image_size: int = 1024
    mask_threshold: float = 0.0
    fill_holes: bool = True
    min_blob_area_px: int = 64
    keep_largest_component: bool = False
    providers: tuple[str, ...] = ()
    threads: int = 0
    box_source: str = "gdino"
    learned: dict[str, Any] = field(default_factory=dict)
    memory_arena: bool = False

    def __post_init__(self) -> None:
        if self.box_source not in BOX_SOURCES:
            from torm.errors import UnknownNameError

            raise UnknownNameError("grounded_sam.box_source", self.box_source, BOX_SOURCES)
        for name in ("box_threshold", "text_threshold", "nms_iou", "max_box_fraction"):
            _fraction(name, getattr(self, name))
        if not self.prompt.strip():
            raise ConfigError("grounded_sam.prompt is empty; give phrases like 'clear glass. transparent object.'")
        if self.gdino_short_side <= 0 or self.gdino_max_size < self.gdino_short_side:
            raise ConfigError("grounded_sam: need 0 < gdino_short_side <= gdino_max_size")
        if self.gdino_image_size is not None and min(self.gdino_image_size) <= 0:
            raise ConfigError("grounded_sam.gdino_image_size must be a positive (H, W) or null")
        if self.sam_image_size <= 0 or self.sam_image_size % 16:
            raise ConfigError("grounded_sam.sam_image_size must be a positive multiple of 16 (1024 for SAM)")
        if self.max_detections <= 0 or self.max_text_len < 3 or self.min_blob_area_px < 0 or self.threads < 0:
            raise ConfigError(
                "grounded_sam: need max_detections > 0, max_text_len >= 3, min_blob_area_px >= 0, threads >= 0")


def read_card(model_path: str | Path) -> dict[str, Any] | None:
    """The model card ``<model_path>.json`` beside an exported ONNX file, or None when there is none."""
    p = Path(str(model_path) + ".json")
    if not p.is_file():
        return None
    try:
        card = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFileError(f"model card {p} cannot be read ({exc}); re-export with `torm export-models`") from exc
    return card if isinstance(card, dict) else None


def gdino_resize_hw(h: int, w: int, short: int = 800, max_size: int = 1333) -> tuple[int, int]:
    """Grounding DINO's ``RandomResize([short], max_size)`` output (H, W) for an (h, w) image."""
    size = short
    lo, hi = float(min(h, w)), float(max(h, w))
    if hi / lo * size > max_size:
        size = int(round(max_size * lo / hi))
    if (w <= h and w == size) or (h <= w and h == size):
        return h, w
    if w < h:
        return int(size * h / w), size
    return size, int(size * w / h)


def letterbox_hw(h: int, w: int, canvas_hw: tuple[int, int]) -> tuple[tuple[int, int], float]:
    """The size (h', w') an (h, w) image takes inside a fixed ``canvas_hw`` keeping its aspect ratio (the largest
    that fits; the rest is padding at the right and bottom), and the scale s = h'/h = w'/w (px per image px)."""
    H, W = canvas_hw
    s = min(H / h, W / w)
    return (min(H, max(1, round(h * s))), min(W, max(1, round(w * s)))), float(s)


def gdino_letterbox(rgb: np.ndarray, canvas_hw: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float]]:
    """(H, W, 3) uint8 RGB -> ((1, 3, Hc, Wc) float32 normalised input, canvas (W, H) in original-image pixels).

    For an export with a static input size: the image keeps its aspect ratio (resized into the canvas, padded at
    the right and bottom with the ImageNet mean, i.e. 0 after normalisation) instead of being stretched. The
    official processor also masks the padding in attention; a static export has no mask input, so the padding is
    mean grey the model sees. Boxes normalised to the canvas map back with the returned canvas size
    (``decode_grounding(..., canvas_wh=...)``)."""
    h, w = rgb.shape[:2]
    (rh, rw), s = letterbox_hw(h, w, canvas_hw)
    x = gdino_preprocess(rgb, (rh, rw))
    Hc, Wc = canvas_hw
    out = np.zeros((1, 3, Hc, Wc), np.float32)
    out[:, :, :rh, :rw] = x
    return out, (Wc / s, Hc / s)


def _resize(rgb: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    h, w = hw
    if (h, w) == rgb.shape[:2]:
        return rgb
    interp = cv2.INTER_AREA if h < rgb.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(rgb, (w, h), interpolation=interp)


def gdino_preprocess(rgb: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (1, 3, h, w) float32 ImageNet-normalised at size ``hw``."""
    x = _resize(rgb, hw).astype(np.float32) / 255.0
    x = (x - IMAGENET_MEAN) / IMAGENET_STD
    return x.transpose(2, 0, 1)[None].astype(np.float32)


def sam_resize_hw(h: int, w: int, long_side: int = 1024) -> tuple[int, int]:
    """SAM's ``ResizeLongestSide.get_preprocess_shape``."""
    scale = long_side / max(h, w)
    return int(h * scale + 0.5), int(w * scale + 0.5)


def sam_preprocess(rgb: np.ndarray, long_side: int = 1024) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (1, 3, S, S) float32: longest side S, SAM-normalised, zero-padded."""
    nh, nw = sam_resize_hw(*rgb.shape[:2], long_side)
    x = (_resize(rgb, (nh, nw)).astype(np.float32) - SAM_PIXEL_MEAN) / SAM_PIXEL_STD
    out = np.zeros((1, 3, long_side, long_side), np.float32)
    out[0, :, :nh, :nw] = x.transpose(2, 0, 1)
    return out


def sam2_preprocess(rgb: np.ndarray, side: int = 1024) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (1, 3, S, S) float32 as SAM 2's predictor prepares it: resized to the square S x S
    (aspect not kept, no padding), RGB/255 normalised with the ImageNet mean/std."""
    x = _resize(rgb, (side, side)).astype(np.float32) / 255.0
    return ((x - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)[None].astype(np.float32)


def sam2_box_prompt(box_xyxy: np.ndarray, hw: tuple[int, int], side: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Box corners in SAM 2's square frame (1, 2, 2) float32 and their labels (1, 2) = [2, 3]."""
    h, w = hw
    pts = np.asarray(box_xyxy, dtype=np.float64).reshape(2, 2) * np.array([side / w, side / h])
    return pts[None].astype(np.float32), np.array([[2.0, 3.0]], dtype=np.float32)


def sam_box_prompt(box_xyxy: np.ndarray, hw: tuple[int, int], long_side: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Box corners in the resized frame (1, 2, 2) float32 and their labels (1, 2) = [2, 3]."""
    h, w = hw
    nh, nw = sam_resize_hw(h, w, long_side)
    pts = np.asarray(box_xyxy, dtype=np.float64).reshape(2, 2) * np.array([nw / w, nh / h])
    return pts[None].astype(np.float32), np.array([[2.0, 3.0]], dtype=np.float32)


def select_sam_mask(masks_1xcxhxw: np.ndarray, iou_1xc: np.ndarray, n_points: int) -> np.ndarray:
    """Pick one (H, W) logit map like SamOnnxModel.select_masks (multimask output unless > 2 points)."""
    m = masks_1xcxhxw[0]
    if m.shape[0] == 1:
        return m[0]
    reweight = np.zeros(m.shape[0])
    reweight[0] = 1000.0
    score = np.asarray(iou_1xc, dtype=np.float64)[0] + (n_points - 2.5) * reweight
    return m[int(np.argmax(score))]


class GroundedSAMSegmenter(Segmenter):
    """Grounding DINO + SAM on onnxruntime; sessions are loaded (and checked) on construction."""

    name = "grounded_sam"

    def __init__(self, config: GroundedSAMConfig) -> None:
        self.config = c = config
        check_fits(self.memory_need(), f"grounded_sam ({self.memory_label()})",
                   "keep grounded_sam memory_arena false (the default: 5.2 GB instead of 12.8 GB measured for "
                   "Grounding DINO + SAM ViT-B), export SAM 2.1 Hiera-Tiny (`torm export-models --sam-kind sam2`), "
                   "prompt SAM with the learned segmenter's boxes (box_source: learned), or free memory")
        providers = list(c.providers) or None
        enc_in, enc_out = sam_encoder_specs(c.sam_image_size)
        self.sam_encoder = open_session(c.sam_encoder, "grounded_sam.sam_encoder", enc_in, enc_out, providers,
                                        c.threads, c.memory_arena)
        self.sam_decoder = open_session(c.sam_decoder, "grounded_sam.sam_decoder",
                                        SAM_DECODER_INPUTS + SAM2_DECODER_INPUTS, SAM_DECODER_OUTPUTS, providers,
                                        c.threads, c.memory_arena)
        enc2 = {"high_res_0", "high_res_1"} <= set(self.sam_encoder.outputs)
        dec2 = {"high_res_0", "high_res_1"} <= set(self.sam_decoder.inputs)
        if enc2 != dec2:
            raise ModelFileError(
                f"grounded_sam: the encoder {self.sam_encoder.path} is a {'SAM 2' if enc2 else 'SAM'} encoder but the "
                f"decoder {self.sam_decoder.path} is a {'SAM 2' if dec2 else 'SAM'} decoder (SAM 2's exchange "
                "high_res_feats_0/1); export both with the same `torm export-models --sam-kind`")
        #: ``sam`` or ``sam2``: which SAM the files hold (told apart by the encoder's outputs)
        self.sam_kind = "sam2" if enc2 else "sam"
        self.boxer = None
        if c.box_source == "learned":  # hybrid prompting: the learned segmenter's instances prompt SAM
            from torm.config import from_dict
            from torm.segmentation.learned import LearnedConfig, LearnedSegmenter

            self.boxer = LearnedSegmenter(from_dict(LearnedConfig, dict(c.learned), where="grounded_sam.learned"))
            self.gdino = None
            return
        if not c.bert_vocab:
            raise ModelFileError("grounded_sam.bert_vocab is not set; point it at the vocab.txt `torm export-models` "
                                 "writes beside the Grounding DINO export (bert-base-uncased's vocabulary)")
        self.tokenizer = WordPieceTokenizer.from_file(c.bert_vocab)
        self.gdino: BoundSession | None = open_session(c.gdino_model, "grounded_sam.gdino_model", GDINO_INPUTS,
                                                       GDINO_OUTPUTS, providers, c.threads, c.memory_arena)
        #: the export's model card (``<gdino_model>.json``, written by ``torm export-models``), or None
        self.gdino_card = read_card(c.gdino_model)
        if self.gdino_card is None:
            log.warning("%s has no model card (%s.json): the vocabulary %s cannot be checked against the export; "
                        "use files written by `torm export-models`", c.gdino_model, c.gdino_model, c.bert_vocab)
        else:
            check_vocabulary(self.tokenizer, self.gdino_card,
                             self.gdino_card.get("special_token_ids") or GROUNDING_SPECIAL_IDS)
        ids_dims = static_dims(self.gdino, "input_ids")
        self._text_len = ids_dims[1]
        img_dims = static_dims(self.gdino, "img")
        self._gdino_static_hw = (img_dims[2], img_dims[3]) if img_dims[2] and img_dims[3] else None
        self.text: TextInputs = grounding_text_inputs(self.tokenizer, c.prompt, c.max_text_len, pad_to=self._text_len)

    def _files(self) -> list[Path]:
        c = self.config
        names = [c.sam_encoder, c.sam_decoder] + ([c.gdino_model] if c.box_source == "gdino" else [])
        return [Path(n).expanduser() for n in names if n and Path(n).expanduser().is_file()]

    def _declared_sam_kind(self) -> str:
        """``sam2`` when the encoder's card says so (``torm export-models`` writes it), else ``sam``."""
        card = read_card(self.config.sam_encoder) if self.config.sam_encoder else None
        return "sam2" if card and (card.get("sam_kind") == "sam2" or "sam2" in str(card.get("model", ""))) else "sam"

    def _declared_gdino_px(self) -> int:
        """Grounding DINO's input pixels: the configured size, else the export's card, else the official resize of
        a 16:9 frame at its maximum (800 x 1333); 0 with box_source learned."""
        c = self.config
        if c.box_source != "gdino":
            return 0
        if c.gdino_image_size is not None:
            return int(c.gdino_image_size[0]) * int(c.gdino_image_size[1])
        hw = (read_card(c.gdino_model) or {}).get("image_hw") if c.gdino_model else None
        return int(hw[0]) * int(hw[1]) if hw else c.gdino_short_side * c.gdino_max_size

    def memory_need(self) -> float:
        """Estimated peak memory (bytes) of this configuration (:func:`torm.resources.grounded_sam_bytes`), from the
        files on disk and their cards, before anything is loaded."""
        return grounded_sam_bytes(sum(p.stat().st_size for p in self._files()), self._declared_gdino_px(),
                                  self._declared_sam_kind(), self.config.sam_image_size, self.config.memory_arena)

    def memory_label(self) -> str:
        c = self.config
        boxes = "Grounding DINO boxes" if c.box_source == "gdino" else "learned boxes"
        return (f"{boxes}, {self._declared_sam_kind()} at {c.sam_image_size} px, memory_arena "
                f"{str(c.memory_arena).lower()}")

    def gdino_input_hw(self, h: int, w: int) -> tuple[int, int]:
        if self._gdino_static_hw is not None:
            return self._gdino_static_hw
        if self.config.gdino_image_size is not None:
            return tuple(self.config.gdino_image_size)  # type: ignore[return-value]
        return gdino_resize_hw(h, w, self.config.gdino_short_side, self.config.gdino_max_size)

    def detect(self, rgb: np.ndarray) -> DecodedBoxes:
        """Box prompts (xyxy pixels of ``rgb``), scores and phrases: Grounding DINO's after thresholds and NMS, or
        with ``box_source: learned`` the boxes of the learned segmenter's instances."""
        if self.boxer is not None:
            _, dets = self.boxer.segment_image(rgb)
            dets = sorted(dets, key=lambda d: -d.score)[: self.config.max_detections]
            return DecodedBoxes(np.array([d.box_xyxy for d in dets], float).reshape(-1, 4),
                                np.array([d.score for d in dets], float), tuple(d.label for d in dets))
        c, t = self.config, self.text
        h, w = rgb.shape[:2]
        canvas = None
        if self._gdino_static_hw is not None:  # a fixed-size export: letterboxed, never stretched
            img, canvas = gdino_letterbox(rgb, self._gdino_static_hw)
        else:
            img = gdino_preprocess(rgb, self.gdino_input_hw(h, w))
        logits, boxes = self.gdino.run(
            {"img": img, "input_ids": t.input_ids, "attention_mask": t.attention_mask, "position_ids": t.position_ids,
             "token_type_ids": t.token_type_ids, "text_token_mask": t.self_attention_mask},
            ("logits", "boxes"),
        )
        return decode_grounding(
            logits[0], boxes[0], t, self.tokenizer, (w, h), c.box_threshold, c.text_threshold, c.nms_iou,
            logits_are_probabilities=c.logits_are_probabilities, max_box_fraction=c.max_box_fraction,
            min_box_px=c.min_box_px, max_detections=c.max_detections, canvas_wh=canvas,
        )

    def embed(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """The encoder's outputs for ``rgb`` by role: ``image_embeddings`` (1, 256, 64, 64) and, for SAM 2,
        ``high_res_0`` / ``high_res_1``."""
        size = self.config.sam_image_size
        if self.sam_kind == "sam2":
            roles = ("image_embeddings", "high_res_0", "high_res_1")
            out = self.sam_encoder.run({"image": sam2_preprocess(rgb, size)}, roles)
            return dict(zip(roles, out, strict=True))
        return {"image_embeddings": self.sam_encoder.run({"image": sam_preprocess(rgb, size)},
                                                         ("image_embeddings",))[0]}

    def mask_logits(self, embeddings: dict[str, np.ndarray], box_xyxy: np.ndarray, hw: tuple[int, int]
                    ) -> np.ndarray:
        """(H, W) SAM mask logits for one box prompt (``embeddings`` from :meth:`embed`)."""
        prompt = sam2_box_prompt if self.sam_kind == "sam2" else sam_box_prompt
        coords, labels = prompt(box_xyxy, hw, self.config.sam_image_size)
        side = 4 * self.config.sam_image_size // 16
        masks, iou = self.sam_decoder.run(
            {**embeddings, "point_coords": coords, "point_labels": labels,
             "mask_input": np.zeros((1, 1, side, side), np.float32), "has_mask_input": np.zeros(1, np.float32),
             "orig_im_size": np.array(hw, dtype=np.float32)},
            ("masks", "iou_predictions"),
        )
        m = select_sam_mask(masks, iou, coords.shape[1])
        if m.shape != tuple(hw):
            raise CaptureError(f"SAM decoder returned a {m.shape} mask for a {hw} image; export it with orig_im_size")
        return m

    def segment_image(self, rgb: np.ndarray, timings: dict[str, float]) -> tuple[np.ndarray, tuple[Detection, ...]]:
        """(H, W) int32 instance mask and detections of one RGB image; adds stage times to ``timings``."""
        c = self.config
        hw = rgb.shape[:2]
        t0 = time.perf_counter()
        dec = self.detect(rgb)
        t1 = time.perf_counter()
        timings["gdino"] = timings.get("gdino", 0.0) + t1 - t0
        if len(dec.scores_n) == 0:
            return np.zeros(hw, np.int32), ()
        emb = self.embed(rgb)
        t2 = time.perf_counter()
        timings["sam_encoder"] = timings.get("sam_encoder", 0.0) + t2 - t1
        bins, t_dec, t_post = [], 0.0, 0.0
        for box in dec.boxes_nx4:
            ta = time.perf_counter()
            logit = self.mask_logits(emb, box, hw)
            tb = time.perf_counter()
            bins.append(clean_mask(logit, c.mask_threshold, c.fill_holes, c.min_blob_area_px,
                                   c.keep_largest_component))
            t_dec += tb - ta
            t_post += time.perf_counter() - tb
        mask, ids = compose_instances(bins, hw, c.min_blob_area_px)
        timings["sam_decoder"] = timings.get("sam_decoder", 0.0) + t_dec
        timings["postprocess"] = timings.get("postprocess", 0.0) + t_post
        dets = tuple(
            Detection(tuple(float(x) for x in b), float(s), p, int(i))  # type: ignore[arg-type]
            for b, s, p, i in zip(dec.boxes_nx4, dec.scores_n, dec.phrases, ids, strict=True)
        )
        return mask, dets

    def segment(self, capture: Capture) -> SegmentationResult:
        t0 = time.perf_counter()
        timings: dict[str, float] = {}
        masks, dets = [], []
        for i, view in enumerate(capture.views):
            if view.rgb is None:
                raise CaptureError(f"view {i} ({view.name!r}) has no RGB image; grounded_sam segments colour images")
            m, d = self.segment_image(view.rgb, timings)
            masks.append(m)
            dets.append(d)
            log.debug("view %d: %d detections", i, len(d))
        timings["total"] = time.perf_counter() - t0
        out = np.stack(masks)
        info: dict[str, Any] = {"segmenter": self.name, "box_source": self.config.box_source, "sam_kind": self.sam_kind,
                                "prompt": self.config.prompt if self.boxer is None else None,
                                "providers": self.sam_encoder.session.get_providers()}
        info.update(score_against_capture(out, capture))
        return SegmentationResult(out, tuple(dets), timings, info)
