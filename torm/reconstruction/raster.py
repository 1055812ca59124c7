"""Differentiable silhouette rendering of triangle meshes on the CPU (nvdiffrast-style).

The design follows nvdiffrast's ``rasterize`` + ``antialias`` split, measured fastest on a 2-core CPU
(RECONSTRUCTION.md):

1. Vertices (metres, world frame) are projected in torch with the pinhole ``K`` and ``T_cam_world``
   (OpenCV camera: x right, y down, z forward): ``u = fx * x / z + cx``, ``v = fy * y / z + cy``, the same
   mapping as :meth:`torm.types.CameraView.project`.
2. A hard z-buffer rasteriser (numba, bounding-box scan per triangle) writes a triangle-id buffer and a
   z-depth buffer. **Pixel (row r, column c) covers [c, c+1) x [r, r+1) in (u, v) and is sampled at its
   centre (c + 0.5, r + 0.5)**, so with ``cx = W / 2`` the optical axis hits the corner between the
   four central pixels. Depth is interpolated as 1/z (perspective-correct) and the nearest surface wins.
   Triangles with a vertex closer than ``NEAR`` (m) to the camera plane are skipped (no clipping).
3. Analytic antialiasing of the silhouette (nvdiffrast's ``antialias``): for every horizontally or
   vertically adjacent pixel pair where exactly one pixel is covered, we walk from the covering
   triangle across same-facing neighbours along the segment between the two pixel centres until a
   silhouette edge (mesh boundary or fold between front/back-facing triangles in screen space) is
   crossed. With ``t`` in [0, 1] the crossing position along the segment (from the covered centre),
   the covered pixel loses ``max(0, 0.5 - t)`` and the empty pixel gains ``max(0, t - 0.5)``.
   Only edges whose screen direction is closer to perpendicular to the pair's axis are used
   (``|e_perp| >= |e_along|``), so a pixel is corrected along one axis and exact 1-D coverage is
   recovered for axis-aligned edges. ``t`` is a torch expression of the two projected edge vertices,
   so gradients reach the vertex positions; only silhouette pixels carry gradients and the torch
   work scales with their number.

The forward value is the hard mask plus the corrections (not clamped; values stay in [0, 1] except
for sub-pixel slivers). Pairs where both pixels are covered by different surfaces do not change a
binary silhouette and are ignored.

:func:`render_silhouettes_sparse` returns the same image as the hard mask plus the corrections at the edge
pixels (:class:`SparseSilhouettes`), so that a loss can be formed on the edge pixels only
(:func:`torm.reconstruction.losses.envelope_mask_loss_sparse`); on CPU tensors the corrections and their
gradient w.r.t. the vertices are two compiled passes in float64 (:class:`_EdgeCoverage`; the torch ops they
replace, :func:`edge_coverage_reference`, are the tested reference). Measured on syn12's final mesh (27k faces,
4 views of 256 x 144, 1 thread): render + loss + backward 11.5-12.2 ms with the dense image and the torch ops,
7.8-8.7 ms this way (``benchmarks/results/recon_vs_carve.md`` has what it does to whole runs).
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass

import numba as nb
import numpy as np
import torch

#: Triangles with a vertex at z < NEAR (m, camera frame) are not rasterised.
NEAR = 1e-3

_MAX_WALK = 16


# ----------------------------------------------------------------------------------------------------------
# Compiled kernels
# ----------------------------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _rasterize_reference_kernel(uvz_mx3, faces_fx3, H, W, tri_id_hw, depth_hw):  # pragma: no cover
    """Hard z-buffer rasterisation. ``uvz`` = (u px, v px, z m). Writes tri ids (-1 empty) and z-depth. The
    reference of :func:`_rasterize_kernel` (same pixels, ids and depths; ``tests/test_recon_raster.py``)."""
    inv_best = np.zeros((H, W), dtype=np.float64)  # 1/z of the nearest surface so far (0 = empty)
    F = faces_fx3.shape[0]
    for f in range(F):
        a = faces_fx3[f, 0]
        b = faces_fx3[f, 1]
        c = faces_fx3[f, 2]
        ax = uvz_mx3[a, 0]
        ay = uvz_mx3[a, 1]
        bx = uvz_mx3[b, 0]
        by = uvz_mx3[b, 1]
        cx = uvz_mx3[c, 0]
        cy = uvz_mx3[c, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        za = uvz_mx3[a, 2]
        zb = uvz_mx3[b, 2]
        zc = uvz_mx3[c, 2]
        if za < NEAR or zb < NEAR or zc < NEAR:
            continue
        if abs(area) < 1e-12:
            continue
        xmin = min(ax, min(bx, cx))
        xmax = max(ax, max(bx, cx))
        ymin = min(ay, min(by, cy))
        ymax = max(ay, max(by, cy))
        # pixel centres c + 0.5 inside [xmin, xmax]
        c0 = max(0, int(np.ceil(xmin - 0.5)))
        c1 = min(W - 1, int(np.floor(xmax - 0.5)))
        r0 = max(0, int(np.ceil(ymin - 0.5)))
        r1 = min(H - 1, int(np.floor(ymax - 0.5)))
        if c0 > c1 or r0 > r1:
            continue
        inv_area = 1.0 / area
        iza = 1.0 / za
        izb = 1.0 / zb
        izc = 1.0 / zc
        for r in range(r0, r1 + 1):
            py = r + 0.5
            for col in range(c0, c1 + 1):
                px = col + 0.5
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv_area
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv_area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                iz = w0 * iza + w1 * izb + w2 * izc
                if iz > inv_best[r, col]:
                    inv_best[r, col] = iz
                    tri_id_hw[r, col] = f
                    depth_hw[r, col] = 1.0 / iz


@nb.njit(cache=True, nogil=True)
def _pixel_spans_kernel(uvz_mx3, H, W):  # pragma: no cover - compiled
    """(M, 4) int32 per vertex: ceil(u - 0.5), floor(u - 0.5), ceil(v - 0.5), floor(v - 0.5), each clamped to
    [-1, W] (u) or [-1, H] (v): the pixel-centre spans of a triangle are the min of the ceils and the max of the
    floors of its corners (ceil and floor are monotone), so they need no per-face rounding."""
    M = uvz_mx3.shape[0]
    out = np.empty((M, 4), dtype=np.int32)
    for i in range(M):
        u = uvz_mx3[i, 0] - 0.5
        v = uvz_mx3[i, 1] - 0.5
        out[i, 0] = int(min(max(np.ceil(u), -1.0), W))
        out[i, 1] = int(min(max(np.floor(u), -1.0), W))
        out[i, 2] = int(min(max(np.ceil(v), -1.0), H))
        out[i, 3] = int(min(max(np.floor(v), -1.0), H))
    return out


@nb.njit(cache=True, nogil=True)
def _rasterize_kernel(uvz_mx3, spans_mx4, faces_fx3, H, W, tri_id_hw, depth_hw):  # pragma: no cover - compiled
    """Hard z-buffer rasterisation. ``uvz`` = (u px, v px, z m), ``spans`` = :func:`_pixel_spans_kernel` of it.
    Writes tri ids (-1 empty) and z-depth: those of :func:`_rasterize_reference_kernel`. Most faces of a fine mesh
    hold no pixel centre; they are dropped on four small integers per corner before any coordinate is read
    (syn12, 27k faces in 256 x 144: about half the time of the reference)."""
    inv_best = np.zeros((H, W), dtype=np.float64)  # 1/z of the nearest surface so far (0 = empty)
    F = faces_fx3.shape[0]
    for f in range(F):
        a = faces_fx3[f, 0]
        b = faces_fx3[f, 1]
        c = faces_fx3[f, 2]
        c0 = max(0, min(spans_mx4[a, 0], min(spans_mx4[b, 0], spans_mx4[c, 0])))
        c1 = min(W - 1, max(spans_mx4[a, 1], max(spans_mx4[b, 1], spans_mx4[c, 1])))
        if c0 > c1:
            continue
        r0 = max(0, min(spans_mx4[a, 2], min(spans_mx4[b, 2], spans_mx4[c, 2])))
        r1 = min(H - 1, max(spans_mx4[a, 3], max(spans_mx4[b, 3], spans_mx4[c, 3])))
        if r0 > r1:
            continue
        za = uvz_mx3[a, 2]
        zb = uvz_mx3[b, 2]
        zc = uvz_mx3[c, 2]
        if za < NEAR or zb < NEAR or zc < NEAR:
            continue
        ax = uvz_mx3[a, 0]
        ay = uvz_mx3[a, 1]
        bx = uvz_mx3[b, 0]
        by = uvz_mx3[b, 1]
        cx = uvz_mx3[c, 0]
        cy = uvz_mx3[c, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        inv_area = 1.0 / area
        iza = 1.0 / za
        izb = 1.0 / zb
        izc = 1.0 / zc
        for r in range(r0, r1 + 1):
            py = r + 0.5
            for col in range(c0, c1 + 1):
                px = col + 0.5
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv_area
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv_area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                iz = w0 * iza + w1 * izb + w2 * izc
                if iz > inv_best[r, col]:
                    inv_best[r, col] = iz
                    tri_id_hw[r, col] = f
                    depth_hw[r, col] = 1.0 / iz


@nb.njit(cache=True, nogil=True)
def _silhouette_kernel(uvz_mx3, faces_fx3, H, W, out_hw):  # pragma: no cover - compiled
    """Hard silhouette: pixel centres covered by any triangle (same rule as ``_rasterize_kernel``, no depth)."""
    for f in range(faces_fx3.shape[0]):
        a = faces_fx3[f, 0]
        b = faces_fx3[f, 1]
        c = faces_fx3[f, 2]
        if uvz_mx3[a, 2] < NEAR or uvz_mx3[b, 2] < NEAR or uvz_mx3[c, 2] < NEAR:
            continue
        ax = uvz_mx3[a, 0]
        ay = uvz_mx3[a, 1]
        bx = uvz_mx3[b, 0]
        by = uvz_mx3[b, 1]
        cx = uvz_mx3[c, 0]
        cy = uvz_mx3[c, 1]
        c0 = max(0, int(np.ceil(min(ax, min(bx, cx)) - 0.5)))
        c1 = min(W - 1, int(np.floor(max(ax, max(bx, cx)) - 0.5)))
        if c0 > c1:
            continue
        r0 = max(0, int(np.ceil(min(ay, min(by, cy)) - 0.5)))
        r1 = min(H - 1, int(np.floor(max(ay, max(by, cy)) - 0.5)))
        if r0 > r1:
            continue
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        inv_area = 1.0 / area
        for r in range(r0, r1 + 1):
            py = r + 0.5
            for col in range(c0, c1 + 1):
                if out_hw[r, col]:
                    continue
                px = col + 0.5
                w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv_area
                w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv_area
                if w0 >= 0.0 and w1 >= 0.0 and 1.0 - w0 - w1 >= 0.0:
                    out_hw[r, col] = True


@nb.njit(cache=True, nogil=True)
def _segment_exit(uv, fa, fb, fc, p0x, p0y, dx, dy, t_min, skip_a, skip_b):
    """Exit of the ray p0 + t d (t > t_min) through the triangle's edges, skipping edge (skip_a, skip_b).

    Returns (local edge index 0..2 or -1, t). Edge k joins vertex k and k+1 (mod 3).
    """
    best_k = -1
    best_t = 1e30
    vs = (fa, fb, fc)
    for k in range(3):
        i = vs[k]
        j = vs[(k + 1) % 3]
        if (i == skip_a and j == skip_b) or (i == skip_b and j == skip_a):
            continue
        ex = uv[j, 0] - uv[i, 0]
        ey = uv[j, 1] - uv[i, 1]
        den = dx * ey - dy * ex
        if abs(den) < 1e-12:
            continue
        qx = uv[i, 0] - p0x
        qy = uv[i, 1] - p0y
        t = (qx * ey - qy * ex) / den
        s = (qx * dy - qy * dx) / den  # position along the edge, 0 at i, 1 at j
        if s < -1e-9 or s > 1.0 + 1e-9 or t <= t_min:
            continue
        if t < best_t:
            best_t = t
            best_k = k
    return best_k, best_t


@nb.njit(cache=True, nogil=True, inline="always")
def _face_orientation(uv, faces_fx3, f):  # pragma: no cover - compiled
    """Sign (+1, -1, 0) of face f's projected signed area: ``_orientation_kernel``'s value for one face."""
    a = faces_fx3[f, 0]
    b = faces_fx3[f, 1]
    c = faces_fx3[f, 2]
    area = ((uv[b, 0] - uv[a, 0]) * (uv[c, 1] - uv[a, 1]) - (uv[b, 1] - uv[a, 1]) * (uv[c, 0] - uv[a, 0]))
    return 1 if area > 0 else (-1 if area < 0 else 0)


@nb.njit(cache=True, nogil=True)
def _aa_pairs_kernel(uv, faces_fx3, adj_fx3, tri_id_hw):
    """Find the silhouette edge for every covered/empty pixel pair.

    Returns an (n, 5) int64 array of records ``[covered_pixel, empty_pixel, axis_dir, vert_a, vert_b]``
    where pixels are flat indices ``r * W + c`` and ``axis_dir`` is 0: +u, 1: -u, 2: +v, 3: -v
    (direction from the covered to the empty pixel).
    """
    H, W = tri_id_hw.shape
    cap = 4 * (H + W) + 64
    out = np.empty((cap, 5), dtype=np.int64)
    n = 0
    for r in range(H):
        for c in range(W):
            for axis in range(2):
                r2 = r + axis
                c2 = c + 1 - axis
                if r2 >= H or c2 >= W:
                    continue
                t1 = tri_id_hw[r, c]
                t2 = tri_id_hw[r2, c2]
                if (t1 < 0) == (t2 < 0):
                    continue
                if t1 >= 0:
                    f = t1
                    pin = r * W + c
                    pout = r2 * W + c2
                    p0x = c + 0.5
                    p0y = r + 0.5
                    dx = float(1 - axis)
                    dy = float(axis)
                    code = 2 * axis
                else:
                    f = t2
                    pin = r2 * W + c2
                    pout = r * W + c
                    p0x = c2 + 0.5
                    p0y = r2 + 0.5
                    dx = -float(1 - axis)
                    dy = -float(axis)
                    code = 2 * axis + 1
                # walk across same-facing neighbours until a silhouette edge
                t_prev = -1e-9
                ea = -1
                eb = -1
                found = False
                for _ in range(_MAX_WALK):
                    fa = faces_fx3[f, 0]
                    fb = faces_fx3[f, 1]
                    fc = faces_fx3[f, 2]
                    k, t = _segment_exit(uv, fa, fb, fc, p0x, p0y, dx, dy, t_prev, ea, eb)
                    if k < 0 or t > 1.0:
                        break
                    ea = faces_fx3[f, k]
                    eb = faces_fx3[f, (k + 1) % 3]
                    g = adj_fx3[f, k]
                    og = _face_orientation(uv, faces_fx3, g) if g >= 0 else 0
                    if g < 0 or og != _face_orientation(uv, faces_fx3, f) or og == 0:
                        found = True
                        break
                    f = g
                    t_prev = t
                if not found:
                    continue
                ex = uv[eb, 0] - uv[ea, 0]
                ey = uv[eb, 1] - uv[ea, 1]
                # dominant-axis rule: a horizontal pair uses mostly-vertical edges and vice versa
                if axis == 0 and abs(ey) < abs(ex):
                    continue
                if axis == 1 and abs(ex) <= abs(ey):
                    continue
                if n >= cap:
                    bigger = np.empty((2 * cap, 5), dtype=np.int64)
                    bigger[:n] = out[:n]
                    out = bigger
                    cap *= 2
                out[n, 0] = pin
                out[n, 1] = pout
                out[n, 2] = code
                out[n, 3] = ea
                out[n, 4] = eb
                n += 1
    return out[:n]


# ----------------------------------------------------------------------------------------------------------
# Mesh topology helpers (numpy)
# ----------------------------------------------------------------------------------------------------------
def face_adjacency(faces_fx3: np.ndarray, n_verts: int) -> np.ndarray:
    """(F, 3) int64: the face across local edge k (vertices k, k+1 mod 3) of each face, -1 on a boundary.

    Edges shared by more than two faces (non-manifold) get one arbitrary partner. Compiled, linear in F
    (half-edges bucketed by their smaller vertex); :func:`face_adjacency_reference` is the sort-based version it
    is tested against.
    """
    f = np.ascontiguousarray(faces_fx3, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return -np.ones((0, 3), dtype=np.int64)
    return _face_adjacency_kernel(f, int(n_verts))


def face_adjacency_reference(faces_fx3: np.ndarray, n_verts: int) -> np.ndarray:
    """:func:`face_adjacency` by sorting edge keys in numpy (the slow reference path)."""
    F = len(faces_fx3)
    adj = -np.ones((F, 3), dtype=np.int64)
    if F == 0:
        return adj
    f = np.asarray(faces_fx3, dtype=np.int64)
    a = f[:, [0, 1, 2]].reshape(-1)
    b = f[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b) * np.int64(n_verts) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = np.nonzero(ks[1:] == ks[:-1])[0]
    h0 = order[same]
    h1 = order[same + 1]
    adj_flat = adj.reshape(-1)
    adj_flat[h0] = h1 // 3
    adj_flat[h1] = h0 // 3
    return adj_flat.reshape(F, 3)


@nb.njit(cache=True, nogil=True)
def _face_adjacency_kernel(faces_fx3, n_verts):  # pragma: no cover - compiled
    """Half-edge h = 3 f + k bucketed by its smaller vertex (counting sort); partners matched by the larger one
    within a bucket. The larger ends are copied beside the bucket so that the matching loop reads one array, and
    the work arrays are int32 (measured on a 24.6k-face syn12 mesh: 1.2-1.3 ms before, with int64 arrays and the
    ends read back through the faces; 1.2-1.4 ms with the copied ends in int64; 0.5-0.6 ms in int32)."""
    F = faces_fx3.shape[0]
    n_half = 3 * F
    lo = np.empty(n_half, dtype=np.int32)
    hi = np.empty(n_half, dtype=np.int32)
    start = np.zeros(n_verts + 1, dtype=np.int32)
    for f in range(F):
        for k in range(3):
            a = faces_fx3[f, k]
            b = faces_fx3[f, (k + 1) % 3]
            h = 3 * f + k
            lo[h] = min(a, b)
            hi[h] = max(a, b)
            start[lo[h] + 1] += 1
    for v in range(n_verts):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    bucket = np.empty(n_half, dtype=np.int32)
    bucket_hi = np.empty(n_half, dtype=np.int32)
    for h in range(n_half):
        i = fill[lo[h]]
        bucket[i] = h
        bucket_hi[i] = hi[h]
        fill[lo[h]] = i + 1
    adj = -np.ones(n_half, dtype=np.int64)
    for v in range(n_verts):
        for i in range(start[v], start[v + 1]):
            hi_ = bucket[i]
            if adj[hi_] >= 0:
                continue
            top = bucket_hi[i]
            for j in range(i + 1, start[v + 1]):
                if bucket_hi[j] != top:
                    continue
                hj = bucket[j]
                if adj[hj] >= 0:
                    continue
                adj[hi_] = hj // 3
                adj[hj] = hi_ // 3
                break
    return adj.reshape(F, 3)


@nb.njit(cache=True, nogil=True)
def _orientation_kernel(uv_mx2, faces_fx3):  # pragma: no cover - compiled
    """Sign (+1, -1, 0) of each projected triangle's signed area."""
    F = faces_fx3.shape[0]
    out = np.empty(F, dtype=np.int8)
    for f in range(F):
        a = faces_fx3[f, 0]
        b = faces_fx3[f, 1]
        c = faces_fx3[f, 2]
        area = ((uv_mx2[b, 0] - uv_mx2[a, 0]) * (uv_mx2[c, 1] - uv_mx2[a, 1])
                - (uv_mx2[b, 1] - uv_mx2[a, 1]) * (uv_mx2[c, 0] - uv_mx2[a, 0]))
        out[f] = 1 if area > 0 else (-1 if area < 0 else 0)
    return out


