"""Projective visual hull written as an SDF on grid vertices (the fast start of DMTet-Multi).

Per view, the silhouette (mask > 0) gets a signed 2-D distance transform in pixels (inside
negative, outside positive, zero on the boundary half-way between an inside and an outside pixel).
Each grid vertex is projected into the view, the signed distance is sampled bilinearly and scaled
by ``depth / focal`` to metres (the lateral distance at the vertex's depth). Views are combined
with a *vote tolerance*: instead of the strict maximum (a vertex is outside as soon as one view says
so) the ``k``-th largest value is taken, ``k = 1 + floor(vote_tol * n)`` with ``n`` the number of
views that see the vertex, so a vertex is carved only when at least ``k`` views put it outside and a
few bad masks cannot carve an object away. Finally the result is intersected with the table
half-space (nothing below ``table_z``) and the workspace box shrunk by a margin
(``sdf = max(sdf, box_sdf + margin)``), which keeps the surface closed at the grid boundary.

Pixel convention (same as :mod:`torm.reconstruction.raster`): pixel (row r, column c) covers
``[c, c+1) x [r, r+1)`` in (u, v) and its centre is ``(c + 0.5, r + 0.5)``.

Points that project outside the image or lie behind the camera (z <= ``near``) carry no
information from that view by default (``outside_image="unknown"``): in our captures the masks
cover the workspace, and treating "outside the image" as "outside the object" would wrongly carve
partially visible scenes. ``outside_image="outside"`` carves them instead (classic visual hull).
Pixels marked as no evidence (``unknown_vxhxw`` of :class:`ProjectiveSDF`: no source pixel after the lens
distortion was undone, :func:`torm.capture.lens.no_evidence_masks`) are treated the same way: a point whose
bilinear sample touches one abstains in that view (it is not counted among the views that see it).
A vertex no view sees gets ``+unseen_value`` (outside).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Sequence

import cv2
import numba as nb
import numpy as np
import torch

from torm.errors import ReconstructionError
from torm.reconstruction.tetgrid import TetGrid
from torm.types import Capture

log = logging.getLogger(__name__)

_OUTSIDE_IMAGE = ("unknown", "outside")


def signed_distance_px(silhouette_hxw: np.ndarray, precise: bool = False) -> np.ndarray:
    """(H, W) float32 signed distance in pixels to the silhouette boundary (inside negative).

    The boundary lies half-way between an inside and an outside pixel centre, so the two pixels
    next to it get -0.5 and +0.5. An empty silhouette gives ``+(H + W)`` everywhere, a full one
    ``-(H + W)``. ``precise`` uses OpenCV's exact Euclidean transform (about 3x slower than the
    default 5x5 chamfer mask, whose error is about 1-2 % of the distance).
    """
    sil = np.asarray(silhouette_hxw, dtype=bool)
    H, W = sil.shape
    big = float(H + W)
    if not sil.any():
        return np.full((H, W), big, dtype=np.float32)
    if sil.all():
        return np.full((H, W), -big, dtype=np.float32)
    flag = cv2.DIST_MASK_PRECISE if precise else cv2.DIST_MASK_5
    u8 = sil.view(np.uint8)
    d_in = cv2.distanceTransform(u8, cv2.DIST_L2, flag)  # inside pixels: distance to nearest outside pixel
    d_out = cv2.distanceTransform(1 - u8, cv2.DIST_L2, flag)  # outside pixels: distance to nearest inside pixel
    return np.where(sil, 0.5 - d_in, d_out - 0.5).astype(np.float32)


def _crop_window(lo_3: np.ndarray, hi_3: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, near: float,
                 H: int, W: int) -> tuple[int, int, int, int]:
    """Pixel window (r0, r1, c0, c1) holding the projections of the points' bounding box (whole image if behind)."""
    corners = np.array([[(lo_3, hi_3)[(c >> a) & 1][a] for a in range(3)] for c in range(8)])
    p = corners @ R.T + t
    if np.any(p[:, 2] <= near):
        return 0, H, 0, W
    u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
    v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
    c0 = int(np.clip(np.floor(u.min()) - 2, 0, W))
    c1 = int(np.clip(np.ceil(u.max()) + 2, 0, W))
    r0 = int(np.clip(np.floor(v.min()) - 2, 0, H))
    r1 = int(np.clip(np.ceil(v.max()) + 2, 0, H))
    if c1 - c0 < 2 or r1 - r0 < 2:
        return 0, H, 0, W
    return r0, r1, c0, c1


