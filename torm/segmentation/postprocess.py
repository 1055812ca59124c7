"""Binary mask clean-up after SAM: threshold, hole filling, small-blob removal, largest component."""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage


def clean_mask(
    logits_hxw: np.ndarray,
    threshold: float = 0.0,
    fill_holes: bool = True,
    min_blob_area_px: int = 0,
    keep_largest: bool = False,
) -> np.ndarray:
    """(H, W) bool mask from SAM logits.

    Pixels with ``logit > threshold`` are foreground; enclosed background holes are filled; 8-connected
    components smaller than ``min_blob_area_px`` pixels are removed; ``keep_largest`` keeps only the
    largest remaining component.
    """
    m = np.asarray(logits_hxw) > threshold
    if fill_holes and m.any():
        m = ndimage.binary_fill_holes(m)
    if (min_blob_area_px > 0 or keep_largest) and m.any():
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
        areas = stats[1:, cv2.CC_STAT_AREA]
        good = np.nonzero(areas >= min_blob_area_px)[0] + 1
        if keep_largest and good.size:
            good = good[[int(np.argmax(areas[good - 1]))]]
        m = np.isin(labels, good)
    return m


def compose_instances(
    masks_nxhxw: list[np.ndarray] | np.ndarray, hw: tuple[int, int], min_area_px: int = 1
) -> tuple[np.ndarray, list[int]]:
    """Paint bool masks (already in descending score order) into one int32 instance mask.

    Earlier (higher-scoring) masks win overlaps. A mask left with fewer than ``min_area_px`` pixels of
    its own (e.g. a duplicate inside a better detection) gets id 0 and paints nothing; the others get
    consecutive ids 1, 2, ... in order. Returns the (H, W) mask and the id of each input mask.
    """
    out = np.zeros(hw, dtype=np.int32)
    ids: list[int] = []
    nxt = 1
    for m in masks_nxhxw:
        free = np.asarray(m, dtype=bool) & (out == 0)
        if np.count_nonzero(free) >= max(min_area_px, 1):
            out[free] = nxt
            ids.append(nxt)
            nxt += 1
        else:
            ids.append(0)
    return out, ids