# ----------------------------------------------------------------------------------------------------------
# Projection
# ----------------------------------------------------------------------------------------------------------
def project_torch(verts_mx3: torch.Tensor, K_vx3x3: torch.Tensor, T_cam_world_vx4x4: torch.Tensor) -> torch.Tensor:
    """Project world points (M, 3) m into V views: (V, M, 3) = (u px, v px, z m), OpenCV convention."""
    R = T_cam_world_vx4x4[:, :3, :3]
    t = T_cam_world_vx4x4[:, :3, 3]
    p = torch.einsum("vij,mj->vmi", R, verts_mx3) + t[:, None, :]
    z = p[..., 2]
    zs = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    u = K_vx3x3[:, None, 0, 0] * p[..., 0] / zs + K_vx3x3[:, None, 0, 2]
    v = K_vx3x3[:, None, 1, 1] * p[..., 1] / zs + K_vx3x3[:, None, 1, 2]
    return torch.stack([u, v, z], dim=-1)


def _as_batch(K, T_cam_world, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    K_t = torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=dtype)
    T_t = torch.as_tensor(np.asarray(T_cam_world, dtype=np.float64), dtype=dtype)
    if K_t.ndim == 2:
        K_t = K_t[None]
    if T_t.ndim == 2:
        T_t = T_t[None]
    if K_t.shape[1:] != (3, 3) or T_t.shape[1:] != (4, 4) or len(K_t) != len(T_t):
        raise ValueError(f"need K (V, 3, 3) and T_cam_world (V, 4, 4), got {tuple(K_t.shape)} and {tuple(T_t.shape)}")
    return K_t, T_t


