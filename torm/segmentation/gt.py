"""Ground-truth segmenter: the simulator's instance masks already stored in the capture."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from torm.errors import CaptureError
from torm.segmentation.base import SegmentationResult, Segmenter
from torm.types import Capture


@dataclass(frozen=True)
class GTConfig:
    """The ground-truth segmenter has no settings; the config exists so every segmenter takes one."""


def gt_masks(capture: Capture) -> np.ndarray:
    """(V, H, W) int32 ground-truth instance masks; CaptureError naming the first view without one."""
    for i, v in enumerate(capture.views):
        if v.mask is None:
            raise CaptureError(
                f"view {i} ({v.name!r}) has no ground-truth instance mask; the 'gt' and 'noisy' segmenters need "
                "simulated captures with masks (or use --segmenter grounded_sam on RGB images)"
            )
    return np.stack([v.mask for v in capture.views]).astype(np.int32)


class GTSegmenter(Segmenter):
    """Returns the capture's own instance masks (object k -> id k)."""

    name = "gt"

    def __init__(self, config: GTConfig | None = None) -> None:
        self.config = config or GTConfig()

    def segment(self, capture: Capture) -> SegmentationResult:
        t0 = time.perf_counter()
        masks = gt_masks(capture)
        return SegmentationResult(
            masks_vxhxw=masks,
            timings={"total": time.perf_counter() - t0},
            info={"segmenter": self.name, "quality": {"silhouette_iou_mean": 1.0, "silhouette_iou_min": 1.0}},
        )
