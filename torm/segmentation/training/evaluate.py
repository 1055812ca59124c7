"""Held-out metrics of a segmenter on rendered test splits (full frames of the rig's layout).

Per (view, GT object) with at least ``min_visible_px`` visible pixels: the best IoU with any predicted
instance (ids need not match). An object is **missed** in a view when that IoU is < ``match_iou``; a
predicted instance is a **false positive** when its best IoU with every GT object is < ``match_iou``.
Miss correlation across views: for every (object, view) pair and the view's nearest neighbour by viewing
direction (both with the object visible), the phi coefficient of the two miss indicators, and
P(miss | neighbour missed) beside P(miss). Independent per-view errors give phi ~ 0.
Mean object IoUs carry a 95 % bootstrap interval over scenes (:func:`scene_bootstrap_ci`): the views of one
scene are not independent, so a split of a dozen scenes pins its mean only to a few hundredths.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np

from torm.metrics import silhouette_iou


def _ious(pred: np.ndarray, gt: np.ndarray) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    gids = [int(i) for i in np.unique(gt) if i > 0]
    pids = [int(i) for i in np.unique(pred) if i > 0]
    iou = np.zeros((len(pids), len(gids)))
    garea = np.array([np.count_nonzero(gt == g) for g in gids])
    for a, p in enumerate(pids):
        pm = pred == p
        pa = np.count_nonzero(pm)
        for b, g in enumerate(gids):
            inter = np.count_nonzero(pm & (gt == g))
            iou[a, b] = inter / (pa + garea[b] - inter) if inter else 0.0
    return pids, gids, iou, garea


def scene_bootstrap_ci(values: list[float], scenes: list[int], n_boot: int = 2000, seed: int = 0,
                       level: float = 0.95) -> tuple[float, float] | None:
    """Percentile bootstrap interval of the mean of ``values`` resampling whole scenes (with replacement):
    (lo, hi), or None with fewer than 2 scenes. ``scenes[i]`` is the scene of ``values[i]``."""
    v, sc = np.asarray(values, float), np.asarray(scenes)
    if v.shape != sc.shape:
        raise ValueError(f"values {v.shape} and scenes {sc.shape} must have the same length")
    ids = np.unique(sc)
    if len(ids) < 2:
        return None
    sums = np.array([v[sc == i].sum() for i in ids])
    counts = np.array([np.count_nonzero(sc == i) for i in ids])
    pick = np.random.default_rng(seed).integers(0, len(ids), (n_boot, len(ids)))
    means = sums[pick].sum(1) / counts[pick].sum(1)
    a = (1 - level) / 2
    return float(np.quantile(means, a)), float(np.quantile(means, 1 - a))


def evaluate(segment: Callable[[np.ndarray], np.ndarray], data: dict[str, Any], held_out: tuple[str, ...] = (),
             match_iou: float = 0.5, min_visible_px: int = 100) -> dict[str, Any]:
    """Metrics of ``segment`` (RGB (H, W, 3) uint8 -> (H, W) int instance mask) on a loaded test split."""
    rgb, gt_all, T, scene = data["rgb"], data["mask"], data["T_world_cam"], data["scene"]
    preds = np.stack([segment(im) for im in rgb])
    sil = silhouette_iou(preds, gt_all)
    per_type: dict[str, list[float]] = defaultdict(list)
    obj_iou_all, obj_iou_held, obj_iou_seen = [], [], []
    sc_all, sc_held, sc_seen = [], [], []  # each value's scene
    miss = {}  # (scene, object id, view index) -> bool
    fp_per_view, miss_per_view = [], []
    for v in range(len(rgb)):
        meta = data["meta"][int(scene[v])]
        pids, gids, iou, garea = _ious(preds[v], gt_all[v])
        best = iou.max(axis=0) if pids else np.zeros(len(gids))
        n_vis = n_miss = 0
        for b, g in enumerate(gids):
            if garea[b] < min_visible_px:
                continue
            # ids past the world's objects are distractors labelled as opaque objects (data.object_distractors)
            name = meta["objects"][g - 1] if g <= len(meta["objects"]) else "distractor"
            per_type[name].append(float(best[b]))
            obj_iou_all.append(float(best[b]))
            sc_all.append(int(scene[v]))
            (obj_iou_held if name in held_out else obj_iou_seen).append(float(best[b]))
            (sc_held if name in held_out else sc_seen).append(int(scene[v]))
            m = bool(best[b] < match_iou)
            miss[(int(scene[v]), g, v)] = m
            n_vis += 1
            n_miss += m
        miss_per_view.append(n_miss / n_vis if n_vis else 0.0)
        big = [a for a in range(len(pids))]
        fp_per_view.append(int(sum(1 for a in big if (iou[a].max() if gids else 0.0) < match_iou)))
    # neighbour-view miss correlation
    pairs = []
    for s in np.unique(scene):
        views = np.nonzero(scene == s)[0]
        dirs = T[views][:, :3, 2]
        cos = dirs @ dirs.T
        np.fill_diagonal(cos, -2)
        nn = views[np.argmax(cos, axis=1)]
        objs = {g for (sc, g, _v) in miss if sc == int(s)}
        for g in objs:
            for v, w in zip(views, nn, strict=True):
                a, b = miss.get((int(s), g, int(v))), miss.get((int(s), g, int(w)))
                if a is not None and b is not None:
                    pairs.append((a, b))
    corr: dict[str, Any] = {"pairs": len(pairs)}
    if pairs:
        x = np.array(pairs, dtype=float)
        p_miss = float(x[:, 0].mean())
        both = x[x[:, 1] == 1]
        corr["p_miss"] = p_miss
        corr["p_miss_given_neighbour_missed"] = float(both[:, 0].mean()) if len(both) else None
        sd = x.std(axis=0)
        corr["phi"] = float(np.corrcoef(x[:, 0], x[:, 1])[0, 1]) if np.all(sd > 0) else None

    def stats(v: list[float], sc: list[int] | None = None) -> dict[str, Any]:
        a = np.asarray(v)
        out = {"n": int(a.size), "iou_mean": float(a.mean()) if a.size else None,
               "iou_median": float(np.median(a)) if a.size else None,
               "miss_rate": float(np.mean(a < match_iou)) if a.size else None}
        if sc is not None:
            ci = scene_bootstrap_ci(v, sc) if a.size else None
            out["iou_ci95_scenes"] = list(ci) if ci else None
        return out

    return {
        "views": int(len(rgb)), "scenes": int(len(np.unique(scene))),
        "silhouette_iou_mean": sil["mean"], "silhouette_iou_min": sil["min"],
        "object": stats(obj_iou_all, sc_all), "held_out_objects": stats(obj_iou_held, sc_held),
        "seen_objects": stats(obj_iou_seen, sc_seen),
        "per_type": {k: stats(v) for k, v in sorted(per_type.items())},
        "miss_rate_per_view_mean": float(np.mean(miss_per_view)),
        "views_with_a_miss": float(np.mean(np.asarray(miss_per_view) > 0)),
        "false_positives_per_view": float(np.mean(fp_per_view)),
        "views_with_a_false_positive": float(np.mean(np.asarray(fp_per_view) > 0)),
        "miss_correlation_neighbour_views": corr,
        "match_iou": match_iou, "min_visible_px": min_visible_px,
    }


#: categories of :func:`miss_causes`, in report order
MISS_CAUSES: tuple[str, ...] = ("ok", "background", "merged", "split", "other")


def miss_causes(pred_hxw: np.ndarray, gt_hxw: np.ndarray, match_iou: float = 0.5, min_visible_px: int = 100,
                merge_share: float = 0.3) -> dict[int, str]:
    """Why each visible GT object of one view is missed: {GT id: one of :data:`MISS_CAUSES`}.

    Args:
        pred_hxw: (H, W) int predicted instances (0 background; ids need not match the GT).
        gt_hxw: (H, W) int GT instances (0 background).
        match_iou: an object whose best IoU with a predicted instance reaches this is ``ok``.
        min_visible_px: GT objects with fewer visible pixels are skipped (as in :func:`evaluate`).
        merge_share: ``merged`` when the object's dominant predicted instance covers other GT objects with more
            than this fraction of its overlap with the object.

    Rules, first match wins: ``ok`` (best IoU >= ``match_iou``); ``background`` (under half of the object's
    pixels are predicted foreground); ``merged`` (see ``merge_share``); ``split`` (the dominant predicted instance
    holds under half of the object's pixels); ``other`` (e.g. an instance much larger than the object that
    spills onto the background).
    """
    pred = np.asarray(pred_hxw)
    gt = np.asarray(gt_hxw)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise ValueError(f"prediction {pred.shape} and GT {gt.shape} must both be (H, W)")
    out: dict[int, str] = {}
    for g in (int(i) for i in np.unique(gt) if i > 0):
        gm = gt == g
        area = int(np.count_nonzero(gm))
        if area < min_visible_px:
            continue
        on = pred[gm]
        fg_on = on[on > 0]
        best = 0.0
        for p in np.unique(fg_on):
            inter = int(np.count_nonzero(fg_on == p))
            best = max(best, inter / (int(np.count_nonzero(pred == p)) + area - inter))
        if best >= match_iou:
            out[g] = "ok"
        elif fg_on.size < 0.5 * area:
            out[g] = "background"
        else:
            ids, counts = np.unique(fg_on, return_counts=True)
            dom = ids[np.argmax(counts)]
            overlap = int(counts.max())
            on_others = int(np.count_nonzero((pred == dom) & (gt > 0) & ~gm))
            if on_others > merge_share * overlap:
                out[g] = "merged"
            elif overlap < 0.5 * area:
                out[g] = "split"
            else:
                out[g] = "other"
    return out
