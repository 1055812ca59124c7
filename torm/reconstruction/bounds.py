"""Reconstruction box from the cameras and masks, for captures that carry no ``workspace_bounds``.

Two steps (world frame, metres):

1. **Silhouette cones.** Every view whose mask holds object pixels bounds the objects by the four planes
   through its optical centre and the sides of the mask's bounding box (``u0 <= u <= u1``,
   ``v0 <= v <= v1``), plus "in front of the camera". A side that touches the image border is dropped
   (the object may continue outside the image). The box of the intersection of all these half-spaces
   (and of ``z >= table_z`` when there is a table) is found by six linear programs.
2. **Hull.** That box, enlarged by ``search_margin`` of its size on every side (so an object that a few
   masks miss is not cut), is covered by a coarse lattice on which the projective visual hull with a
   vote tolerance is evaluated; the box of the lattice points inside the hull and seen by enough views,
   grown by ``margin`` of its size (at least two lattice cells), is the result.

Errors name the keys to set instead (``workspace_bounds`` in transforms.json, ``--bounds``,
``ReconstructionConfig.bounds``).
"""

from __future__ import annotations

import logging

import numpy as np

from torm.errors import ReconstructionError
from torm.reconstruction.visual_hull import ProjectiveSDF

log = logging.getLogger(__name__)

#: What to tell the user when automatic bounds fail.
BOUNDS_HINT = ("give the box instead: 'workspace_bounds': [[xmin, ymin, zmin], [xmax, ymax, zmax]] (m) in "
               "transforms.json, --bounds XMIN YMIN ZMIN XMAX YMAX ZMAX on the command line, or "
               "ReconstructionConfig.bounds")


