"""Per-object checks that need no instance-id correspondence between views.

Masks from a real segmenter (Grounding DINO + SAM, a learned segmenter) carry per-view instance ids:
id k in one view need not be the object with id k in another. So nothing here follows an id across
views. Objects are the connected components of a 3-D reconstruction, and each view is asked about
their projections:

- :func:`consensus_objects`: the connected components of a coarse visual hull that tolerates a few
  dissenting views (the *consensus*), as lattice points inside each component.
- :func:`repair_masks`: a view whose silhouette covers less than ``min_coverage`` of a consensus object's
  projection has missed that object (a segmenter miss); the object's projected footprint is added to
  that view's silhouette, so the view keeps carving everything else but not that object. Optionally the
  same for a view in which the object is cut by the image border (``skip_cut=True``).
- :func:`check_objects`: per reconstructed component, the views it lies in (projection in front of the
  camera and inside the image), the views that see it whole (not cut by the border), and whether it
  touches the reconstruction box (then the box cuts it and its extent is unknown). A component seen by
  fewer than ``min_views`` views, or cut by the box, is rejected: recorded as not reconstructed, never
  passed on as an object.
- :func:`unexplained_views`: per view, the silhouette regions that no reconstructed object covers
  (an object that other views' masks carved away, e.g. missed by the segmenter in many views).

Units: metres, world frame; pixels (pixel (r, c) covers [c, c+1) x [r, r+1)).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from torm.types import TriMesh


@dataclass
class ConsensusObject:
    """A component of the consensus hull: lattice points inside it (P, 3) m and the lattice step (m)."""

    points_px3: np.ndarray
    step: float
    missing_views: list[int] = field(default_factory=list)
    cut_views: list[int] = field(default_factory=list)


def consensus_objects(values_n: np.ndarray, points_nx3: np.ndarray, shape: tuple[int, int, int], step: float,
                      min_points: int = 2) -> list[ConsensusObject]:
    """Connected components (6-connectivity) of the lattice points with ``values < 0``.

    ``points_nx3`` is the lattice in ``ij`` order with ``shape`` points per axis; components with fewer
    than ``min_points`` points are dropped.
    """
    from scipy import ndimage

    occ = (np.asarray(values_n) < 0).reshape(shape)
    labels, n = ndimage.label(occ)
    flat = labels.reshape(-1)
    out = []
    order = np.argsort(flat, kind="stable")
    starts = np.searchsorted(flat[order], np.arange(1, n + 2))
    for c in range(n):
        idx = order[starts[c]:starts[c + 1]]
        if len(idx) >= min_points:
            out.append(ConsensusObject(points_px3=np.asarray(points_nx3)[idx], step=float(step)))
    return out


def project_views(points_px3: np.ndarray, Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray, hw: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points into every view: uv (V, P, 2) px (NaN behind the camera), z (V, P) m and
    ``inside`` (V, P) bool (in front of the camera and inside the H x W image)."""
    H, W = hw
    T_cw = np.linalg.inv(np.asarray(T_world_cam_vx4x4, dtype=np.float64))
    p = np.einsum("vij,pj->vpi", T_cw[:, :3, :3], points_px3) + T_cw[:, None, :3, 3]
    z = p[..., 2]
    zs = np.where(z > 1e-6, z, np.nan)
    K = np.asarray(Ks_vx3x3, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        uv = np.stack([K[:, None, 0, 0] * p[..., 0] / zs + K[:, None, 0, 2],
                       K[:, None, 1, 1] * p[..., 1] / zs + K[:, None, 1, 2]], axis=-1)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
    return uv, z, inside


def repair_masks(silhouettes_vxhxw: np.ndarray, Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray,
                 objects: list[ConsensusObject], *, min_coverage: float = 0.5, skip_cut: bool = False
                 ) -> tuple[np.ndarray, list[int]]:
    """Silhouettes with each consensus object's footprint added where a view missed it (module docstring).

    A view checks an object only when at least half of the object's lattice points project into its
    image. Fills ``objects[k].missing_views`` / ``cut_views``. Returns the repaired (V, H, W) bool
    silhouettes and the sorted views whose silhouette changed.
    """
    sil = np.asarray(silhouettes_vxhxw) > 0
    V, H, W = sil.shape
    out = sil.copy()
    changed: set[int] = set()
    for obj in objects:
        uv, z, inside = project_views(obj.points_px3, Ks_vx3x3, T_world_cam_vx4x4, (H, W))
        for v in np.flatnonzero(inside.mean(axis=1) >= 0.5):
            c = uv[v, inside[v]].astype(np.int64)
            cut = not bool(inside[v].all())
            missing = sil[v, c[:, 1], c[:, 0]].mean() < min_coverage
            if cut:
                obj.cut_views.append(int(v))
            if missing:
                obj.missing_views.append(int(v))
            if missing or (cut and skip_cut):
                r = int(np.ceil(obj.step * Ks_vx3x3[v, 0, 0] / max(float(np.median(z[v, inside[v]])), 1e-6)))
                foot = np.zeros((H, W), np.uint8)
                foot[c[:, 1], c[:, 0]] = 1
                foot = cv2.dilate(foot, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
                out[v] |= foot.astype(bool)
                changed.add(int(v))
    return out, sorted(changed)


def check_objects(meshes: list[TriMesh], Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray, hw: tuple[int, int],
                  bounds_2x3: np.ndarray, *, min_views: int, box_tol: float, floor_z: float | None = None,
                  max_points: int = 400, unknown_vxhxw: np.ndarray | None = None) -> list[dict]:
    """Per component: views it lies in, views that see it whole, box contact, and a verdict.

    A component "lies in" a view when most of its vertices project in front of the camera and inside
    the image, and is seen "whole" when all of them do. It touches the box when a vertex lies within
    ``box_tol`` (m) of a box face; the floor face does not count when ``floor_z`` (the table) is at or
    above it (objects stand on the table). Verdict ``ok`` is False with a ``reason`` when the component
    lies in fewer than ``min_views`` views or touches the box. A vertex that projects onto a pixel marked in
    ``unknown_vxhxw`` ((V, H, W) bool, no evidence: no source after undistortion) counts as outside that image.
    """
    b = np.asarray(bounds_2x3, dtype=np.float64)
    out = []
    for m in meshes:
        v = m.verts_vx3
        sel = v[np.linspace(0, len(v) - 1, min(len(v), max_points)).astype(np.int64)]
        uv, _, inside = project_views(sel, Ks_vx3x3, T_world_cam_vx4x4, hw)
        if unknown_vxhxw is not None:
            vi, pi = np.nonzero(inside)
            cols = np.floor(uv[vi, pi, 0]).astype(np.int64)
            rows = np.floor(uv[vi, pi, 1]).astype(np.int64)
            inside[vi, pi] = ~unknown_vxhxw[vi, rows, cols]
        frac = inside.mean(axis=1)
        seen = np.flatnonzero(frac >= 0.5)
        cut = [int(i) for i in seen if frac[i] < 1.0]
        lo_hit = v.min(0) <= b[0] + box_tol
        if floor_z is not None and floor_z >= b[0, 2] - 1e-9:
            lo_hit[2] = False
        faces = [f"{'xyz'[a]}{'min' if s == 0 else 'max'}" for s, hit in ((0, lo_hit), (1, v.max(0) >= b[1] - box_tol))
                 for a in range(3) if hit[a]]
        rec = {"centroid": v.mean(0).tolist(), "n_faces": int(len(m.faces_fx3)), "views_seen": int(len(seen)),
               "views_whole": int(len(seen) - len(cut)), "views_cut_by_border": cut, "box_faces_touched": faces,
               "ok": True, "reason": ""}
        if len(seen) < min_views:
            rec.update(ok=False, reason=f"seen by only {len(seen)} views (fewer than min_views_per_object="
                                        f"{min_views}): a phantom where few views look, not an object")
        elif faces:
            rec.update(ok=False, reason=f"touches the reconstruction box at {', '.join(faces)}: the box cuts it; "
                                        "widen the bounds (--bounds / workspace_bounds) or leave them unset")
        out.append(rec)
    return out


def unexplained_views(silhouettes_vxhxw: np.ndarray, renders_vxhxw: np.ndarray, min_area_px: int) -> dict[int, int]:
    """Views (index -> largest area px) with a silhouette region of >= ``min_area_px`` that no render covers."""
    out: dict[int, int] = {}
    for i, (s, r) in enumerate(zip(np.asarray(silhouettes_vxhxw) > 0, renders_vxhxw, strict=True)):
        miss = (s & ~r).astype(np.uint8)
        if miss.sum() < min_area_px:
            continue
        miss = cv2.morphologyEx(miss, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))  # not the thin rims
        n, _, stats, _ = cv2.connectedComponentsWithStats(miss, connectivity=8)
        if n > 1 and stats[1:, cv2.CC_STAT_AREA].max() >= min_area_px:
            out[i] = int(stats[1:, cv2.CC_STAT_AREA].max())
    return out


__all__ = ["ConsensusObject", "check_objects", "consensus_objects", "project_views", "repair_masks",
           "unexplained_views"]
