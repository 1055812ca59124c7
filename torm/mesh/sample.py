"""Area-uniform surface sampling of meshes into point clouds with outward normals."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from torm.errors import ReconstructionError
from torm.types import ObjectPointCloud, TriMesh


def _rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        raise ReconstructionError("sampling needs a seed or a numpy Generator (nothing is seeded globally)")
    return np.random.default_rng(int(rng))


def sample_surface(mesh: TriMesh, n_points: int, rng: np.random.Generator | int,
                   object_index: int = 0) -> ObjectPointCloud:
    """Sample ``n_points`` points uniformly by area on the mesh surface.

    Faces are drawn with probability proportional to their area, points uniformly inside each face
    (square-root barycentric trick). Each point gets its face's unit normal, which points outward for
    an outward (counter-clockwise seen from outside) wound mesh such as marching-tets output.

    Args:
        mesh: the object mesh (metres); faces with zero area are never drawn.
        n_points: number of samples (> 0).
        rng: numpy Generator or integer seed.
        object_index: stored in the returned cloud.

    Returns:
        :class:`ObjectPointCloud` with points (n_points, 3) m and unit normals (n_points, 3), float64.
    """
    if n_points <= 0:
        raise ReconstructionError(f"sample_surface: n_points must be positive, got {n_points}")
    gen = _rng(rng)
    v, f = mesh.verts_vx3, mesh.faces_fx3
    if len(f) == 0:
        raise ReconstructionError("sample_surface: the mesh has no faces; reconstruct or split it first")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    total = area2.sum()
    if not np.isfinite(total) or total <= 0:
        raise ReconstructionError("sample_surface: the mesh has zero surface area (degenerate faces only)")
    face = gen.choice(len(f), size=n_points, p=area2 / total)
    r1 = np.sqrt(gen.random(n_points))
    r2 = gen.random(n_points)
    w0, w1, w2 = 1.0 - r1, r1 * (1.0 - r2), r1 * r2
    pts = w0[:, None] * a[face] + w1[:, None] * b[face] + w2[:, None] * c[face]
    normals = cross[face] / area2[face, None]
    return ObjectPointCloud(points_nx3=pts, normals_nx3=normals, object_index=int(object_index))


def sample_objects(meshes: Sequence[TriMesh], n_points: int, rng: np.random.Generator | int
                   ) -> tuple[ObjectPointCloud, ...]:
    """One cloud of exactly ``n_points`` per mesh (``object_index`` = position in ``meshes``), sharing ``rng``."""
    gen = _rng(rng)
    return tuple(sample_surface(m, n_points, gen, object_index=i) for i, m in enumerate(meshes))
