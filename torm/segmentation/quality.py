"""Mask quality against ground truth: per-view silhouette IoU (``torm.metrics``) plus per-object IoU.

Every benchmark row should carry the quality of the masks it was run on; :func:`mask_quality` computes it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from torm.errors import SegmentationError
from torm.metrics import silhouette_iou


def mask_quality(pred_vxhxw: np.ndarray, gt_vxhxw: np.ndarray) -> dict[str, Any]:
    """Quality of predicted (V, H, W) masks against ground truth (V, H, W), both instance masks.

    Returns a JSON-friendly dict:
        ``silhouette_iou_mean`` / ``_min`` / ``_per_view``: IoU of the union silhouettes per view;
        ``object_iou_mean``: mean over (view, GT object visible in that view) of the best IoU between
        that GT object and any predicted instance (instance ids need not match);
        ``missed_fraction``: fraction of (view, GT object) pairs with best IoU < 0.1;
        ``spurious_fraction``: fraction of predicted instances whose best IoU with any GT object < 0.1.
    """
    pred = np.asarray(pred_vxhxw)
    gt = np.asarray(gt_vxhxw)
    if pred.shape != gt.shape or pred.ndim != 3:
        raise SegmentationError(f"predicted masks {pred.shape} and ground truth {gt.shape} must both be (V, H, W)")
    if (pred.size and pred.min() < 0) or (gt.size and gt.min() < 0):
        raise SegmentationError("instance masks must be >= 0 (0 = background)")
    sil = silhouette_iou(pred, gt)
    obj_ious: list[float] = []
    n_spurious = n_pred = 0
    for p, g in zip(pred, gt, strict=True):
        gcount = np.bincount(g.ravel())
        pcount = np.bincount(p.ravel())
        gids = [int(i) for i in np.nonzero(gcount)[0] if i > 0]
        pids = [int(i) for i in np.nonzero(pcount)[0] if i > 0]
        if not gids and not pids:
            continue
        inter = _pair_intersections(p, g, pids, gids)
        parea = pcount[pids].astype(np.float64)
        garea = gcount[gids].astype(np.float64)
        iou = inter / np.maximum(parea[:, None] + garea[None, :] - inter, 1.0)
        if gids:
            obj_ious.extend((iou.max(axis=0) if pids else np.zeros(len(gids))).tolist())
        n_pred += len(pids)
        if pids:
            n_spurious += int(np.count_nonzero((iou.max(axis=1) if gids else np.zeros(len(pids))) < 0.1))
    obj = np.asarray(obj_ious)
    return {
        "silhouette_iou_mean": sil["mean"],
        "silhouette_iou_min": sil["min"],
        "silhouette_iou_per_view": sil["per_view"],
        "object_iou_mean": float(obj.mean()) if obj.size else 1.0,
        "missed_fraction": float(np.mean(obj < 0.1)) if obj.size else 0.0,
        "spurious_fraction": float(n_spurious / n_pred) if n_pred else 0.0,
    }


def _pair_intersections(p: np.ndarray, g: np.ndarray, pids: list[int], gids: list[int]) -> np.ndarray:
    """(len(pids), len(gids)) pixel counts of p == pid & g == gid."""
    out = np.zeros((len(pids), len(gids)), dtype=np.float64)
    if not pids or not gids:
        return out
    both = (p > 0) & (g > 0)
    pi = np.searchsorted(pids, p[both])
    gi = np.searchsorted(gids, g[both])
    np.add.at(out, (pi, gi), 1.0)
    return out
