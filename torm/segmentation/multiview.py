"""Union silhouettes for the reconstruction and optional cross-view consistency checks.

The reconstruction consumes one bool silhouette per view (``mask > 0``). A segmenter can fail in a
single view (a missed object, a whole-table box, a blob), and one bad view carves a visual hull or
pulls a silhouette loss the wrong way. Two optional checks find such views; both only compare a view
with the others, so they need no ground truth:

``area``  robust z-score of the log silhouette area against the ``n_neighbours`` views with the
          closest viewing directions (median and MAD of the neighbours, sigma floored at
          ``area_sigma_floor``). Neighbouring views see nearly the same projected area, so a missed
          object or a spurious blob shows up as an outlier. Cheap; blind to errors that keep the area.
``hull``  leave-one-out visual hull: voxels over the workspace box are carved by every view, a voxel
          stays when at most ``hull_vote_tolerance`` of the views that see it call it outside (robust to
          the other views' errors, like RECONSTRUCTION.md's vote carving). For view i the hull built
          without i's votes is splatted into view i and compared with its silhouette (IoU); views whose
          IoU is a low outlier (robust z below ``-hull_z_threshold``) or below ``hull_min_iou`` are flagged.
          Catches shape and position errors too; costs one pass of V x res^3 projections (~0.1-1 s).

``check_views`` returns the kept view indices and the reason for each flagged view; with
``action="flag"`` every view is kept and the reasons are only reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from torm.errors import ConfigError, SegmentationError
from torm.types import Capture


def union_silhouettes(masks_vxhxw: np.ndarray) -> np.ndarray:
    """(V, H, W) bool silhouettes: any instance (> 0) is foreground."""
    m = np.asarray(masks_vxhxw)
    if m.ndim != 3:
        raise SegmentationError(f"masks must be (V, H, W), got {m.shape}")
    return m > 0


@dataclass(frozen=True)
class ConsistencyConfig:
    """Which cross-view checks to run and their thresholds (see the module docstring)."""

    checks: tuple[Literal["area", "hull"], ...] = ("area", "hull")
    action: Literal["drop", "flag"] = "drop"
    n_neighbours: int = 6
    area_z_threshold: float = 4.0
    area_sigma_floor: float = 0.08
    hull_res: int = 40
    hull_vote_tolerance: float = 0.15
    hull_z_threshold: float = 4.0
    hull_sigma_floor: float = 0.03
    hull_min_iou: float = 0.3
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None

    def __post_init__(self) -> None:
        bad = [c for c in self.checks if c not in ("area", "hull")]
        if bad:
            raise ConfigError(f"consistency.checks: unknown check(s) {bad}; valid: area, hull")
        if self.action not in ("drop", "flag"):
            raise ConfigError("consistency.action must be 'drop' or 'flag'")
        if self.n_neighbours < 2 or self.hull_res < 4 or not 0 <= self.hull_vote_tolerance < 1:
            raise ConfigError("consistency: need n_neighbours >= 2, hull_res >= 4, 0 <= hull_vote_tolerance < 1")


@dataclass
class ConsistencyReport:
    """Outcome of :func:`check_views`: kept view indices, ``reasons[i]`` for flagged view i, and per-view stats."""

    kept: list[int]
    reasons: dict[int, list[str]] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def flagged(self) -> list[int]:
        return sorted(self.reasons)


def _robust_z(x: float, ref: np.ndarray, floor: float) -> float:
    med = float(np.median(ref))
    sigma = max(1.4826 * float(np.median(np.abs(ref - med))), floor)
    return (x - med) / sigma


def area_z_scores(sil_vxhxw: np.ndarray, poses_vx4x4: np.ndarray, n_neighbours: int, floor: float) -> np.ndarray:
    """(V,) robust z of log(area + 1) against the views with the most similar viewing direction."""
    V = len(sil_vxhxw)
    la = np.log1p(sil_vxhxw.reshape(V, -1).sum(axis=1).astype(np.float64))
    dirs = poses_vx4x4[:, :3, 2]
    cos = dirs @ dirs.T
    k = min(n_neighbours, V - 1)
    z = np.zeros(V)
    for i in range(V):
        order = [j for j in np.argsort(-cos[i]) if j != i][:k]
        z[i] = _robust_z(la[i], la[order], floor)
    return z


def _voxel_centres(bounds: np.ndarray, res: int) -> tuple[np.ndarray, float]:
    ext = bounds[1] - bounds[0]
    size = float(ext.max() / res)
    n = np.maximum(np.round(ext / size).astype(int), 1)
    axes = [bounds[0, a] + (np.arange(n[a]) + 0.5) * ext[a] / n[a] for a in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return g, size


def hull_ious(sil_vxhxw: np.ndarray, Ks: np.ndarray, poses: np.ndarray, bounds: np.ndarray, res: int,
              tolerance: float) -> np.ndarray:
    """(V,) IoU of each view's silhouette with the leave-one-out vote hull splatted into that view."""
    V, H, W = sil_vxhxw.shape
    X, vsize = _voxel_centres(bounds, res)
    outside = np.zeros((V, len(X)), bool)
    seen = np.zeros((V, len(X)), bool)
    uv_all, z_all = [], []
    for i in range(V):
        T = np.linalg.inv(poses[i])
        p = X @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = Ks[i, 0, 0] * p[:, 0] / z + Ks[i, 0, 2]
            v = Ks[i, 1, 1] * p[:, 1] / z + Ks[i, 1, 2]
        ok = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        seen[i] = ok
        ui = np.clip(u, 0, W - 1).astype(int)
        vi = np.clip(v, 0, H - 1).astype(int)
        outside[i] = ok & ~sil_vxhxw[i][vi, ui]
        uv_all.append((ui, vi))
        z_all.append(z)
    n_out = outside.sum(axis=0)
    n_seen = seen.sum(axis=0)
    ious = np.zeros(V)
    for i in range(V):
        occ = (n_out - outside[i]) <= tolerance * np.maximum(n_seen - seen[i], 1)
        occ &= seen[i]
        img = np.zeros((H, W), np.uint8)
        ui, vi = uv_all[i]
        img[vi[occ], ui[occ]] = 1
        if occ.any():
            r = 0.5 * vsize * Ks[i, 0, 0] / float(np.median(z_all[i][occ]))
            k = max(int(np.ceil(r)), 1)
            img = cv2.dilate(img, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1)))
            img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
        hull = img > 0
        union = np.count_nonzero(hull | sil_vxhxw[i])
        ious[i] = np.count_nonzero(hull & sil_vxhxw[i]) / union if union else 1.0
    return ious