def cone_halfspaces(silhouettes_vxhxw: np.ndarray, Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray,
                    near: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Half-spaces ``A p <= b`` (world points p, m) bounding the mask bounding-box cones of all views.

    Returns ``A`` (M, 3) and ``b`` (M,). Views with empty masks add nothing; sides of a mask's bounding box
    that touch the image border add nothing either.
    """
    sil = np.asarray(silhouettes_vxhxw) > 0
    V, H, W = sil.shape
    rows_a, rows_b = [], []
    for v in range(V):
        cols = np.flatnonzero(sil[v].any(axis=0))
        rows = np.flatnonzero(sil[v].any(axis=1))
        if len(cols) == 0:
            continue
        K = np.asarray(Ks_vx3x3[v], dtype=np.float64)
        T_cw = np.linalg.inv(np.asarray(T_world_cam_vx4x4[v], dtype=np.float64))
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        u0, u1, v0, v1 = float(cols[0]), float(cols[-1] + 1), float(rows[0]), float(rows[-1] + 1)
        # n_cam . p_cam >= c in camera coordinates, for p_cam = R p + t
        planes = [(np.array([0.0, 0.0, 1.0]), near)]
        if cols[0] > 0:
            planes.append((np.array([fx, 0.0, cx - u0]), 0.0))  # u >= u0
        if cols[-1] < W - 1:
            planes.append((np.array([-fx, 0.0, u1 - cx]), 0.0))  # u <= u1
        if rows[0] > 0:
            planes.append((np.array([0.0, fy, cy - v0]), 0.0))  # v >= v0
        if rows[-1] < H - 1:
            planes.append((np.array([0.0, -fy, v1 - cy]), 0.0))  # v <= v1
        for n_cam, c in planes:
            n_w = R.T @ n_cam
            scale = np.linalg.norm(n_w)
            rows_a.append(-n_w / scale)
            rows_b.append((n_cam @ t - c) / scale)
    if not rows_a:
        raise ReconstructionError(f"cannot compute the reconstruction box: every mask is empty; {BOUNDS_HINT}")
    return np.array(rows_a), np.array(rows_b)


def cone_box(silhouettes_vxhxw: np.ndarray, Ks_vx3x3: np.ndarray, T_world_cam_vx4x4: np.ndarray,
             table_z: float | None = None) -> np.ndarray:
    """(2, 3) box (m) of the intersection of the mask bounding-box cones (step 1 of the module docstring)."""
    from scipy.optimize import linprog

    A, b = cone_halfspaces(silhouettes_vxhxw, Ks_vx3x3, T_world_cam_vx4x4)
    if table_z is not None:
        A = np.vstack([A, [0.0, 0.0, -1.0]])
        b = np.append(b, -float(table_z))
    out = np.zeros((2, 3))
    for axis in range(3):
        for side, sign in ((0, 1.0), (1, -1.0)):
            c = np.zeros(3)
            c[axis] = sign
            res = linprog(c, A_ub=A, b_ub=b, bounds=[(None, None)] * 3, method="highs")
            if res.status == 2 and table_z is not None and cone_box(silhouettes_vxhxw, Ks_vx3x3, T_world_cam_vx4x4,
                                                                     None)[1, 2] < table_z:
                raise ReconstructionError(
                    f"the table plane z = {table_z} m lies above everything the masks' silhouette cones allow; set "
                    "the table height (table_height in transforms.json, ReconstructionConfig.table_z, --table-z) or "
                    "no table (table_height: null, --no-table)")
            if res.status == 2:
                raise ReconstructionError(
                    "cannot compute the reconstruction box: the masks' silhouette cones do not intersect (the "
                    f"masks or camera poses disagree); check the poses (transform_matrix) or {BOUNDS_HINT}")
            if res.status == 3 or not res.success:
                raise ReconstructionError(
                    "cannot compute the reconstruction box: the masks' silhouette cones do not close around the "
                    f"objects (cameras all looking the same way, or masks touching the image border); {BOUNDS_HINT}")
            out[side, axis] = res.x[axis]
    return out


def auto_bounds(
    silhouettes_vxhxw: np.ndarray,
    Ks_vx3x3: np.ndarray,
    T_world_cam_vx4x4: np.ndarray,
    *,
    table_z: float | None = None,
    vote_views: int = 0,
    lattice_res: int = 48,
    search_margin: float = 0.5,
    margin: float = 0.1,
    min_views: int | None = None,
) -> np.ndarray:
    """(2, 3) reconstruction box (m, world frame) from the cameras and masks (see the module docstring).

    Args:
        silhouettes_vxhxw, Ks_vx3x3, T_world_cam_vx4x4: masks (> 0 = object), intrinsics (px) and
            camera-to-world poses (OpenCV axes, m).
        table_z: table height (m); the box does not reach below it. None: no table.
        vote_views: views that may disagree in the coarse hull (:func:`torm.reconstruction.visual_hull.vote_index`).
        lattice_res: lattice points along the longest axis of the search box.
        search_margin: the cone box is enlarged by this fraction of its size on every side before the hull.
        margin: the hull's box is grown by this fraction of its size on every side (at least 2 lattice cells).
        min_views: hull points seen by fewer views are ignored (regions few views look at are unbounded
            phantoms, not objects); None = max(3, 20 % of the views), as ``min_views_per_object``.
    """
    box = cone_box(silhouettes_vxhxw, Ks_vx3x3, T_world_cam_vx4x4, table_z)
    ext = box[1] - box[0]
    size = max(float(ext.max()), 1e-3)
    search = box + np.array([[-1.0], [1.0]]) * search_margin * np.maximum(ext, 0.1 * size)
    if table_z is not None:
        search[0, 2] = max(search[0, 2], float(table_z))
    step = float((search[1] - search[0]).max()) / lattice_res
    axes = [np.arange(lo, hi + 0.5 * step, step) for lo, hi in zip(search[0], search[1], strict=True)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    field = ProjectiveSDF(silhouettes_vxhxw, Ks_vx3x3, T_world_cam_vx4x4, roi_bounds_2x3=search,
                          vote_views=vote_views)
    val, n_seen = field(pts)
    V = len(silhouettes_vxhxw)
    n_min = min(V, max(3, int(np.ceil(0.2 * V)))) if min_views is None else min_views
    inside = pts[(val < 0) & (n_seen >= n_min)]
    if len(inside) == 0:
        log.info("automatic bounds: the coarse hull is empty; using the silhouette-cone box")
        inside = box
    lo, hi = inside.min(0), inside.max(0)
    grow = np.maximum(margin * (hi - lo), 2 * step)
    out = np.stack([lo - grow, hi + grow])
    if table_z is not None:
        out[0, 2] = max(out[0, 2], float(table_z) - step)
    log.info("automatic reconstruction box %s m (cone box %s)", np.round(out, 4).tolist(), np.round(box, 4).tolist())
    return out


__all__ = ["BOUNDS_HINT", "auto_bounds", "cone_box", "cone_halfspaces"]
