"""Reconstruction metrics: silhouette IoU, depth errors (paper Table II), Chamfer, volume IoU, object counts.

All functions are pure (no state, no global seeding). Units: metres for inputs; Chamfer is reported
in millimetres. Arrays are named with their shapes (``V`` views, ``H x W`` pixels, ``N`` points).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from torm.errors import ReconstructionError
from torm.types import TriMesh

DELTA_THRESHOLDS = (1.05, 1.10, 1.25)


def _as_views(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ReconstructionError(f"{name} must be (H, W) or (V, H, W), got shape {a.shape}")
    return a


def silhouette_iou(pred_vxhxw: np.ndarray, gt_vxhxw: np.ndarray) -> dict[str, object]:
    """Per-view IoU of binary silhouettes (values > 0 are object).

    Args:
        pred_vxhxw: (V, H, W) or (H, W) predicted masks (bool or instance ids).
        gt_vxhxw: same shape, ground truth.

    Returns:
        ``{"per_view": list of V floats, "mean": float, "min": float}``. A view where both masks are
        empty scores 1.0 (nothing to find, nothing found).
    """
    p = _as_views(pred_vxhxw, "pred masks") > 0
    g = _as_views(gt_vxhxw, "gt masks") > 0
    if p.shape != g.shape:
        raise ReconstructionError(f"silhouette_iou: pred {p.shape} and gt {g.shape} masks differ in shape")
    inter = (p & g).sum(axis=(1, 2)).astype(np.float64)
    union = (p | g).sum(axis=(1, 2)).astype(np.float64)
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    return {"per_view": iou.tolist(), "mean": float(iou.mean()), "min": float(iou.min())}


def depth_metrics(pred_depth_vxhxw: np.ndarray, gt_depth_vxhxw: np.ndarray, gt_mask_vxhxw: np.ndarray
                  ) -> dict[str, float]:
    """Depth errors inside the GT object masks, as in the paper's Table II.

    Evaluated pixels: GT mask > 0, GT depth finite and > 0, and a predicted depth (finite, > 0).
    All evaluated pixels of all views are pooled (each pixel weighs the same).

    Returns (z-depths in metres):
        ``rmse`` sqrt(mean (d - d*)^2) m; ``absrel`` mean |d - d*| / d*; ``mae`` mean |d - d*| m;
        ``delta_1.05``, ``delta_1.10``, ``delta_1.25``: fraction (0..1, the paper prints percent) of pixels
        with ``max(d / d*, d* / d) < threshold``; ``coverage``: share of GT-mask pixels (with valid GT
        depth) that have a predicted depth; ``n_pixels``: evaluated pixel count. With no evaluated
        pixel the error metrics are NaN and coverage is 0.
    """
    pred = _as_views(pred_depth_vxhxw, "pred depth").astype(np.float64)
    gt = _as_views(gt_depth_vxhxw, "gt depth").astype(np.float64)
    mask = _as_views(gt_mask_vxhxw, "gt mask") > 0
    if not pred.shape == gt.shape == mask.shape:
        raise ReconstructionError(f"depth_metrics: shapes differ: pred {pred.shape}, gt {gt.shape}, mask {mask.shape}")
    with np.errstate(invalid="ignore"):
        gt_ok = mask & np.isfinite(gt) & (gt > 0)
        ev = gt_ok & np.isfinite(pred) & (pred > 0)
    n_gt, n = int(gt_ok.sum()), int(ev.sum())
    out: dict[str, float] = {"coverage": (n / n_gt) if n_gt else 0.0, "n_pixels": float(n)}
    if n == 0:
        out.update({"rmse": float("nan"), "absrel": float("nan"), "mae": float("nan")})
        out.update({f"delta_{t:.2f}": float("nan") for t in DELTA_THRESHOLDS})
        return out
    d, d_gt = pred[ev], gt[ev]
    err = d - d_gt
    ratio = np.maximum(d / d_gt, d_gt / d)
    out["rmse"] = float(np.sqrt(np.mean(err**2)))
    out["absrel"] = float(np.mean(np.abs(err) / d_gt))
    out["mae"] = float(np.mean(np.abs(err)))
    for t in DELTA_THRESHOLDS:
        out[f"delta_{t:.2f}"] = float(np.mean(ratio < t))
    return out


def chamfer_distance_mm(points_a_nx3: np.ndarray, points_b_mx3: np.ndarray) -> float:
    """Two-sided Chamfer distance in millimetres between point sets given in metres.

    Definition: ``(mean_a min_b |a - b| + mean_b min_a |a - b|) / 2`` (Euclidean, not squared), times 1000.
    """
    a = np.asarray(points_a_nx3, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(points_b_mx3, dtype=np.float64).reshape(-1, 3)
    if len(a) == 0 or len(b) == 0:
        raise ReconstructionError("chamfer_distance_mm: both point sets need at least one point")
    d_ab = cKDTree(b).query(a)[0]
    d_ba = cKDTree(a).query(b)[0]
    return float(500.0 * (d_ab.mean() + d_ba.mean()))


def _concat(meshes: TriMesh | Sequence[TriMesh]) -> TriMesh:
    if isinstance(meshes, TriMesh):
        return meshes
    vs, fs, off = [], [], 0
    for m in meshes:
        vs.append(m.verts_vx3)
        fs.append(m.faces_fx3 + off)
        off += len(m.verts_vx3)
    if not vs:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    return TriMesh(np.concatenate(vs), np.concatenate(fs))


def mesh_volume(mesh: TriMesh | Sequence[TriMesh]) -> float:
    """Enclosed volume (m^3) of a closed outward-wound mesh (sum over several meshes), by the divergence theorem."""
    m = _concat(mesh)
    v, f = m.verts_vx3, m.faces_fx3
    if len(f) == 0:
        return 0.0
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def mesh_centroid(mesh: TriMesh) -> np.ndarray:
    """(3,) volume centroid (m) of a closed mesh; the vertex mean when the enclosed volume is ~0."""
    v, f = mesh.verts_vx3, mesh.faces_fx3
    if len(f) == 0:
        return v.mean(0) if len(v) else np.full(3, np.nan)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol6 = np.einsum("ij,ij->i", a, np.cross(b, c))
    total = vol6.sum()
    if abs(total) < 1e-15:
        return v.mean(0)
    return ((a + b + c) * vol6[:, None]).sum(0) / (4.0 * total)


def occupancy_grid(mesh: TriMesh | Sequence[TriMesh], origin_3: np.ndarray, pitch: float,
                   shape: tuple[int, int, int]) -> np.ndarray:
    """(nx, ny, nz) bool occupancy of voxel centres ``origin + (i + 0.5, j + 0.5, k + 0.5) * pitch``.

    Exact point-in-mesh test at the voxel centres by vertical ray casting: each triangle adds its
    crossing with every voxel column whose centre lies in its xy projection, signed by the triangle's
    normal z (outward up = +1); the winding number of a centre is the sum of the crossings above it,
    and the centre is inside when it is >= 1 (so overlapping closed meshes give their union). Column
    centres are offset by a tiny irrational fraction of the pitch so that no column passes exactly
    through a mesh edge or vertex.
    """
    m = _concat(mesh)
    nx, ny, nz = (int(s) for s in shape)
    occ_diff = np.zeros((nx * ny, nz + 1), dtype=np.int32)
    v, f = m.verts_vx3, m.faces_fx3
    if len(f):
        jitter = pitch * np.array([1.2345678e-4 * np.sqrt(2), 0.98765432e-4 * np.sqrt(3)])
        org = np.asarray(origin_3, dtype=np.float64)
        xy = (v[:, :2] - org[:2] - jitter) / pitch - 0.5  # column index space: centre of column i is at i
        z = (v[:, 2] - org[2]) / pitch - 0.5  # voxel k centre at k
        tri_xy = xy[f]  # (F, 3, 2)
        lo = np.maximum(np.ceil(tri_xy.min(1)).astype(np.int64), 0)
        hi = np.minimum(np.floor(tri_xy.max(1)).astype(np.int64), [nx - 1, ny - 1])
        cnt = np.clip(hi - lo + 1, 0, None)
        n_cols = cnt[:, 0] * cnt[:, 1]
        tid = np.repeat(np.arange(len(f)), n_cols)
        if len(tid):
            start = np.cumsum(n_cols) - n_cols
            local = np.arange(len(tid)) - np.repeat(start, n_cols)
            ci = lo[tid, 0] + local // np.maximum(cnt[tid, 1], 1)
            cj = lo[tid, 1] + local % np.maximum(cnt[tid, 1], 1)
            p0, p1, p2 = tri_xy[tid, 0], tri_xy[tid, 1], tri_xy[tid, 2]
            q = np.stack([ci, cj], axis=1).astype(np.float64)
            e1, e2, e3 = p1 - p0, p2 - p0, q - p0
            det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                b1 = (e3[:, 0] * e2[:, 1] - e3[:, 1] * e2[:, 0]) / det
                b2 = (e1[:, 0] * e3[:, 1] - e1[:, 1] * e3[:, 0]) / det
                hit = (det != 0) & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1)
            tz = z[f[tid[hit]]]
            zc = tz[:, 0] * (1 - b1[hit] - b2[hit]) + tz[:, 1] * b1[hit] + tz[:, 2] * b2[hit]
            sign = np.sign(det[hit]).astype(np.int32)  # +1 when the xy projection is CCW = normal up
            kc = np.clip(np.ceil(zc), 0, nz).astype(np.int64)  # centres k < zc lie below the crossing
            col = ci[hit] * ny + cj[hit]
            np.add.at(occ_diff, (col, np.zeros_like(col)), sign)
            np.add.at(occ_diff, (col, kc), -sign)
    winding = np.cumsum(occ_diff[:, :nz], axis=1)
    return (winding >= 1).reshape(nx, ny, nz)


def volume_iou(pred: TriMesh | Sequence[TriMesh], gt: TriMesh | Sequence[TriMesh], *, pitch: float = 0.001,
               max_voxels: int = 8_000_000) -> dict[str, float]:
    """Volume IoU and volume ratio between closed meshes (each side may be a list: their union).

    Occupancy is sampled at the centres of a regular voxel grid (edge ``pitch`` m, default 1 mm) over
    the union of both bounding boxes; the pitch grows when the grid would exceed ``max_voxels``
    samples. Deterministic (no random sampling).

    Returns:
        ``{"iou": |P & G| / |P | G| over voxel centres, "volume_ratio": V_pred / V_gt from the exact
        enclosed volumes, "pred_volume" m^3, "gt_volume" m^3, "pitch" m, "n_samples": voxel count}``.
        IoU is 1.0 when both are empty.
    """
    P, G = _concat(pred), _concat(gt)
    vol_p, vol_g = mesh_volume(P), mesh_volume(G)
    pts = [m.verts_vx3 for m in (P, G) if len(m.faces_fx3)]
    out = {"pred_volume": vol_p, "gt_volume": vol_g,
           "volume_ratio": (vol_p / vol_g) if vol_g > 0 else float("nan")}
    if not pts:
        out.update({"iou": 1.0, "pitch": pitch, "n_samples": 0.0})
        return out
    allp = np.concatenate(pts)
    lo, hi = allp.min(0) - pitch, allp.max(0) + pitch
    n = np.ceil((hi - lo) / pitch)
    if np.prod(n) > max_voxels:
        pitch = float(pitch * (np.prod(n) / max_voxels) ** (1 / 3) * 1.001)
        n = np.ceil((hi - lo) / pitch)
    shape = tuple(int(x) for x in n)
    op = occupancy_grid(P, lo, pitch, shape) if len(P.faces_fx3) else np.zeros(shape, bool)
    og = occupancy_grid(G, lo, pitch, shape) if len(G.faces_fx3) else np.zeros(shape, bool)
    union = int((op | og).sum())
    out["iou"] = float((op & og).sum() / union) if union else 1.0
    out["pitch"] = float(pitch)
    out["n_samples"] = float(np.prod(shape))
    return out


def match_objects(pred_centroids_kx3: np.ndarray, gt_centroids_mx3: np.ndarray, max_dist: float = 0.03
                  ) -> dict[str, object]:
    """Match reconstructed objects to GT objects by centroid distance (Hungarian, one-to-one).

    Args:
        pred_centroids_kx3: (K, 3) centroids of the reconstructed components (m), e.g. :func:`mesh_centroid`.
        gt_centroids_mx3: (M, 3) centroids of the GT objects (m).
        max_dist: a pair farther apart than this (m) is not a match.

    Returns:
        ``{"n_present": M, "n_found": matched GT objects, "n_spurious": unmatched predictions,
        "pairs": [(pred_index, gt_index), ...], "distances": [m, ...]}``.
    """
    p = np.asarray(pred_centroids_kx3, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(gt_centroids_mx3, dtype=np.float64).reshape(-1, 3)
    pairs: list[tuple[int, int]] = []
    dists: list[float] = []
    if len(p) and len(g):
        d = np.linalg.norm(p[:, None] - g[None], axis=-1)
        cost = np.where(d <= max_dist, d, 1e6)
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows, cols, strict=True):
            if d[r, c] <= max_dist:
                pairs.append((int(r), int(c)))
                dists.append(float(d[r, c]))
    return {"n_present": len(g), "n_found": len(pairs), "n_spurious": len(p) - len(pairs),
            "pairs": pairs, "distances": dists}


def match_meshes(pred: Sequence[TriMesh], gt: Sequence[TriMesh], max_dist: float = 0.03) -> dict[str, object]:
    """:func:`match_objects` on the volume centroids of two lists of meshes."""
    pc = np.array([mesh_centroid(m) for m in pred]).reshape(-1, 3)
    gc = np.array([mesh_centroid(m) for m in gt]).reshape(-1, 3)
    return match_objects(pc, gc, max_dist=max_dist)


def match_clouds_to_meshes(clouds: Sequence[np.ndarray], gt: Sequence[TriMesh], tol: float = 0.01,
                           min_fraction: float = 0.5, spacing: float = 0.002) -> dict[str, object]:
    """Match reconstructed point clouds to GT meshes by surface overlap (Hungarian, one-to-one).

    A cloud's score for a GT object is the fraction of its points within ``tol`` of that object's surface (a
    dense area-uniform sample, at most ``spacing`` apart on average). Unlike centroid matching it holds when
    only part of an object was seen (a test tube whose lower half a rack hides: its reconstruction's centroid
    sits centimetres above the tube's) and it does not depend on how the GT mesh's vertices are spread (a
    tube's vertex mean sits in its dense rounded bottom).

    Args:
        clouds: K point arrays (N_k, 3), m, world frame.
        gt: M GT meshes, same frame.
        tol: a point this close to a surface (m) counts for that object.
        min_fraction: a pair whose score is lower is not a match.
        spacing: mean spacing of the GT surface sample (m).

    Returns:
        ``{"n_present": M, "n_found": matched GT objects, "n_spurious": unmatched clouds,
        "pairs": [(cloud_index, gt_index), ...], "fractions": [score of each pair, ...]}``.
    """
    from torm.mesh.sample import sample_surface

    if tol <= 0 or not 0 < min_fraction <= 1 or spacing <= 0:
        raise ReconstructionError(f"match_clouds_to_meshes: need tol > 0, 0 < min_fraction <= 1, spacing > 0; got "
                                  f"{tol}, {min_fraction}, {spacing}")
    score = np.zeros((len(clouds), len(gt)))
    for j, mesh in enumerate(gt):
        if not len(mesh.faces_fx3):
            continue
        v, f = mesh.verts_vx3, mesh.faces_fx3
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
        n = int(np.clip(area / spacing**2, 2000, 200_000))
        tree = cKDTree(sample_surface(mesh, n, np.random.default_rng(0)).points_nx3)
        for k, pts in enumerate(clouds):
            pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
            if len(pts):
                d, _ = tree.query(pts, distance_upper_bound=tol)
                score[k, j] = float(np.mean(d <= tol))
    pairs: list[tuple[int, int]] = []
    fractions: list[float] = []
    if score.size:
        rows, cols = linear_sum_assignment(-score)
        for r, c in zip(rows, cols, strict=True):
            if score[r, c] >= min_fraction:
                pairs.append((int(r), int(c)))
                fractions.append(float(score[r, c]))
    return {"n_present": len(gt), "n_found": len(pairs), "n_spurious": len(clouds) - len(pairs),
            "pairs": pairs, "fractions": fractions}
