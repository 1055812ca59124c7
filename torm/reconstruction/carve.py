"""Voxel carving: the classic survivors-only silhouette carve, a baseline for the projective hull.

A regular grid of voxel centres covers the box (``res`` voxels along its longest axis, cubic voxels of
edge ``pitch = longest extent / res``). Views are applied one after another and each re-projects only
the voxels that survived the views before it (RECONSTRUCTION.md: "carving only surviving voxels is an
easy 10x over naive carving"). A voxel survives a view when its centre projects inside the view's
silhouette; a centre that projects outside the image or lies behind the camera gets no evidence from
that view and survives it (as in :mod:`torm.reconstruction.visual_hull`, ``outside_image="unknown"``).
Voxels below the table plane are never occupied. The surface is extracted by marching cubes
(scikit-image) at level 0.5 of the binary occupancy, padded by one empty voxel so it is closed, with
faces wound outward (counter-clockwise seen from outside, like marching-tets output).

Pixel convention: pixel (row r, column c) covers ``[c, c+1) x [r, r+1)``, so a centre projecting to
(u, v) lies in pixel ``(floor(v), floor(u))``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from torm.errors import ReconstructionError
from torm.mesh.split import signed_volume
from torm.resources import CARVE_BYTES_PER_VOXEL, check_fits
from torm.types import TriMesh

log = logging.getLogger(__name__)

#: Points with camera z <= NEAR (m) are behind the camera: no evidence.
NEAR = 1e-3


@dataclass(frozen=True)
class CarveResult:
    """Output of :func:`carve_visual_hull`.

    occupancy: (nx, ny, nz) bool, voxel (i, j, k) centred at ``origin + (i + 0.5, j + 0.5, k + 0.5) * pitch``.
    origin: (3,) float64 corner of voxel (0, 0, 0) in metres (world frame; the box's min corner).
    pitch: voxel edge (m).
    mesh: the marching-cubes surface (metres, world frame, outward winding); empty when nothing survived.
    """

    occupancy: np.ndarray
    origin: np.ndarray
    pitch: float
    mesh: TriMesh


def voxel_grid_shape(bounds_2x3: np.ndarray, res: int) -> tuple[tuple[int, int, int], float]:
    """Voxels per axis and the voxel edge (m) for ``res`` voxels along the box's longest axis."""
    b = np.asarray(bounds_2x3, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)) or not np.all(b[1] > b[0]):
        raise ReconstructionError(f"carve: bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {b.tolist()}")
    if res < 2:
        raise ReconstructionError(f"carve: res must be >= 2 voxels, got {res}")
    ext = b[1] - b[0]
    pitch = float(ext.max() / res)
    n = np.maximum(1, np.ceil(ext / pitch - 1e-9)).astype(int)
    return (int(n[0]), int(n[1]), int(n[2])), pitch


