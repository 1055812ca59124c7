"""The segmenter interface: capture in, per-view instance masks and detections out.

A :class:`Segmenter` turns every view of a :class:`~torm.types.Capture` into an int32 instance mask
(0 background, k > 0 instance k). Instance ids are per view: the ground-truth and noisy segmenters
keep the simulator's object ids, Grounded-SAM numbers its detections 1..N in descending score, so
ids do not correspond across views there. The reconstruction only needs the union silhouette
(``mask > 0``), see :mod:`torm.segmentation.multiview`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from torm.errors import SegmentationError
from torm.types import Capture


@dataclass(frozen=True)
class Detection:
    """One detected instance in one view.

    Attributes:
        box_xyxy: (x_min, y_min, x_max, y_max) in pixels (x right, y down), float.
        score: detector confidence in [0, 1].
        label: phrase or class name the detection was matched to.
        instance_id: the value this instance has in the view's mask (0 when it got no pixels).
    """

    box_xyxy: tuple[float, float, float, float]
    score: float
    label: str = ""
    instance_id: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"box_xyxy": list(self.box_xyxy), "score": self.score, "label": self.label,
                "instance_id": self.instance_id}


@dataclass(frozen=True, eq=False)
class SegmentationResult:
    """Masks and detections for every view of a capture.

    Attributes:
        masks_vxhxw: (V, H, W) int32 instance masks, 0 = background.
        detections: per view, the detections in that view (empty tuples for mask-only segmenters).
        timings: wall time in seconds per stage (e.g. ``"detect"``, ``"sam"``, ``"total"``).
        info: segmenter name, config and, when ground truth was available, the mask quality
            (see :func:`torm.segmentation.quality.mask_quality`).
    """

    masks_vxhxw: np.ndarray
    detections: tuple[tuple[Detection, ...], ...] = ()
    timings: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = np.asarray(self.masks_vxhxw)
        if m.ndim != 3:
            raise SegmentationError(f"masks must be (V, H, W), got shape {m.shape}")
        if not np.issubdtype(m.dtype, np.integer):
            raise SegmentationError(f"masks must be integer instance ids, got dtype {m.dtype}")
        object.__setattr__(self, "masks_vxhxw", m.astype(np.int32, copy=False))
        dets = tuple(tuple(d) for d in self.detections) if self.detections else tuple(() for _ in range(len(m)))
        if len(dets) != len(m):
            raise SegmentationError(f"got detections for {len(dets)} views but masks for {len(m)}")
        object.__setattr__(self, "detections", dets)

    @property
    def n_views(self) -> int:
        return int(self.masks_vxhxw.shape[0])

    @property
    def silhouettes_vxhxw(self) -> np.ndarray:
        """(V, H, W) bool union of all instances per view."""
        return self.masks_vxhxw > 0

    def apply(self, capture: Capture) -> Capture:
        """A copy of ``capture`` whose views carry these masks (replacing any ground-truth masks); its metadata's
        :data:`MASK_SOURCE_KEY` names the segmenter, so the masks are never taken for ground truth later.

        Pixels without evidence (no source pixel after the lens distortion was undone at load,
        :func:`torm.capture.lens.no_evidence_masks`) hold no instance in the attached masks, whatever the segmenter
        saw in the black border there; the capture's metadata keeps marking them, so the reconstruction ignores them
        instead of reading them as background.
        """
        if capture.image_size != tuple(self.masks_vxhxw.shape[1:]):
            raise SegmentationError(
                f"masks are {self.masks_vxhxw.shape[1:]} (H, W) but the capture is {capture.image_size}; "
                "segment the same capture you attach the masks to"
            )
        from torm.capture.lens import no_evidence_masks

        masks = self.masks_vxhxw
        unknown = no_evidence_masks(capture)
        if unknown is not None and (masks[unknown] != 0).any():
            masks = np.where(unknown, 0, masks).astype(np.int32)
        name = self.info.get("segmenter", "?")
        if name == "gt" and not self.info.get("phantoms"):
            return capture.with_masks(masks)  # the capture's own masks: their source stays
        source = f"segmenter {name}"
        if self.info.get("model_fingerprint"):
            source += f" ({self.info['model_fingerprint']})"
        out = capture.with_masks(masks)
        return replace(out, metadata={**out.metadata, MASK_SOURCE_KEY: source})

    def summary(self) -> dict[str, Any]:
        """JSON-friendly summary: counts, timings and info (no arrays)."""
        return {
            "n_views": self.n_views,
            "instances_per_view": [int(len(np.unique(m[m > 0]))) for m in self.masks_vxhxw],
            "detections_per_view": [len(d) for d in self.detections],
            "timings": dict(self.timings),
            **{k: v for k, v in self.info.items()},
        }


#: Capture metadata key naming where a capture's masks come from: :data:`GT_MASK_SOURCE` for the simulator's
#: instance masks, ``segmenter <name> (...)`` for a segmenter's; absent = unknown (recorded frames), never ground truth.
MASK_SOURCE_KEY = "mask_source"
#: The value the simulated camera rig writes. Only sources ending in "(ground truth)" (this one, the analytic sphere
#: captures of the tests) are called ground truth.
GT_MASK_SOURCE = "simulator (ground truth)"


def masks_are_ground_truth(capture: Capture) -> bool:
    """True only when the capture's masks are the simulator's own instance masks (see :data:`MASK_SOURCE_KEY`)."""
    return capture.has_masks and str(capture.metadata.get(MASK_SOURCE_KEY, "")).endswith("(ground truth)")


def score_against_capture(masks_vxhxw: np.ndarray, capture: Capture) -> dict[str, Any]:
    """``{"quality", "quality_reference"}`` of predicted masks against the capture's own masks, named by their source
    (never assumed ground truth); ``{}`` when the capture has no masks."""
    if not capture.has_masks:
        return {}
    from torm.segmentation.quality import mask_quality

    return {"quality": mask_quality(masks_vxhxw, capture.masks()), "quality_reference": mask_reference(capture)}


def mask_reference(capture: Capture) -> str:
    """How to name a capture's masks when scoring against them: ``ground truth`` only for the simulator's."""
    if masks_are_ground_truth(capture):
        return f"ground truth ({capture.metadata[MASK_SOURCE_KEY].removesuffix(' (ground truth)')})"
    src = capture.metadata.get(MASK_SOURCE_KEY)
    return f"the capture's masks ({src})" if src else "the capture's masks (source unknown, not ground truth)"


class Segmenter(abc.ABC):
    """Extracts per-view instance masks from a capture."""

    #: registry name ("gt", "noisy", "grounded_sam")
    name: str = ""

    @abc.abstractmethod
    def segment(self, capture: Capture) -> SegmentationResult:
        """Segment every view of ``capture``; raises a SegmentationError/CaptureError on bad input."""


def segment_capture(segmenter: Segmenter, capture: Capture) -> tuple[Capture, SegmentationResult]:
    """Run ``segmenter`` and return the capture with the predicted masks attached, plus the result."""
    result = segmenter.segment(capture)
    return result.apply(capture), result