@nb.njit(cache=True, nogil=True)
def _accumulate_view(pts_nx3, R_3x3, t_3, fx, fy, cx, cy, W, H, near, sd_hxw, r0, c0, carve_outside,
                     top_nxk, n_seen_n):  # pragma: no cover - compiled
    """Project every point into one view, sample the signed distance (m) and insert it into the top-K buffer."""
    h, w = sd_hxw.shape
    K = top_nxk.shape[1]
    f_mean = 0.5 * (fx + fy)
    for i in range(pts_nx3.shape[0]):
        x = R_3x3[0, 0] * pts_nx3[i, 0] + R_3x3[0, 1] * pts_nx3[i, 1] + R_3x3[0, 2] * pts_nx3[i, 2] + t_3[0]
        y = R_3x3[1, 0] * pts_nx3[i, 0] + R_3x3[1, 1] * pts_nx3[i, 1] + R_3x3[1, 2] * pts_nx3[i, 2] + t_3[1]
        z = R_3x3[2, 0] * pts_nx3[i, 0] + R_3x3[2, 1] * pts_nx3[i, 1] + R_3x3[2, 2] * pts_nx3[i, 2] + t_3[2]
        if z <= near:
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        inside_img = u >= 0.0 and u <= W and v >= 0.0 and v <= H
        if not inside_img and not carve_outside:
            continue
        # bilinear sample at index coordinates (pixel centres at c + 0.5), clamped to the window
        xs = min(max(u - 0.5 - c0, 0.0), w - 1.0)
        ys = min(max(v - 0.5 - r0, 0.0), h - 1.0)
        x0 = min(int(xs), max(w - 2, 0))
        y0 = min(int(ys), max(h - 2, 0))
        x1 = min(x0 + 1, w - 1)
        y1 = min(y0 + 1, h - 1)
        ax = xs - x0
        ay = ys - y0
        val = ((sd_hxw[y0, x0] * (1.0 - ax) + sd_hxw[y0, x1] * ax) * (1.0 - ay)
               + (sd_hxw[y1, x0] * (1.0 - ax) + sd_hxw[y1, x1] * ax) * ay)
        if val != val:  # NaN: a pixel without evidence (no source after undistortion) - no information
            continue
        if not inside_img:
            du = max(0.0, -u) + max(0.0, u - W)
            dv = max(0.0, -v) + max(0.0, v - H)
            val = np.sqrt(du * du + dv * dv) + max(val, 0.0)
        cur = np.float32(val * z / f_mean)
        n_seen_n[i] += 1
        for j in range(K):  # insertion into the descending buffer
            if cur > top_nxk[i, j]:
                tmp = top_nxk[i, j]
                top_nxk[i, j] = cur
                cur = tmp


def box_sdf(points_nx3: np.ndarray, bounds_2x3: np.ndarray) -> np.ndarray:
    """(N,) signed distance (m) to an axis-aligned box, negative inside (exact inside, a lower bound outside)."""
    b = np.asarray(bounds_2x3, dtype=np.float64)
    return np.max(np.maximum(b[0] - points_nx3, points_nx3 - b[1]), axis=1)


