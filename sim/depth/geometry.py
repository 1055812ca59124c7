"""Per-pixel geometry of a depth image: camera-frame points, surface normals and incidence angles.

Normals come from the exact first-surface depth by central differences of the back-projected points
(one-sided at a neighbour that belongs to another surface), which is exact on planar facets and needs no
ray casting. Frames: camera (OpenCV axes), m; angles in degrees.
"""

from __future__ import annotations

import numpy as np

from torm.geometry import backproject_depth as backproject


def incidence_deg(depth_hxw: np.ndarray, K: np.ndarray, surface_id_hxw: np.ndarray,
                  max_step_m: float = 0.01) -> np.ndarray:
    """(H, W) angle (deg) between each pixel's viewing ray and its surface normal; NaN where undefined.

    ``surface_id_hxw`` (H, W) int labels the surface of each pixel (e.g. geom or instance ids); differences are
    taken only between neighbours with the same label, valid depth and a depth step below ``max_step_m``.
    0 deg = the ray meets the surface head-on, 90 deg = grazing. Undefined (NaN) where a pixel has no valid
    neighbour along a row or a column (isolated pixels, background).
    """
    z = np.nan_to_num(depth_hxw.astype(np.float64), nan=0.0)
    P = backproject(z, K)
    valid = z > 0
    n_rows, n_cols = z.shape
    # a pair (p, q) is usable when both are valid, on the same surface and without a depth jump
    pair_u = valid[:, 1:] & valid[:, :-1] & (surface_id_hxw[:, 1:] == surface_id_hxw[:, :-1]) & \
        (np.abs(z[:, 1:] - z[:, :-1]) < max_step_m)
    pair_v = valid[1:] & valid[:-1] & (surface_id_hxw[1:] == surface_id_hxw[:-1]) & \
        (np.abs(z[1:] - z[:-1]) < max_step_m)
    du = np.full(P.shape, np.nan)
    dv = np.full(P.shape, np.nan)
    if n_cols > 1:
        d = P[:, 1:] - P[:, :-1]
        f = np.where(pair_u[..., None], d, np.nan)
        fwd = np.concatenate([f, np.full((n_rows, 1, 3), np.nan)], axis=1)
        bwd = np.concatenate([np.full((n_rows, 1, 3), np.nan), f], axis=1)
        du = np.where(np.isnan(fwd), bwd, np.where(np.isnan(bwd), fwd, 0.5 * (fwd + bwd)))
    if n_rows > 1:
        d = P[1:] - P[:-1]
        f = np.where(pair_v[..., None], d, np.nan)
        fwd = np.concatenate([f, np.full((1, n_cols, 3), np.nan)], axis=0)
        bwd = np.concatenate([np.full((1, n_cols, 3), np.nan), f], axis=0)
        dv = np.where(np.isnan(fwd), bwd, np.where(np.isnan(bwd), fwd, 0.5 * (fwd + bwd)))
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1)
    ray = P / np.maximum(np.linalg.norm(P, axis=-1, keepdims=True), 1e-12)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(np.einsum("hwi,hwi->hw", n, ray)) / norm
    ang = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
    ang[~valid | ~np.isfinite(ang) | (norm <= 0)] = np.nan
    return ang
