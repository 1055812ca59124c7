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


def centre_targets(mask_hxw: np.ndarray, sigma_px: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Centre heatmap and centre offsets of one instance mask (Panoptic-DeepLab's targets).

    Each instance's centre is the mean (y, x) of its visible pixels (px). Returns ``heat`` (H, W) float32 in
    [0, 1]: the maximum over instances of exp(-d^2 / (2 sigma^2)), d the distance to the instance's centre (px);
    and ``offset`` (2, H, W) float32: on each object pixel, centre minus pixel position (dy, dx) in px; 0 on
    the background.
    """
    m = np.asarray(mask_hxw)
    h, w = m.shape
    heat = np.zeros((h, w), np.float32)
    offset = np.zeros((2, h, w), np.float32)
    if sigma_px <= 0:
        raise ValueError(f"sigma_px = {sigma_px} must be > 0")
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r = int(np.ceil(3 * sigma_px))
    for i in np.unique(m[m > 0]):
        sel = m == i
        cy, cx = float(yy[sel].mean()), float(xx[sel].mean())
        offset[0][sel] = cy - yy[sel]
        offset[1][sel] = cx - xx[sel]
        y0, y1 = max(int(cy) - r, 0), min(int(cy) + r + 2, h)
        x0, x1 = max(int(cx) - r, 0), min(int(cx) + r + 2, w)
        if y0 < y1 and x0 < x1:
            g = np.exp(-((yy[y0:y1, x0:x1] - cy) ** 2 + (xx[y0:y1, x0:x1] - cx) ** 2) / (2 * sigma_px ** 2))
            np.maximum(heat[y0:y1, x0:x1], g, out=heat[y0:y1, x0:x1])
    return heat, offset