def carve_occupancy(
    silhouettes_vxhxw: np.ndarray,
    Ks_vx3x3: np.ndarray,
    T_world_cam_vx4x4: np.ndarray,
    bounds_2x3: np.ndarray,
    res: int,
    *,
    table_z: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Survivors-only carve: (occupancy (nx, ny, nz) bool, origin (3,) m, pitch m); see the module docstring.

    Args:
        silhouettes_vxhxw: (V, H, W) silhouettes (any value > 0 is object).
        Ks_vx3x3: (V, 3, 3) intrinsics in pixels of the H x W masks.
        T_world_cam_vx4x4: (V, 4, 4) camera-to-world poses, OpenCV axes, metres.
        bounds_2x3: the box (m, world frame).
        res: voxels along the box's longest axis.
        table_z: table-top height (m); voxel centres below it are empty. None: no table.
    """
    sil = np.asarray(silhouettes_vxhxw) > 0
    if sil.ndim != 3:
        raise ReconstructionError(f"carve: silhouettes must be (V, H, W), got shape {sil.shape}")
    V, H, W = sil.shape
    Ks = np.asarray(Ks_vx3x3, dtype=np.float64)
    Ts = np.asarray(T_world_cam_vx4x4, dtype=np.float64)
    if Ks.shape != (V, 3, 3) or Ts.shape != (V, 4, 4):
        raise ReconstructionError(f"carve: need Ks ({V}, 3, 3) and poses ({V}, 4, 4), got {Ks.shape} and {Ts.shape}")
    b = np.asarray(bounds_2x3, dtype=np.float64)
    (nx, ny, nz), pitch = voxel_grid_shape(b, res)
    check_fits(nx * ny * nz * CARVE_BYTES_PER_VOXEL, f"carve at {res} voxels ({nx} x {ny} x {nz})",
               "lower reconstruction.carve_res (default 128)")
    origin = b[0].copy()
    axes = [origin[a] + (np.arange(n) + 0.5) * pitch for a, n in enumerate((nx, ny, nz))]
    k0 = 0 if table_z is None else int(np.searchsorted(axes[2], float(table_z)))
    ii, jj, kk = np.meshgrid(np.arange(nx, dtype=np.int32), np.arange(ny, dtype=np.int32),
                             np.arange(k0, nz, dtype=np.int32), indexing="ij")
    idx = ((ii * ny + jj) * nz + kk).ravel()  # flat indices of the surviving voxels
    pts = np.stack([axes[0][ii.ravel()], axes[1][jj.ravel()], axes[2][kk.ravel()]], axis=1).astype(np.float32)
    flat = sil.reshape(V, -1)
    for v in range(V):
        if len(idx) == 0:
            break
        T_cw = np.linalg.inv(Ts[v])
        p = np.einsum("ij,nj->ni", T_cw[:3, :3].astype(np.float32), pts) + T_cw[:3, 3].astype(np.float32)
        z = p[:, 2]
        front = z > NEAR
        zs = np.where(front, z, 1.0)
        u = np.floor(Ks[v, 0, 0] * p[:, 0] / zs + Ks[v, 0, 2])
        r = np.floor(Ks[v, 1, 1] * p[:, 1] / zs + Ks[v, 1, 2])
        seen = front & (u >= 0) & (u < W) & (r >= 0) & (r < H)
        keep = ~seen
        s = np.flatnonzero(seen)
        keep[s] = flat[v, r[s].astype(np.int64) * W + u[s].astype(np.int64)]
        idx, pts = idx[keep], pts[keep]
    occ = np.zeros(nx * ny * nz, dtype=bool)
    occ[idx] = True
    return occ.reshape(nx, ny, nz), origin, pitch


def occupancy_mesh(occupancy: np.ndarray, origin_3: np.ndarray, pitch: float) -> TriMesh:
    """Marching-cubes surface (level 0.5) of a binary voxel occupancy, closed and wound outward (metres)."""
    from skimage.measure import marching_cubes

    occ = np.asarray(occupancy, dtype=bool)
    if not occ.any():
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    padded = np.pad(occ, 1).astype(np.float32)
    verts, faces, _, _ = marching_cubes(padded, level=0.5, allow_degenerate=False)
    # padded index i sits at voxel centre origin + (i - 1 + 0.5) * pitch
    verts = np.asarray(origin_3, dtype=np.float64) + (verts.astype(np.float64) - 0.5) * pitch
    faces = faces.astype(np.int64)
    if signed_volume(verts, faces) < 0:
        faces = faces[:, [0, 2, 1]]
    return TriMesh(verts, faces)


def carve_visual_hull(
    silhouettes_vxhxw: np.ndarray,
    Ks_vx3x3: np.ndarray,
    T_world_cam_vx4x4: np.ndarray,
    bounds_2x3: np.ndarray,
    res: int = 128,
    *,
    table_z: float | None = None,
) -> CarveResult:
    """Carve the silhouettes into a ``res``-voxel grid over the box and mesh it (see the module docstring).

    Cost (measured in ``benchmarks/results/recon_vs_carve.md``): one projection of the surviving voxel
    centres per view; memory about :data:`torm.resources.CARVE_BYTES_PER_VOXEL` (96) bytes x voxels at the first
    view, checked against the free memory before any work.
    """
    occ, origin, pitch = carve_occupancy(silhouettes_vxhxw, Ks_vx3x3, T_world_cam_vx4x4, bounds_2x3, res,
                                         table_z=table_z)
    return CarveResult(occupancy=occ, origin=origin, pitch=pitch, mesh=occupancy_mesh(occ, origin, pitch))


__all__ = ["CarveResult", "carve_occupancy", "carve_visual_hull", "occupancy_mesh", "voxel_grid_shape"]
