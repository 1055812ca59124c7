"""The learned segmenter: a small U-Net trained here on rendered scenes, run with onnxruntime.

It reads pixels only (no ground truth, no depth): per view, the network predicts an object-foreground
probability and an instance-boundary probability; :func:`torm.segmentation.instances.extract_instances`
turns them into instances (connected cores grown back into the foreground). Ids are per view, 1..N by
descending area, and do **not** correspond across views (like Grounded-SAM); the reconstruction uses the
union ``mask > 0``.

Model file signature (``model``; default the shipped ``models/learned_seg.onnx``):
    input  ``image`` (1, 3, H, W) float32, RGB in [0, 255] (normalisation is inside the graph), H and W
           multiples of 16 (torm pads bottom/right by edge replication);
    output ``logits`` (1, 2, H, W) float32: channel 0 foreground, channel 1 boundary band (sigmoid -> prob).

Each view is resized to ``input_width`` px wide (aspect kept; the shipped model was trained on the
pipeline's 640x360 frames of the 91.5 deg camera, so objects should have about that pixel size),
padded, run, cropped and the probabilities resized back to the capture size (bilinear).
Training, data recipe and held-out metrics: the JSON beside the model file (``models/learned_seg.json``).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torm.errors import CaptureError, ConfigError
from torm.segmentation.base import Detection, SegmentationResult, Segmenter
from torm.segmentation.instances import extract_instances
from torm.segmentation.onnx_models import TensorSpec, open_session
from torm.segmentation.quality import mask_quality
from torm.types import Capture

log = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_MODEL = MODELS_DIR / "learned_seg.onnx"
INPUTS = (TensorSpec("image", ("image",), (1, 3, None, None)),)
OUTPUTS = (TensorSpec("logits", ("logits",), (1, 2, None, None)),)
STRIDE = 16
#: post-processing used when neither the config nor the model card sets it (the first model's untuned values)
POSTPROCESS_DEFAULTS: dict[str, Any] = {"fg_threshold": 0.5, "boundary_threshold": 0.5, "min_core_px": 8,
                                        "flip_tta": False}


@dataclass(frozen=True)
class LearnedConfig:
    """Settings of the learned segmenter (thresholds are probabilities; sizes in pixels of the capture).

    ``model`` empty = the shipped file. ``input_width`` 0 = the capture's own width.
    ``min_area_px`` / ``min_core_px`` refer to the network input resolution.
    ``fg_threshold``, ``boundary_threshold``, ``min_core_px`` and ``flip_tta`` left unset (None) come from the
    model card's ``postprocess`` entry (calibrated on the model's validation split by
    ``benchmarks/seg_postprocess.py``), else 0.5, 0.5, 8 px and False. ``flip_tta``: average the probabilities
    with those of the horizontally flipped view (two network runs per view). ``core_split_px`` (network input
    pixels, 0 = off): split an instance core at a neck this deep
    (:func:`torm.segmentation.instances.split_cores_at_necks`); off: at 4 px (chosen on val) it gained 0.003 object
    IoU on unseen layouts and 0.015 on held-out shapes for 0.3-0.5 more false positives per view
    (``benchmarks/results/seg_miss_causes.md``).
    """

    model: str = ""
    input_width: int = 640
    fg_threshold: float | None = None
    boundary_threshold: float | None = None
    min_core_px: int | None = None
    flip_tta: bool | None = None
    min_area_px: int = 30
    core_split_px: float = 0.0
    providers: tuple[str, ...] = ()
    threads: int = 0

    def __post_init__(self) -> None:
        for name in ("fg_threshold", "boundary_threshold"):
            v = getattr(self, name)
            if v is not None and not 0.0 < v < 1.0:
                raise ConfigError(f"learned.{name} = {v} must be in (0, 1)")
        if self.input_width < 0 or (self.input_width and self.input_width < STRIDE):
            raise ConfigError(f"learned.input_width must be 0 (capture width) or >= {STRIDE} px")
        if (self.min_core_px is not None and self.min_core_px < 1) or self.min_area_px < 0 or self.threads < 0:
            raise ConfigError("learned: need min_core_px >= 1, min_area_px >= 0, threads >= 0")
        if self.core_split_px < 0:
            raise ConfigError(f"learned.core_split_px = {self.core_split_px} must be >= 0 (0 turns the split off)")

    @property
    def model_path(self) -> Path:
        return Path(self.model).expanduser() if self.model else DEFAULT_MODEL


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -30, 30)))


class LearnedSegmenter(Segmenter):
    """U-Net foreground + boundary on onnxruntime; the session is loaded (and checked) on construction."""

    name = "learned"

    def __init__(self, config: LearnedConfig | None = None) -> None:
        self.config = c = config or LearnedConfig()
        self.session = open_session(c.model_path, "learned.model", INPUTS, OUTPUTS, list(c.providers) or None,
                                    c.threads)
        card = c.model_path.with_suffix(".json")
        self.card: dict[str, Any] = json.loads(card.read_text()) if card.is_file() else {}
        post = self.card.get("postprocess", {})
        #: the post-processing in use: the config's values, else the card's calibration, else the defaults
        self.postprocess: dict[str, Any] = {k: getattr(c, k) if getattr(c, k) is not None else post.get(k, d)
                                            for k, d in POSTPROCESS_DEFAULTS.items()}

    def probabilities(self, rgb: np.ndarray, flip_tta: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) foreground and boundary probabilities of one (H, W, 3) uint8 RGB image, at its own size.

        ``flip_tta`` (None = :attr:`postprocess`): the mean of the view's and its mirror image's probabilities.
        """
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise CaptureError(f"the learned segmenter needs (H, W, 3) uint8 RGB images, got {rgb.shape} {rgb.dtype}")
        if flip_tta if flip_tta is not None else self.postprocess["flip_tta"]:
            fg, bd = self._probabilities(rgb)
            ffg, fbd = self._probabilities(np.ascontiguousarray(rgb[:, ::-1]))
            return (fg + ffg[:, ::-1]) / 2, (bd + fbd[:, ::-1]) / 2
        return self._probabilities(rgb)

    def _probabilities(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = rgb.shape[:2]
        tw = self.config.input_width or w
        th = max(int(round(h * tw / w)), 1)
        x = rgb if (th, tw) == (h, w) else cv2.resize(rgb, (tw, th), interpolation=cv2.INTER_AREA)
        ph, pw = -th % STRIDE, -tw % STRIDE
        if ph or pw:
            x = cv2.copyMakeBorder(x, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
        inp = x.astype(np.float32).transpose(2, 0, 1)[None]
        logits = self.session.run({"image": inp}, ("logits",))[0][0, :, :th, :tw]
        prob = _sigmoid(logits.astype(np.float32))
        if (th, tw) != (h, w):
            prob = np.stack([cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR) for p in prob])
        return prob[0], prob[1]

    def segment_image(self, rgb: np.ndarray) -> tuple[np.ndarray, tuple[Detection, ...]]:
        """(H, W) int32 instance mask and one detection (box, mean foreground probability) per instance."""
        c, pp = self.config, self.postprocess
        fg, bd = self.probabilities(rgb)
        scale = (rgb.shape[1] / (c.input_width or rgb.shape[1])) ** 2
        mask, scores = extract_instances(fg, bd, pp["fg_threshold"], pp["boundary_threshold"],
                                         max(int(round(pp["min_core_px"] * scale)), 1),
                                         int(round(c.min_area_px * scale)), c.core_split_px * scale ** 0.5)
        dets = []
        for i, s in enumerate(scores, start=1):
            ys, xs = np.nonzero(mask == i)
            dets.append(Detection((float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)), s,
                                  "object", i))
        return mask, tuple(dets)

    def segment(self, capture: Capture) -> SegmentationResult:
        t0 = time.perf_counter()
        masks, dets = [], []
        for i, view in enumerate(capture.views):
            if view.rgb is None:
                raise CaptureError(f"view {i} ({view.name!r}) has no RGB image; the learned segmenter reads pixels")
            m, d = self.segment_image(view.rgb)
            masks.append(m)
            dets.append(d)
        out = np.stack(masks)
        info: dict[str, Any] = {"segmenter": self.name, "model": str(self.config.model_path),
                                "model_renderer": self.card.get("data", {}).get("renderer"),
                                "postprocess": dict(self.postprocess)}
        if capture.has_masks:
            info["quality"] = mask_quality(out, capture.masks())
        return SegmentationResult(out, tuple(dets), {"total": time.perf_counter() - t0}, info)


_SHIPPED: list[LearnedSegmenter] = []


def foreground_mask(rgb: np.ndarray) -> np.ndarray:
    """(H, W) bool foreground of the shipped model on one (H, W, 3) uint8 RGB image (instances merged).

    A ``MODULE:FUNCTION`` hook for ``benchmarks/render.py --segmenter torm.segmentation.learned:foreground_mask``:
    the render-noise agreement measured with the segmenter the pipeline runs, not a proxy. The session is
    created on the first call (the shipped ONNX file, onnxruntime's default threads) and kept.
    """
    if not _SHIPPED:
        _SHIPPED.append(LearnedSegmenter())
    return _SHIPPED[0].segment_image(rgb)[0] > 0
