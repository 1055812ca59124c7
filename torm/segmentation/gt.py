"""Ground-truth segmenter: the simulator's instance masks already stored in the capture."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from torm.errors import CaptureError, ConfigError
from torm.segmentation.base import SegmentationResult, Segmenter
from torm.types import Capture


@dataclass(frozen=True)
class GTConfig:
    """Settings of the ground-truth segmenter.

    Attributes:
        phantoms: forced false positives, ``((x, y, z, radius), ...)`` spheres in the world frame (m) that every
            view's mask marks as an extra object where it shows background, as a segmenter that mistakes an opaque
            object for glass would, consistently across views. Each gets its own instance id after the real ones.
            For testing that the loop attempts what it believes in (``phantom_attempt`` rows); empty by default.
    """

    phantoms: tuple[tuple[float, float, float, float], ...] = ()

    def __post_init__(self) -> None:
        ph = tuple(tuple(float(v) for v in p) for p in self.phantoms)
        for p in ph:
            if len(p) != 4 or not np.all(np.isfinite(p)) or p[3] <= 0:
                raise ConfigError(f"gt.phantoms: each entry is (x, y, z, radius) in m with radius > 0, got {p}")
        object.__setattr__(self, "phantoms", ph)


def paint_phantoms(capture: Capture, masks_vxhxw: np.ndarray, phantoms: tuple, first_id: int) -> np.ndarray:
    """``masks_vxhxw`` with each phantom sphere's silhouette painted over background pixels (ids from
    ``first_id``): the projection of a sphere is convex, so the convex hull of its projected surface samples is its
    silhouette. Views behind which a sphere lies are left unchanged."""
    import cv2

    out = masks_vxhxw.copy()
    u = np.random.default_rng(0).normal(size=(2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for j, (x, y, z, r) in enumerate(phantoms):
        pts = np.array([x, y, z]) + r * u
        for v, view in enumerate(capture.views):
            uv, depth = view.project(pts)
            if np.any(depth <= 0):
                continue
            layer = np.zeros(out.shape[1:], np.uint8)
            cv2.fillConvexPoly(layer, cv2.convexHull(np.round(uv).astype(np.int32)), 1)
            out[v][(layer > 0) & (out[v] == 0)] = first_id + j
    return out


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
        if self.config.phantoms:
            masks = paint_phantoms(capture, masks, self.config.phantoms, int(masks.max()) + 1)
        return SegmentationResult(
            masks_vxhxw=masks,
            timings={"total": time.perf_counter() - t0},
            info={"segmenter": self.name, "quality": {"silhouette_iou_mean": 1.0, "silhouette_iou_min": 1.0},
                  "phantoms": len(self.config.phantoms)},
        )