def check_views(
    capture: Capture, config: ConsistencyConfig | None = None, masks_vxhxw: np.ndarray | None = None
) -> ConsistencyReport:
    """Run the configured checks on ``masks_vxhxw`` (default: the capture's masks) and list kept views."""
    cfg = config or ConsistencyConfig()
    masks = capture.masks() if masks_vxhxw is None else np.asarray(masks_vxhxw)
    sil = union_silhouettes(masks)
    nv = len(sil)
    if nv != len(capture):
        raise SegmentationError(f"{nv} masks for {len(capture)} views")
    reasons: dict[int, list[str]] = {}
    stats: dict[str, Any] = {}
    if nv >= 4 and "area" in cfg.checks:
        z = area_z_scores(sil, capture.poses(), cfg.n_neighbours, cfg.area_sigma_floor)
        stats["area_z"] = [round(float(x), 3) for x in z]
        for i in np.nonzero(np.abs(z) > cfg.area_z_threshold)[0]:
            kind = "larger" if z[i] > 0 else "smaller"
            reasons.setdefault(int(i), []).append(f"silhouette area {kind} than neighbouring views (z = {z[i]:.1f})")
    if nv >= 4 and "hull" in cfg.checks:
        bounds = np.asarray(cfg.bounds if cfg.bounds is not None else capture.workspace_bounds, dtype=np.float64)
        if bounds.shape != (2, 3):
            raise SegmentationError("the hull check needs workspace bounds: set consistency.bounds or the capture's")
        ious = hull_ious(sil, capture.Ks(), capture.poses(), bounds, cfg.hull_res, cfg.hull_vote_tolerance)
        stats["hull_iou"] = [round(float(x), 4) for x in ious]
        for i in range(nv):
            z = _robust_z(ious[i], np.delete(ious, i), cfg.hull_sigma_floor)
            if z < -cfg.hull_z_threshold or ious[i] < cfg.hull_min_iou:
                reasons.setdefault(i, []).append(
                    f"silhouette disagrees with the other views' visual hull (IoU {ious[i]:.2f}, z = {z:.1f})")
    kept = list(range(nv)) if cfg.action == "flag" else [i for i in range(nv) if i not in reasons]
    if not kept:
        raise SegmentationError("every view was flagged as inconsistent; check the masks or relax the thresholds")
    return ConsistencyReport(kept, reasons, stats)
