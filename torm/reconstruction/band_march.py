"""Marching tets on a narrow band in one compiled pass: the mesh topology without torch bookkeeping.

Paper mode extracts the mesh of its narrow band (:mod:`torm.reconstruction.narrow_band`) every step. The
topology (which tets cross zero, which edges carry a surface vertex, the triangles) depends only on the signs
of the SDF, so it is found here in one numba pass over the band tets; only the surface-vertex interpolation,
through which gradients flow, stays in torch (:func:`interpolate_surface`). The result is the mesh that
:func:`torm.reconstruction.marching_tets.marching_tets` gives on the crossing tets with the edge ids of the
grid (same vertex order: crossing edges by increasing edge id; same face order: one-triangle tets, then
two-triangle tets, each in band order), which ``tests/test_recon_band_march.py`` checks on random fields.
Measured on syn5 (grid 48, 5000 steps, 1 torch thread, idle 2-core AVX-512 machine): the mesh stage took 5.0 ms
per step with ``marching_tets_with_info`` and its torch bookkeeping (mostly per-op overhead on a few thousand tets)
and 1.3-1.5 ms with this kernel, with a bit-identical optimisation result (``benchmarks/results/
reconstruction_paper.json``).
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
import torch

from torm.reconstruction.marching_tets import NUM_TRI_16, TRI_TABLE_16x6
from torm.reconstruction.tetgrid import TET_EDGES_6x2

_TET_EDGES = np.ascontiguousarray(TET_EDGES_6x2, dtype=np.int64)
_TABLE = np.ascontiguousarray(TRI_TABLE_16x6, dtype=np.int64)
_NUM = np.ascontiguousarray(NUM_TRI_16, dtype=np.int64)


class BandMesh(NamedTuple):
    """Topology of the surface in a band (indices only; no positions).

    vert_ids_c: (C,) int64 indices (into the band's vertices, increasing) of every vertex of a crossing tet.
    edge_a_m, edge_b_m: (M,) int64 ends of the crossing edge of each surface vertex, as indices into
        ``vert_ids_c`` with ``edge_a < edge_b``; surface vertices ordered by increasing grid edge id.
    faces_fx3: (F, 3) int64 triangles over the M surface vertices, wound inside -> outside.
    """

    vert_ids_c: np.ndarray
    edge_a_m: np.ndarray
    edge_b_m: np.ndarray
    faces_fx3: np.ndarray


@nb.njit(cache=True, nogil=True)
def _band_march_kernel(s_n, tets_bx4, edges_bx6, n_edges, tet_edges, table, num):  # pragma: no cover - compiled
    Tb = tets_bx4.shape[0]
    Nb = s_n.shape[0]
    cross = np.empty(Tb, dtype=np.int64)
    case = np.empty(Tb, dtype=np.int64)
    n_c = 0
    n_faces = 0
    for t in range(Tb):
        c = 0
        for k in range(4):
            if s_n[tets_bx4[t, k]] < 0:
                c |= 1 << k
        if c != 0 and c != 15:
            cross[n_c] = t
            case[n_c] = c
            n_c += 1
            n_faces += num[c]
    used = np.zeros(Nb, dtype=np.bool_)
    flag = np.zeros(n_edges, dtype=np.bool_)
    end_a = np.empty(n_edges, dtype=np.int64)
    end_b = np.empty(n_edges, dtype=np.int64)
    ids = np.empty(6 * n_c, dtype=np.int64)
    n_e = 0
    for i in range(n_c):
        t = cross[i]
        for k in range(4):
            used[tets_bx4[t, k]] = True
        for j in range(6):
            a = tets_bx4[t, tet_edges[j, 0]]
            b = tets_bx4[t, tet_edges[j, 1]]
            if (s_n[a] < 0) != (s_n[b] < 0):
                e = edges_bx6[t, j]
                if not flag[e]:
                    flag[e] = True
                    end_a[e] = min(a, b)
                    end_b[e] = max(a, b)
                    ids[n_e] = e
                    n_e += 1
    local = np.full(Nb, -1, dtype=np.int64)
    vc = np.empty(Nb, dtype=np.int64)
    n_v = 0
    for v in range(Nb):
        if used[v]:
            local[v] = n_v
            vc[n_v] = v
            n_v += 1
    ids = np.sort(ids[:n_e])
    slot = np.empty(n_edges, dtype=np.int64)
    ea = np.empty(n_e, dtype=np.int64)
    eb = np.empty(n_e, dtype=np.int64)
    for m in range(n_e):
        e = ids[m]
        slot[e] = m
        ea[m] = local[end_a[e]]
        eb[m] = local[end_b[e]]
    faces = np.empty((n_faces, 3), dtype=np.int64)
    f = 0
    for want in (1, 2):
        for i in range(n_c):
            c = case[i]
            if num[c] != want:
                continue
            t = cross[i]
            for q in range(3 * want):
                faces[f + q // 3, q % 3] = slot[edges_bx6[t, table[c, q]]]
            f += want
    return vc[:n_v], ea, eb, faces


def band_march(s_n: np.ndarray | torch.Tensor, tets_bx4: np.ndarray, edges_bx6: np.ndarray,
               n_edges: int) -> BandMesh:
    """Surface topology of the zero level set of ``s_n`` on the band tets.

    Args:
        s_n: (Nb,) SDF (any unit; only signs are read, ``s < 0`` inside) of the band's vertices.
        tets_bx4: (Tb, 4) int64 band tets as indices into ``s_n``, positively oriented, vertex order of the grid
            (indices increasing with the grid's vertex ids, e.g. the positions in a sorted id list).
        edges_bx6: (Tb, 6) int64 ids in ``[0, n_edges)`` of each tet's edges in ``TET_EDGES_6x2`` order
            (:attr:`TetGrid.tet_edges_tx6` of the band tets).
        n_edges: number of edges of the grid.

    Returns:
        :class:`BandMesh`; all arrays empty when no tet crosses zero.
    """
    s = s_n.detach().cpu().numpy() if torch.is_tensor(s_n) else np.asarray(s_n)
    if s.ndim != 1:
        raise ValueError(f"band_march: s_n must be (Nb,), got {s.shape}")
    tets = np.ascontiguousarray(tets_bx4, dtype=np.int64)
    edges = np.ascontiguousarray(edges_bx6, dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4 or edges.shape != (len(tets), 6):
        raise ValueError(f"band_march: need tets (Tb, 4) and edges (Tb, 6), got {tets.shape} and {edges.shape}")
    vc, ea, eb, faces = _band_march_kernel(np.ascontiguousarray(s), tets, edges, int(n_edges), _TET_EDGES,
                                           _TABLE, _NUM)
    return BandMesh(vc, ea, eb, faces)


def interpolate_surface(verts_cx3: torch.Tensor, sdf_c: torch.Tensor, edge_a_m: np.ndarray,
                        edge_b_m: np.ndarray) -> torch.Tensor:
    """(M, 3) surface vertices ``(v_a s_b - v_b s_a) / (s_b - s_a)`` on the crossing edges, differentiable.

    ``verts_cx3`` (C, 3) positions (m) and ``sdf_c`` (C,) SDF of the crossing tets' vertices
    (:attr:`BandMesh.vert_ids_c`); the formula and its evaluation order are those of
    :func:`torm.reconstruction.marching_tets.marching_tets_with_info`.
    """
    ea = torch.from_numpy(edge_a_m)
    eb = torch.from_numpy(edge_b_m)
    s_a = sdf_c[ea].unsqueeze(-1)
    s_b = sdf_c[eb].unsqueeze(-1)
    return (verts_cx3[ea] * s_b - verts_cx3[eb] * s_a) / (s_b - s_a)


__all__ = ["BandMesh", "band_march", "interpolate_surface"]
