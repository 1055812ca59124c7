"""Exact ray / triangle-mesh casting, vectorised in numpy (Moller-Trumbore), no external ray engine.

Used by the antipodal sampler to find the opposite contact when an object's mesh is available:
from a contact ``p1`` with outward normal ``n1`` the ray ``p1 - t n1`` runs through the object and
leaves it at the first *exit* face (face normal pointing along the ray). Triangles are pre-filtered
per ray with a KD-tree over the face centroids queried at samples along the ray segment (bounding-sphere
test), so the exact test runs only on the few faces near each ray.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def face_normals(verts_vx3: np.ndarray, faces_fx3: np.ndarray) -> np.ndarray:
    """Unit face normals (F, 3) of a CCW-outward triangle mesh (degenerate faces give zeros)."""
    v0, v1, v2 = (verts_vx3[faces_fx3[:, i]] for i in range(3))
    n = np.cross(v1 - v0, v2 - v0)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


def _ray_face_pairs(cen_fx3: np.ndarray, rad_f: np.ndarray, origins_rx3: np.ndarray, dirs_rx3: np.ndarray,
                    t_min: float, t_max: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """(ray, face) index pairs whose face may cross the ray segment [t_min, t_max].

    The segment is sampled every ``step`` m; a face crossing the segment within ``step / 2`` of a sample
    has its centroid within ``rad_f + step / 2`` of that sample (``rad_f`` = face bounding radius), so a
    KD-tree ball query around the samples finds every such face (and a few more).
    """
    R = len(origins_rx3)
    J = max(1, int(np.ceil((t_max - t_min) / step)) + 1)
    s = t_min + step * np.arange(J)
    samples = origins_rx3[:, None, :] + s[None, :, None] * dirs_rx3[:, None, :]  # (R, J, 3)
    radius = float(rad_f.max()) + step / 2
    pairs = cKDTree(samples.reshape(-1, 3)).sparse_distance_matrix(cKDTree(cen_fx3), radius, output_type="ndarray")
    hit = np.zeros((R, len(cen_fx3)), dtype=bool)  # dedupe (ray, face) pairs found from several samples
    hit[pairs["i"] // J, pairs["j"]] = True
    ri, fi = np.nonzero(hit)
    return ri.astype(np.int64), fi.astype(np.int64)


def exit_hits(
    verts_vx3: np.ndarray,
    faces_fx3: np.ndarray,
    origins_rx3: np.ndarray,
    dirs_rx3: np.ndarray,
    t_min: float = 1e-4,
    t_max: float | None = None,
    step: float | None = None,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """First and last hit of each ray with faces whose normal points along the ray (exit faces) in [t_min, t_max].

    Args:
        verts_vx3, faces_fx3: the mesh (m), outward CCW faces.
        origins_rx3: ray origins (R, 3) m.
        dirs_rx3: unit ray directions (R, 3).
        t_min: hits closer than this (m) are ignored (self-hits at the origin).
        t_max: hits farther than this (m) are ignored (default: the mesh's bounding-box diagonal).
        step: sampling step (m) of the candidate-face search (default: twice the median face radius,
            at least 1 mm).

    Returns:
        ``(t, points, normals)`` for the first and for the last exit hit: t (R,) distance in m (inf when no
        exit hit), hit points (R, 3) and hit face normals (R, 3) (NaN when none). For a convex mesh both agree.
    """
    R = len(origins_rx3)
    empty = (np.full(R, np.inf), np.full((R, 3), np.nan), np.full((R, 3), np.nan))
    if R == 0 or len(faces_fx3) == 0:
        return empty, (empty[0].copy(), empty[1].copy(), empty[2].copy())
    v0 = verts_vx3[faces_fx3[:, 0]]
    v1 = verts_vx3[faces_fx3[:, 1]]
    v2 = verts_vx3[faces_fx3[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    fn = face_normals(verts_vx3, faces_fx3)
    cen = (v0 + v1 + v2) / 3.0
    rad = np.sqrt(np.max(np.stack([np.sum((v - cen) ** 2, axis=1) for v in (v0, v1, v2)]), 0)) + 1e-9
    if t_max is None:
        t_max = float(np.linalg.norm(np.ptp(verts_vx3, axis=0)))
    if step is None:
        step = max(1e-3, 2.0 * float(np.median(rad)))
    ri, fi = _ray_face_pairs(cen, rad, origins_rx3, dirs_rx3, t_min, t_max, step)
    keep = np.einsum("ij,ij->i", fn[fi], dirs_rx3[ri]) > 0  # exit faces only
    ri, fi = ri[keep], fi[keep]
    out = []
    if ri.size:
        dd = dirs_rx3[ri]
        pvec = np.cross(dd, e2[fi])
        det = np.einsum("ij,ij->i", e1[fi], pvec)
        ok = np.abs(det) > 1e-15
        inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        tvec = origins_rx3[ri] - v0[fi]
        u = np.einsum("ij,ij->i", tvec, pvec) * inv
        qvec = np.cross(tvec, e1[fi])
        v = np.einsum("ij,ij->i", dd, qvec) * inv
        t = np.einsum("ij,ij->i", e2[fi], qvec) * inv
        eps = 1e-9
        hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > t_min) & (t <= t_max)
        ri, fi, t = ri[hit], fi[hit], t[hit]
    for sign in (1.0, -1.0):  # first hit (smallest t), then last hit (largest t)
        t_best = np.full(R, np.inf)
        face_best = np.full(R, -1, dtype=np.int64)
        if ri.size:
            order = np.lexsort((sign * t, ri))  # by ray, then by distance
            r_o, f_o, t_o = ri[order], fi[order], t[order]
            first = np.ones(len(r_o), dtype=bool)
            first[1:] = r_o[1:] != r_o[:-1]
            t_best[r_o[first]] = t_o[first]
            face_best[r_o[first]] = f_o[first]
        found = face_best >= 0
        pts = np.full((R, 3), np.nan)
        nrm = np.full((R, 3), np.nan)
        pts[found] = origins_rx3[found] + t_best[found, None] * dirs_rx3[found]
        nrm[found] = fn[face_best[found]]
        t_best[~found] = np.inf
        out.append((t_best, pts, nrm))
    return out[0], out[1]


def first_exit_hits(
    verts_vx3: np.ndarray,
    faces_fx3: np.ndarray,
    origins_rx3: np.ndarray,
    dirs_rx3: np.ndarray,
    t_min: float = 1e-4,
    t_max: float | None = None,
    step: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first exit hit of :func:`exit_hits`: t (R,) m, points (R, 3), face normals (R, 3)."""
    return exit_hits(verts_vx3, faces_fx3, origins_rx3, dirs_rx3, t_min, t_max, step)[0]