# ----------------------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------------------
def rasterize(uvz_mx3: np.ndarray, faces_fx3: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Hard rasterisation of projected vertices (u px, v px, z m): (tri_id (H, W) int32, -1 empty; z-depth float32)."""
    tri = -np.ones((H, W), dtype=np.int32)
    depth = np.zeros((H, W), dtype=np.float32)
    if len(faces_fx3) and len(uvz_mx3):
        uvz = np.ascontiguousarray(uvz_mx3, dtype=np.float64)
        _rasterize_kernel(uvz, _pixel_spans_kernel(uvz, int(H), int(W)),
                          np.ascontiguousarray(faces_fx3, dtype=np.int64), int(H), int(W), tri, depth)
    return tri, depth


def render_depth(verts_mx3, faces_fx3, K: np.ndarray, T_cam_world: np.ndarray, H: int, W: int) -> np.ndarray:
    """Z-depth (H, W) float32 in metres of the nearest surface (0 where empty); no gradients."""
    v = np.asarray(verts_mx3.detach().cpu().numpy() if torch.is_tensor(verts_mx3) else verts_mx3, dtype=np.float64)
    f = np.asarray(faces_fx3.detach().cpu().numpy() if torch.is_tensor(faces_fx3) else faces_fx3, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((H, W), dtype=np.float32)
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_world, dtype=np.float64)
    p = v @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    uvz = np.stack([K[0, 0] * p[:, 0] / zs + K[0, 2], K[1, 1] * p[:, 1] / zs + K[1, 2], z], axis=1)
    return rasterize(uvz, f, H, W)[1]


def render_mask(verts_mx3, faces_fx3, K: np.ndarray, T_cam_world: np.ndarray, H: int, W: int) -> np.ndarray:
    """Hard (H, W) bool silhouette (pixel centre covered); no gradients."""
    return render_depth(verts_mx3, faces_fx3, K, T_cam_world, H, W) > 0


def render_mask_fast(verts_mx3: np.ndarray, faces_fx3: np.ndarray, K: np.ndarray, T_cam_world: np.ndarray,
                     H: int, W: int) -> np.ndarray:
    """Hard (H, W) bool silhouette like :func:`render_mask` (same pixels), without a depth buffer: faster."""
    v = np.asarray(verts_mx3, dtype=np.float64)
    f = np.ascontiguousarray(faces_fx3, dtype=np.int64)
    out = np.zeros((H, W), dtype=bool)
    if len(f) == 0:
        return out
    T = np.asarray(T_cam_world, dtype=np.float64)
    # einsum, not a BLAS matmul: a multithreaded BLAS made this (N, 3) x (3, 3) product 100-300x slower on
    # a loaded machine
    p = np.einsum("ij,nj->ni", T[:3, :3], v) + T[:3, 3]
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    uvz = np.stack([K[0, 0] * p[:, 0] / zs + K[0, 2], K[1, 1] * p[:, 1] / zs + K[1, 2], z], axis=1)
    _silhouette_kernel(np.ascontiguousarray(uvz), f, int(H), int(W), out)
    return out


def render_silhouettes(
    verts_mx3: torch.Tensor,
    faces_fx3,
    K_vx3x3,
    T_cam_world_vx4x4,
    H: int,
    W: int,
    adjacency_fx3: np.ndarray | None = None,
    pool: Executor | None = None,
) -> torch.Tensor:
    """Antialiased silhouettes (V, H, W) of one mesh in V views, differentiable w.r.t. ``verts_mx3``.

    Args:
        verts_mx3: (M, 3) world-frame vertices in metres (float32/64 torch tensor, may require grad).
        faces_fx3: (F, 3) vertex indices (torch or numpy); winding does not matter for silhouettes.
        K_vx3x3: (V, 3, 3) or (3, 3) intrinsics in pixels of an H x W image.
        T_cam_world_vx4x4: (V, 4, 4) or (4, 4) world-to-camera transforms, OpenCV axes.
        H, W: image size in pixels.
        adjacency_fx3: optional precomputed :func:`face_adjacency` of ``faces_fx3``.
        pool: optional executor that runs the compiled per-view work (rasterisation, silhouette-edge search; it
            releases the GIL) of the views in parallel; the torch work stays in the calling thread (a torch op in
            a pool thread would start its own OpenMP team at the default size).

    Returns:
        (V, H, W) tensor in the dtype of ``verts_mx3``: hard coverage plus the edge antialiasing term
        (:meth:`SparseSilhouettes.dense` of :func:`render_silhouettes_sparse`).
    """
    return render_silhouettes_sparse(verts_mx3, faces_fx3, K_vx3x3, T_cam_world_vx4x4, H, W, adjacency_fx3,
                                     pool).dense()


@dataclass(frozen=True)
class SparseSilhouettes:
    """Antialiased silhouettes of V views of H x W pixels as the hard coverage plus the antialiasing corrections at
    the few pixels that have one (the silhouette's edge pixels; the only pixels whose value has a gradient).

    Attributes:
        hard_vxhxw: (V, H, W) float32 numpy, 1 where a triangle covers the pixel centre, else 0 (no gradient).
        pix_n: (N,) int64 torch, distinct flat pixel indices ``(view * H + row) * W + column``, ascending.
        delta_n: (N,) torch in the vertices' dtype, differentiable: the sum of the corrections at each pixel.
    """

    hard_vxhxw: np.ndarray
    pix_n: torch.Tensor
    delta_n: torch.Tensor

    def dense(self) -> torch.Tensor:
        """(V, H, W) torch: ``hard + corrections``, the value :func:`render_silhouettes` returns."""
        hard = torch.from_numpy(self.hard_vxhxw).to(dtype=self.delta_n.dtype, device=self.delta_n.device)
        return hard.reshape(-1).index_add(0, self.pix_n, self.delta_n).reshape(self.hard_vxhxw.shape)

    def values(self) -> np.ndarray:
        """(V, H, W) float32 numpy copy of :meth:`dense` without a graph."""
        out = self.hard_vxhxw.copy()
        out.reshape(-1)[self.pix_n.cpu().numpy()] += self.delta_n.detach().cpu().numpy().astype(np.float32)
        return out


def render_silhouettes_sparse(
    verts_mx3: torch.Tensor,
    faces_fx3,
    K_vx3x3,
    T_cam_world_vx4x4,
    H: int,
    W: int,
    adjacency_fx3: np.ndarray | None = None,
    pool: Executor | None = None,
) -> SparseSilhouettes:
    """:func:`render_silhouettes` as a :class:`SparseSilhouettes`: the autograd graph holds only the edge pixels'
    corrections, so a loss written on them (:func:`torm.reconstruction.losses.envelope_mask_loss_sparse`) costs
    time in proportion to the silhouettes' perimeter instead of V x H x W. Same arguments as
    :func:`render_silhouettes`."""
    batch = SilhouetteBatch(verts_mx3, faces_fx3, K_vx3x3, T_cam_world_vx4x4, H, W)
    if batch.empty:
        return batch.finish()
    adj = face_adjacency(batch.faces_fx3, len(verts_mx3)) if adjacency_fx3 is None else adjacency_fx3
    views = range(batch.n_views)
    for _ in (map if pool is None or batch.n_views < 2 else pool.map)(lambda i: batch.view(i, adj), views):
        pass
    return batch.finish()


class SilhouetteBatch:
    """The steps of :func:`render_silhouettes_sparse`, for callers that schedule the views themselves.

    Construct (projects every vertex into every view, no graph), call :meth:`view` once for every view index in any
    order and on any threads (compiled, releases the GIL; views write disjoint slices), then :meth:`finish` in the
    thread that owns the autograd graph.

    Args: as :func:`render_silhouettes`; ``compiled``: project and differentiate the edge corrections with the
    compiled kernels in float64 (CPU tensors), else with torch ops in the vertices' dtype (the reference path).
    """

    def __init__(self, verts_mx3: torch.Tensor, faces_fx3, K_vx3x3, T_cam_world_vx4x4, H: int, W: int,
                 compiled: bool = True) -> None:
        self.verts = verts_mx3
        self.dtype = verts_mx3.dtype if verts_mx3.is_floating_point() else torch.float32
        K_t, T_t = _as_batch(K_vx3x3, T_cam_world_vx4x4, self.dtype)
        self.K_t, self.T_t = K_t.to(verts_mx3.device), T_t.to(verts_mx3.device)
        self.n_views, self.H, self.W = len(K_t), int(H), int(W)
        f = faces_fx3.detach().cpu().numpy() if torch.is_tensor(faces_fx3) else faces_fx3
        self.faces_fx3 = np.ascontiguousarray(np.asarray(f, dtype=np.int64).reshape(-1, 3))
        self.hard = np.zeros((self.n_views, self.H, self.W), dtype=np.float32)
        self.empty = len(self.faces_fx3) == 0 or len(verts_mx3) == 0
        self._recs: list[np.ndarray | None] = [None] * self.n_views
        self.compiled = compiled
        self._K64 = np.ascontiguousarray(np.broadcast_to(np.asarray(K_vx3x3, dtype=np.float64), (self.n_views, 3, 3)))
        self._T64 = np.ascontiguousarray(np.broadcast_to(np.asarray(T_cam_world_vx4x4, dtype=np.float64),
                                                         (self.n_views, 4, 4)))
        if not self.empty:
            if compiled and verts_mx3.device.type == "cpu":
                X = verts_mx3.detach().numpy().astype(np.float64)
                self._uvz = _project_kernel(np.ascontiguousarray(X), self._K64, self._T64)
            else:
                with torch.no_grad():
                    self._uvz = project_torch(verts_mx3, self.K_t, self.T_t).cpu().numpy().astype(np.float64)

    def view(self, i: int, adjacency_fx3: np.ndarray, raster: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Rasterise view ``i`` and find its silhouette-edge pixel pairs; ``adjacency_fx3`` is
        :func:`face_adjacency` of the faces. ``raster``: this view's :meth:`rasterize_view` if already done."""
        tri, _ = self.rasterize_view(i) if raster is None else raster
        self.hard[i] = tri >= 0
        uv = np.ascontiguousarray(self._uvz[i, :, :2])
        self._recs[i] = _aa_pairs_kernel(uv, self.faces_fx3, adjacency_fx3, tri)

    def rasterize_view(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """View ``i``'s hard pass: (triangle ids (H, W), z-depth (H, W)), :func:`rasterize`; needs no adjacency."""
        return rasterize(self._uvz[i], self.faces_fx3, self.H, self.W)

    def finish(self) -> SparseSilhouettes:
        """The silhouettes, with the graph of the antialiasing corrections (after :meth:`view` of every view)."""
        V, H, W, dev = self.n_views, self.H, self.W, self.verts.device
        no_pix = torch.zeros(0, dtype=torch.int64, device=dev)
        if self.empty:
            return SparseSilhouettes(self.hard, no_pix,
                                     self.verts.sum() * 0.0 + torch.zeros(0, dtype=self.dtype, device=dev))
        if any(r is None for r in self._recs):
            raise RuntimeError("SilhouetteBatch.finish: call view(i, adjacency) for every view first")
        recs = []
        for i, r in enumerate(self._recs):
            if len(r):
                r = r.copy()
                r[:, 0] += i * H * W
                r[:, 1] += i * H * W
                recs.append(np.concatenate([r, np.full((len(r), 1), i, dtype=np.int64)], axis=1))
        if not recs:
            return SparseSilhouettes(self.hard, no_pix, torch.zeros(0, dtype=self.dtype, device=dev))
        rec_np = np.concatenate(recs)
        pix, inv = _compact_pixels(np.concatenate([rec_np[:, 0], rec_np[:, 1]]), V * H * W)
        if self.compiled and dev.type == "cpu":
            delta = _EdgeCoverage.apply(self.verts, rec_np, inv, len(pix), self._K64, self._T64, H, W)
        else:
            delta = edge_coverage_reference(self.verts, rec_np, inv, len(pix), self.K_t, self.T_t, H, W)
        return SparseSilhouettes(self.hard, torch.from_numpy(pix).to(dev), delta)


def edge_coverage_reference(verts_mx3: torch.Tensor, rec_nx6: np.ndarray, inv_2n: np.ndarray, n_pix: int,
                            K_t: torch.Tensor, T_t: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """The antialiasing corrections summed per pixel, (n_pix,), in torch ops (the slow reference path of the
    compiled :class:`_EdgeCoverage`): the records' edge ends projected again with a graph, eq. of the module
    docstring, summed with ``index_add`` at ``inv_2n`` (covered pixels' records first, then the empty pixels')."""
    dev = verts_mx3.device
    ends, ends_inv = np.unique(rec_nx6[:, 3:5], return_inverse=True)
    uv_e = project_torch(verts_mx3[torch.from_numpy(ends).to(dev)], K_t, T_t)[..., :2]  # (V, E, 2)
    rec = torch.from_numpy(rec_nx6).to(dev)
    corr = _aa_corrections(uv_e, rec, torch.from_numpy(ends_inv.reshape(-1, 2)).to(dev), H, W)
    return torch.zeros(n_pix, dtype=corr.dtype, device=dev).index_add(0, torch.from_numpy(inv_2n).to(dev), corr)


class _EdgeCoverage(torch.autograd.Function):
    """:func:`edge_coverage_reference` as two compiled passes: the forward computes each record's crossing
    ``t`` and its derivative w.r.t. the two edge ends' world positions (float64); the backward scatters them.
    Replaces about 40 small torch ops and their backward (syn12, 4 views of 256 x 144: about 4k records)."""

    @staticmethod
    def forward(ctx, verts_mx3, rec_nx6, inv_2n, n_pix, K64, T64, H, W):  # noqa: D102
        X = verts_mx3.detach().cpu().numpy().astype(np.float64)
        delta, dtdx, wt = _edge_coverage_fwd(X, K64, T64, rec_nx6, inv_2n, int(n_pix), int(H), int(W))
        ctx.save_for_backward(torch.from_numpy(dtdx), torch.from_numpy(wt))
        ctx.rec, ctx.inv, ctx.n_verts, ctx.dtype = rec_nx6, inv_2n, len(X), verts_mx3.dtype
        return torch.from_numpy(delta).to(verts_mx3.dtype)

    @staticmethod
    def backward(ctx, g_delta):  # noqa: D102
        dtdx, wt = ctx.saved_tensors
        g = _edge_coverage_bwd(g_delta.detach().cpu().numpy().astype(np.float64), ctx.rec, ctx.inv, dtdx.numpy(),
                               wt.numpy(), ctx.n_verts)
        return torch.from_numpy(g).to(ctx.dtype), None, None, None, None, None, None, None


@nb.njit(cache=True, nogil=True)
def _edge_coverage_fwd(X, K, T, rec, inv, n_pix, H, W):  # pragma: no cover - compiled
    """Per record n: the crossing t of the segment from the covered pixel's centre towards the empty one with the
    projected edge (a, b); corrections ``-relu(0.5 - clamp(t))`` at inv[n], ``relu(clamp(t) - 0.5)`` at inv[N + n];
    ``dtdx[n, k]`` = dt / d(world position of end k), ``wt[n]`` = d(correction) / dt of the two corrections."""
    N = rec.shape[0]
    delta = np.zeros(n_pix, dtype=np.float64)
    dtdx = np.zeros((N, 2, 3), dtype=np.float64)
    wt = np.zeros((N, 2), dtype=np.float64)
    uv = np.empty((2, 2), dtype=np.float64)
    jac = np.empty((2, 2, 3), dtype=np.float64)  # d(u, v) / d(world x, y, z) of the two ends
    for n in range(N):
        view = rec[n, 5]
        local = rec[n, 0] - view * H * W
        p0x = (local % W) + 0.5
        p0y = (local // W) + 0.5
        code = rec[n, 2]
        axis = code // 2
        sgn = 1.0 - 2.0 * (code % 2)
        dx = sgn * (1 - axis)
        dy = sgn * axis
        for k in range(2):
            i = rec[n, 3 + k]
            px = T[view, 0, 0] * X[i, 0] + T[view, 0, 1] * X[i, 1] + T[view, 0, 2] * X[i, 2] + T[view, 0, 3]
            py = T[view, 1, 0] * X[i, 0] + T[view, 1, 1] * X[i, 1] + T[view, 1, 2] * X[i, 2] + T[view, 1, 3]
            pz = T[view, 2, 0] * X[i, 0] + T[view, 2, 1] * X[i, 1] + T[view, 2, 2] * X[i, 2] + T[view, 2, 3]
            if abs(pz) < 1e-9:
                pz = 1e-9
            fx = K[view, 0, 0]
            fy = K[view, 1, 1]
            uv[k, 0] = fx * px / pz + K[view, 0, 2]
            uv[k, 1] = fy * py / pz + K[view, 1, 2]
            # d(u, v)/d(camera point), then through R to the world point
            du = (fx / pz, 0.0, -fx * px / (pz * pz))
            dv = (0.0, fy / pz, -fy * py / (pz * pz))
            for c in range(3):
                jac[k, 0, c] = du[0] * T[view, 0, c] + du[1] * T[view, 1, c] + du[2] * T[view, 2, c]
                jac[k, 1, c] = dv[0] * T[view, 0, c] + dv[1] * T[view, 1, c] + dv[2] * T[view, 2, c]
        ex = uv[1, 0] - uv[0, 0]
        ey = uv[1, 1] - uv[0, 1]
        qx = uv[0, 0] - p0x
        qy = uv[0, 1] - p0y
        den = dx * ey - dy * ex
        t = (qx * ey - qy * ex) / den
        tc = min(max(t, 0.0), 1.0)
        delta[inv[n]] -= max(0.0, 0.5 - tc)
        delta[inv[N + n]] += max(0.0, tc - 0.5)
        inside = t >= 0.0 and t <= 1.0  # torch.clamp passes the gradient on [min, max]
        wt[n, 0] = 1.0 if inside and tc < 0.5 else 0.0
        wt[n, 1] = 1.0 if inside and tc > 0.5 else 0.0
        # t = (q x e) / (d x e), q = a - p0, e = b - a (2-D cross products)
        dta_u = ((ey + qy) - t * dy) / den
        dta_v = (-(ex + qx) + t * dx) / den
        dtb_u = (-qy + t * dy) / den
        dtb_v = (qx - t * dx) / den
        for c in range(3):
            dtdx[n, 0, c] = dta_u * jac[0, 0, c] + dta_v * jac[0, 1, c]
            dtdx[n, 1, c] = dtb_u * jac[1, 0, c] + dtb_v * jac[1, 1, c]
    return delta, dtdx, wt


@nb.njit(cache=True, nogil=True)
def _edge_coverage_bwd(g_delta, rec, inv, dtdx, wt, n_verts):  # pragma: no cover - compiled
    N = rec.shape[0]
    g = np.zeros((n_verts, 3), dtype=np.float64)
    for n in range(N):
        gt = g_delta[inv[n]] * wt[n, 0] + g_delta[inv[N + n]] * wt[n, 1]
        if gt == 0.0:
            continue
        for k in range(2):
            i = rec[n, 3 + k]
            for c in range(3):
                g[i, c] += gt * dtdx[n, k, c]
    return g


@nb.njit(cache=True, nogil=True)
def _project_kernel(X, K, T):  # pragma: no cover - compiled
    """(V, M, 3) = (u px, v px, z m) of the world points X (M, 3) in the V views: :func:`project_torch` in float64."""
    V = K.shape[0]
    M = X.shape[0]
    out = np.empty((V, M, 3), dtype=np.float64)
    for v in range(V):
        for i in range(M):
            px = T[v, 0, 0] * X[i, 0] + T[v, 0, 1] * X[i, 1] + T[v, 0, 2] * X[i, 2] + T[v, 0, 3]
            py = T[v, 1, 0] * X[i, 0] + T[v, 1, 1] * X[i, 1] + T[v, 1, 2] * X[i, 2] + T[v, 1, 3]
            pz = T[v, 2, 0] * X[i, 0] + T[v, 2, 1] * X[i, 1] + T[v, 2, 2] * X[i, 2] + T[v, 2, 3]
            zs = 1e-9 if abs(pz) < 1e-9 else pz
            out[v, i, 0] = K[v, 0, 0] * px / zs + K[v, 0, 2]
            out[v, i, 1] = K[v, 1, 1] * py / zs + K[v, 1, 2]
            out[v, i, 2] = pz
    return out


def _compact_pixels(idx_n: np.ndarray, n_pix: int) -> tuple[np.ndarray, np.ndarray]:
    """(distinct values of ``idx_n`` ascending, for each entry the position of its value among them): what
    ``np.unique(idx_n, return_inverse=True)`` gives, in O(N + n_pix) (compiled) instead of a sort."""
    slot = np.full(n_pix, -1, dtype=np.int32)
    return _compact_kernel(np.ascontiguousarray(idx_n, dtype=np.int64), slot)


@nb.njit(cache=True, nogil=True)
def _compact_kernel(idx_n, slot):  # pragma: no cover - compiled
    n = idx_n.shape[0]
    for i in range(n):
        slot[idx_n[i]] = 0
    m = 0
    for p in range(slot.shape[0]):
        if slot[p] == 0:
            slot[p] = m
            m += 1
    pix = np.empty(m, dtype=np.int64)
    inv = np.empty(n, dtype=np.int64)
    for i in range(n):
        k = slot[idx_n[i]]
        pix[k] = idx_n[i]
        inv[i] = k
    return pix, inv


def _aa_corrections(uv_vxex2: torch.Tensor, rec: torch.Tensor, ab_nx2: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """Coverage changes for the covered pixels (first half) and the empty pixels (second half) of the (N, 6)
    records; the edge of record n joins the projected points ``uv_vxex2[view, ab_nx2[n, 0]]`` and
    ``uv_vxex2[view, ab_nx2[n, 1]]`` (pixels)."""
    view = rec[:, 5]
    pin = rec[:, 0] - view * H * W
    code = rec[:, 2]
    a = uv_vxex2[view, ab_nx2[:, 0]]
    b = uv_vxex2[view, ab_nx2[:, 1]]
    p0 = torch.stack([(pin % W).to(a.dtype) + 0.5, (pin // W).to(a.dtype) + 0.5], dim=1)
    axis = code // 2
    sgn = 1.0 - 2.0 * (code % 2).to(a.dtype)
    d = torch.stack([sgn * (1 - axis).to(a.dtype), sgn * axis.to(a.dtype)], dim=1)
    e = b - a
    q = a - p0
    den = d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0]
    t = (q[:, 0] * e[:, 1] - q[:, 1] * e[:, 0]) / den
    t = t.clamp(0.0, 1.0)
    return torch.cat([-torch.relu(0.5 - t), torch.relu(t - 0.5)])


def render_silhouette(
    verts_mx3: torch.Tensor, faces_fx3, K: np.ndarray, T_cam_world: np.ndarray, H: int, W: int
) -> torch.Tensor:
    """Antialiased silhouette (H, W) of a mesh in one view; see :func:`render_silhouettes`."""
    return render_silhouettes(verts_mx3, faces_fx3, K, T_cam_world, H, W)[0]