def vote_index(n_seen_n: np.ndarray, vote_tol: float = 0.0, vote_views: int | None = None) -> np.ndarray:
    """(N,) how many of the views seeing each point may call it outside before it is carved.

    ``vote_views`` given: that many views, but never half or more of the ``n`` views that see the point
    (``min(vote_views, (n - 1) // 2)``), so a point seen by few views is decided by their majority.
    Otherwise the fraction ``vote_tol`` of them: ``floor(vote_tol * n)``. The hull value of a point is the
    ``(1 + tolerance)``-th largest per-view value.
    """
    n = np.asarray(n_seen_n, dtype=np.int64)
    if vote_views is not None:
        return np.minimum(int(vote_views), np.maximum(n - 1, 0) // 2)
    return np.floor(vote_tol * n).astype(np.int64)


class ProjectiveSDF:
    """The projective visual-hull SDF of a set of silhouettes, evaluated at any world points.

    Construction computes one signed 2-D distance transform per view, over the pixel window the region
    of interest projects into, and keeps them; :meth:`__call__` then costs one compiled projection loop
    per view over the points. This lets a coarse-to-fine evaluation (:mod:`torm.reconstruction.adaptive_grid`)
    query the same field many times.

    Args:
        masks_vxhxw: (V, H, W) silhouettes; any value > 0 (bool True, instance id) is object.
        Ks_vx3x3: (V, 3, 3) intrinsics in pixels.
        T_world_cam_vx4x4: (V, 4, 4) camera-to-world poses, OpenCV axes, metres.
        roi_bounds_2x3: (2, 3) box (m) that holds every point that will be queried (limits the distance
            transforms to its projection); None = whole images.
        vote_tol, vote_views: the vote tolerance (:func:`vote_index`).
        outside_image: ``"unknown"`` (a view says nothing about points outside its image) or ``"outside"``.
        near: points with camera z <= near (m) are behind the camera: no information.
        precise: exact Euclidean distance transform (slower) instead of the 5x5 chamfer approximation.
        unknown_vxhxw: (V, H, W) bool pixels without evidence, or None: a point projecting there gets no
            information from that view, as outside the image (the distance transform counts them as inside,
            so no background distance is measured from a boundary that may not exist).
    """

    def __init__(self, masks_vxhxw: np.ndarray, Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray, *,
                 roi_bounds_2x3: np.ndarray | None = None, vote_tol: float = 0.15, vote_views: int | None = None,
                 outside_image: str = "unknown", near: float = 1e-3, precise: bool = False,
                 unknown_vxhxw: np.ndarray | None = None) -> None:
        masks = np.asarray(masks_vxhxw)
        Ks = np.asarray(Ks_vx3x3, dtype=np.float64)
        Ts = np.asarray(T_world_cam_vx4x4, dtype=np.float64)
        if masks.ndim != 3:
            raise ReconstructionError(f"visual hull: masks must be (V, H, W), got shape {masks.shape}")
        n_views, H, W = masks.shape
        if n_views == 0:
            raise ReconstructionError("visual hull: no views given; pass at least one mask with its camera")
        if Ks.shape != (n_views, 3, 3) or Ts.shape != (n_views, 4, 4):
            raise ReconstructionError(
                f"visual hull: expected Ks ({n_views}, 3, 3) and T_world_cam ({n_views}, 4, 4) for {n_views} masks, "
                f"got {Ks.shape} and {Ts.shape}"
            )
        if not 0.0 <= vote_tol < 1.0:
            raise ReconstructionError(f"visual hull: vote_tol must be in [0, 1), got {vote_tol}")
        if vote_views is not None and vote_views < 0:
            raise ReconstructionError(f"visual hull: vote_views must be >= 0 views, got {vote_views}")
        if outside_image not in _OUTSIDE_IMAGE:
            raise ReconstructionError(
                f"visual hull: outside_image must be one of {_OUTSIDE_IMAGE}, got {outside_image!r}")
        self.n_views, self.H, self.W = n_views, H, W
        self.vote_tol, self.vote_views = float(vote_tol), vote_views
        self.carve_outside = outside_image == "outside"
        self.near = float(near)
        self.k_max = 1 + (min(int(vote_views), max(n_views - 1, 0) // 2) if vote_views is not None
                          else math.floor(vote_tol * n_views))
        if unknown_vxhxw is not None and np.shape(unknown_vxhxw) != masks.shape:
            raise ReconstructionError(f"visual hull: unknown_vxhxw has shape {np.shape(unknown_vxhxw)} but the masks "
                                      f"{masks.shape}; give one no-evidence map per mask")
        self._roi, self._Ks, self._precise = roi_bounds_2x3, Ks, precise
        self._unknown = None if unknown_vxhxw is None else np.asarray(unknown_vxhxw, dtype=bool)
        self._views = [self._view(masks[v], Ks[v], Ts[v], self._unknown_of(v)) for v in range(n_views)]

    def _unknown_of(self, v: int) -> np.ndarray | None:
        return None if self._unknown is None or not self._unknown[v].any() else self._unknown[v]

    def _view(self, mask_hxw: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
              unknown_hxw: np.ndarray | None = None) -> tuple:
        T_cw = np.linalg.inv(T_world_cam)
        R, t = T_cw[:3, :3].copy(), T_cw[:3, 3].copy()
        # distance transform only over the window the region projects into (sign exact; distances
        # can only ignore mask pixels outside the window, i.e. outside the projected region)
        r0, r1, c0, c1 = ((0, self.H, 0, self.W) if self._roi is None else
                          _crop_window(self._roi[0], self._roi[1], R, t, K, self.near, self.H, self.W))
        if unknown_hxw is None:
            sd = signed_distance_px(mask_hxw[r0:r1, c0:c1] > 0, precise=self._precise)
        else:  # no-evidence pixels: inside for the distances, NaN (abstain) when sampled
            unk = unknown_hxw[r0:r1, c0:c1]
            sd = signed_distance_px((mask_hxw[r0:r1, c0:c1] > 0) | unk, precise=self._precise)
            sd[unk] = np.nan
        return (R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2], sd, r0, c0, T_world_cam)

    def derive(self, *, vote_views: int | None, masks_vxhxw: np.ndarray | None = None,
               changed_views: Sequence[int] = ()) -> ProjectiveSDF:
        """A copy with another ``vote_views`` and, optionally, new masks for ``changed_views`` (only those
        views' distance transforms are recomputed; the others are shared)."""
        out = copy.copy(self)
        out.vote_views = vote_views
        out.k_max = 1 + (min(int(vote_views), max(self.n_views - 1, 0) // 2) if vote_views is not None
                         else math.floor(self.vote_tol * self.n_views))
        out._views = list(self._views)
        for v in changed_views:
            out._views[v] = self._view(np.asarray(masks_vxhxw[v]), self._Ks[v], self._views[v][-1], self._unknown_of(v))
        return out

    def _top(self, points_nx3: np.ndarray, k_max: int) -> tuple[np.ndarray, np.ndarray]:
        pts = np.ascontiguousarray(points_nx3, dtype=np.float32).reshape(-1, 3)
        top = np.full((len(pts), k_max), -np.inf, dtype=np.float32)
        n_seen = np.zeros(len(pts), dtype=np.int32)
        for R, t, fx, fy, cx, cy, sd, r0, c0, _ in self._views:
            _accumulate_view(pts, R, t, fx, fy, cx, cy, float(self.W), float(self.H), self.near, sd, r0, c0,
                             self.carve_outside, top, n_seen)
        return top, n_seen

    def __call__(self, points_nx3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(hull value (N,) float64 m, negative inside; views seeing each point (N,) int32). Unseen: +inf."""
        top, n_seen = self._top(points_nx3, self.k_max)
        k_n = vote_index(n_seen, self.vote_tol, self.vote_views)
        val = top[np.arange(len(top)), np.minimum(k_n, self.k_max - 1)].astype(np.float64)
        val[n_seen == 0] = np.inf
        return val, n_seen

    def values(self, points_nx3: np.ndarray, tolerances: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Hull values (N, len(tolerances)) for several vote tolerances (``vote_views`` semantics of
        :func:`vote_index`) from one projection pass, and the views seeing each point (N,)."""
        k_max = 1 + min(max(tolerances), max(self.n_views - 1, 0) // 2)
        top, n_seen = self._top(points_nx3, k_max)
        rows = np.arange(len(top))
        out = np.stack([top[rows, np.minimum(vote_index(n_seen, vote_views=t), k_max - 1)] for t in tolerances],
                       axis=1).astype(np.float64)
        out[n_seen == 0] = np.inf
        return out, n_seen


def visual_hull_sdf(
    masks_vxhxw: np.ndarray,
    Ks_vx3x3: np.ndarray,
    T_world_cam_vx4x4: np.ndarray,
    grid: TetGrid | np.ndarray | torch.Tensor,
    *,
    table_z: float | None = 0.0,
    workspace_bounds_2x3: np.ndarray | None = None,
    box_margin: float | None = None,
    vote_tol: float = 0.15,
    vote_views: int | None = None,
    outside_image: str = "unknown",
    near: float = 1e-3,
    precise: bool = False,
) -> torch.Tensor:
    """Visual-hull SDF (m) at the grid vertices (or at arbitrary points).

    Args:
        masks_vxhxw: (V, H, W) silhouettes; any value > 0 (bool True, instance id) is object.
        Ks_vx3x3: (V, 3, 3) intrinsics in pixels.
        T_world_cam_vx4x4: (V, 4, 4) camera-to-world poses, OpenCV axes, metres.
        grid: a :class:`TetGrid` (its vertices are used) or points (N, 3) in metres, world frame.
        table_z: table-top height (m); everything below it is outside. ``None`` skips the table.
        workspace_bounds_2x3: box (m) the result is intersected with; defaults to the grid's bounds
            (for points: no box).
        box_margin: the box is shrunk by this much (m) on every side before the intersection. Default:
            half the smallest grid cell for a :class:`TetGrid` (so the grid's boundary vertices are
            strictly outside, sdf >= margin, and the surface stays closed while an optimiser moves
            the SDF), 0 for points.
        vote_tol: fraction of the views seeing a vertex that may disagree: a vertex seen by ``n`` views
            is outside when at least ``1 + floor(vote_tol * n)`` of them say so. 0 = strict visual hull.
            Must be in [0, 1).
        vote_views: instead of ``vote_tol``, a number of views that may disagree (:func:`vote_index`).
        outside_image: ``"unknown"`` (default; the view is ignored for that vertex) or ``"outside"``
            (the vertex is carved by that view).
        near: points with camera z <= near (m) are behind the camera: no information.
        precise: exact Euclidean distance transform (slower) instead of the 5x5 chamfer approximation.

    Returns:
        (N,) float32 CPU tensor, negative inside the hull, in metres (approximate distance).

    Cost: one distance transform per view (over the window the points project into) plus a compiled
    loop over the points per view; memory is ``4 N (k_max + 1)`` bytes for the running top-k buffer
    plus the distance images (:class:`ProjectiveSDF`).
    """
    if isinstance(grid, TetGrid):
        pts = grid.verts_vx3.detach().cpu().numpy().astype(np.float32)
        bounds = grid.bounds if workspace_bounds_2x3 is None else np.asarray(workspace_bounds_2x3, dtype=np.float64)
        margin = 0.5 * float(np.min(grid.cell_size)) if box_margin is None else float(box_margin)
    else:
        pts = torch.as_tensor(grid).detach().cpu().numpy().astype(np.float32).reshape(-1, 3)
        bounds = None if workspace_bounds_2x3 is None else np.asarray(workspace_bounds_2x3, dtype=np.float64)
        margin = 0.0 if box_margin is None else float(box_margin)
    if bounds is not None and (bounds.shape != (2, 3) or np.any(bounds[1] - bounds[0] <= 2 * margin)):
        raise ReconstructionError(
            f"visual hull: workspace box {bounds.tolist()} must be (2, 3) with max - min > 2 * box_margin ({margin})"
        )
    N = len(pts)
    roi = np.stack([pts.min(0), pts.max(0)]).astype(np.float64) if N else None
    field = ProjectiveSDF(masks_vxhxw, Ks_vx3x3, T_world_cam_vx4x4, roi_bounds_2x3=roi, vote_tol=vote_tol,
                          vote_views=vote_views, outside_image=outside_image, near=near, precise=precise)
    sdf, n_seen = field(pts)
    extent = float(np.ptp(pts, axis=0).max()) if N else 1.0
    sdf[n_seen == 0] = max(extent, 1e-3)
    if n_seen.min(initial=1) == 0:
        log.info("visual hull: %d of %d points are seen by no view; they are set outside", int((n_seen == 0).sum()), N)
    if table_z is not None:
        sdf = np.maximum(sdf, float(table_z) - pts[:, 2])
    if bounds is not None:
        sdf = np.maximum(sdf, box_sdf(pts, bounds) + margin)
    return torch.from_numpy(sdf.astype(np.float32))


def visual_hull_sdf_from_capture(
    capture: Capture,
    grid: TetGrid | np.ndarray | torch.Tensor,
    *,
    table_z: float | None = None,
    workspace_bounds_2x3: np.ndarray | None = None,
    **kwargs,
) -> torch.Tensor:
    """:func:`visual_hull_sdf` for a :class:`~torm.types.Capture` (silhouettes = instance mask > 0).

    ``table_z`` defaults to ``capture.table_height`` (or 0.0 when unknown); ``workspace_bounds_2x3``
    defaults to the grid's bounds. Other keyword arguments are passed on.
    """
    if table_z is None:
        table_z = capture.table_height if capture.table_height is not None else 0.0
    return visual_hull_sdf(capture.masks() > 0, capture.Ks(), capture.poses(), grid, table_z=table_z,
                           workspace_bounds_2x3=workspace_bounds_2x3, **kwargs)
