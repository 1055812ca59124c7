"""Training targets from instance masks: foreground and an instance-boundary band."""

from __future__ import annotations

import cv2
import numpy as np


def boundary_band(mask_hxw: np.ndarray, radius_px: int = 2) -> np.ndarray:
    """(H, W) bool: object pixels within ``radius_px`` of a pixel of another id (background or another object).

    ``foreground & ~band`` are the instance cores; touching objects' cores are separated by >= 2 radius px.
    """
    m = np.asarray(mask_hxw)
    fg = m > 0
    if not fg.any() or radius_px <= 0:
        return np.zeros(m.shape, bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    core = np.zeros(m.shape, bool)
    for i in np.unique(m[fg]):
        core |= cv2.erode((m == i).astype(np.uint8), k, borderType=cv2.BORDER_REPLICATE).astype(bool)
    return fg & ~core


def targets(masks_nxhxw: np.ndarray, radius_px: int = 2) -> np.ndarray:
    """(N, 2, H, W) uint8 targets: channel 0 foreground, channel 1 boundary band."""
    m = np.asarray(masks_nxhxw)
    out = np.zeros((len(m), 2, *m.shape[1:]), np.uint8)
    for i, mi in enumerate(m):
        out[i, 0] = mi > 0
        out[i, 1] = boundary_band(mi, radius_px)
    return out
