"""Split a triangle mesh into connected components (one per object).

Faces are nodes of a graph whose edges join faces sharing a mesh edge (the same two vertex
indices), as in the paper's Sec. III-C; components are the connected components of that graph
(``scipy.sparse.csgraph.connected_components``). Two objects that touch only at a vertex stay
separate; duplicated vertices (same position, different index) are *not* merged, so weld them first
if the mesh comes from a format that splits vertices (marching-tets output never does).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from torm.errors import ReconstructionError
from torm.types import TriMesh

log = logging.getLogger(__name__)


def face_components(faces_fx3: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the face-adjacency graph (faces sharing an edge).

    Returns:
        ``(n_components, labels_f)`` with labels (F,) int in ``[0, n_components)``.
    """
    f = np.asarray(faces_fx3, dtype=np.int64).reshape(-1, 3)
    n_f = len(f)
    if n_f == 0:
        return 0, np.zeros(0, dtype=np.int64)
    e = np.sort(f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)  # (3F, 2), face i owns rows 3i..3i+2
    n_v = int(f.max()) + 1
    key = e[:, 0] * n_v + e[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    fid = order // 3
    same = ks[1:] == ks[:-1]  # consecutive rows with the same edge: link their faces
    a, b = fid[:-1][same], fid[1:][same]
    g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n_f, n_f))
    n, labels = connected_components(g, directed=False)
    return int(n), labels.astype(np.int64)


def signed_volume(verts_vx3: np.ndarray, faces_fx3: np.ndarray) -> float:
    """Signed volume (m^3) enclosed by a closed, outward-wound triangle mesh (divergence theorem)."""
    v = np.asarray(verts_vx3, dtype=np.float64)
    f = np.asarray(faces_fx3, dtype=np.int64)
    if len(f) == 0:
        return 0.0
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def _submesh(verts: np.ndarray, faces: np.ndarray) -> TriMesh:
    used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
    return TriMesh(verts[used], inverse.reshape(-1, 3))


def split_components(
    verts_vx3: np.ndarray,
    faces_fx3: np.ndarray,
    *,
    min_faces: int = 0,
    min_fraction: float = 0.0,
    min_volume: float = 0.0,
) -> list[TriMesh]:
    """Split a mesh into its edge-connected components, dropping tiny ones.

    Args:
        verts_vx3: (V, 3) vertices in metres.
        faces_fx3: (F, 3) int faces (outward winding).
        min_faces: drop components with fewer faces than this (count).
        min_fraction: drop components with fewer than ``min_fraction * F`` faces (fraction of all faces).
        min_volume: drop components whose enclosed volume ``|signed volume|`` is below this, in m^3
            (e.g. 1e-6 = 1 cm^3); meaningful for closed components.

    Returns:
        The kept components as :class:`TriMesh` (vertices re-indexed to the used ones; every face of a
        kept component is preserved exactly, in its original order and winding), sorted by centroid
        (mean vertex position) x, then y, then z.
    """
    v = np.asarray(verts_vx3, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces_fx3, dtype=np.int64).reshape(-1, 3)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ReconstructionError("split_components: face indices out of range of the vertex array")
    if min_faces < 0 or not 0.0 <= min_fraction <= 1.0 or min_volume < 0:
        raise ReconstructionError(
            f"split_components: thresholds must be non-negative (min_fraction in [0, 1]); got "
            f"min_faces={min_faces}, min_fraction={min_fraction}, min_volume={min_volume}"
        )
    n, labels = face_components(f)
    if n == 0:
        return []
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(n + 1))
    thresh_faces = max(min_faces, int(np.ceil(min_fraction * len(f))))
    kept: list[tuple[tuple[float, float, float], TriMesh]] = []
    n_dropped = 0
    for c in range(n):
        fc = f[order[bounds[c] : bounds[c + 1]]]  # original face order within the component
        if len(fc) < thresh_faces or (min_volume > 0 and abs(signed_volume(v, fc)) < min_volume):
            n_dropped += 1
            continue
        m = _submesh(v, fc)
        cen = m.verts_vx3.mean(0)
        kept.append(((round(float(cen[0]), 9), round(float(cen[1]), 9), round(float(cen[2]), 9)), m))
    if n_dropped:
        log.info("split_components: dropped %d of %d components below the size thresholds", n_dropped, n)
    kept.sort(key=lambda cm: cm[0])
    return [m for _, m in kept]
