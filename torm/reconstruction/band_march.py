"""Marching tets on a narrow band in one compiled pass: the mesh topology without torch bookkeeping.

Paper mode extracts the mesh of its narrow band (:mod:`torm.reconstruction.crossing_band`) every step. The
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


class BandMarchWork:
    """Buffers :func:`band_march` reuses from call to call on one grid (``n_edges`` edges).

    Buffers passed in rather than allocated inside the compiled kernel: on syn12's band (72k tets, 368k grid
    edges) the same kernel took 2.1-2.3 ms allocating its edge-sized arrays itself and 1.0-1.1 ms on these
    (large arrays allocated in compiled code came from fresh ``mmap`` pages, mapped and zeroed on first touch).
    ``slot`` holds -1 between calls.
    """

    def __init__(self, n_edges: int) -> None:
        self.n_edges = int(n_edges)
        self.slot = np.full(self.n_edges, -1, dtype=np.int32)
        self._buf = np.empty(0, dtype=np.int64)

    def scratch(self, n_tets: int) -> np.ndarray:
        """(14 * n_tets,) int64 scratch: crossing tets and cases (n_tets each), found edge ends (6 n_tets each)."""
        if len(self._buf) < 14 * n_tets:
            self._buf = np.empty(14 * n_tets, dtype=np.int64)
        return self._buf


@nb.njit(cache=True, nogil=True)
def _band_march_kernel(s_n, tets_bx4, edges_bx6, slot, scratch, tet_edges, table, num):  # pragma: no cover
    """Crossing tets -> crossing edges (numbered in the order found, then ranked by edge id with one sequential
    scan of ``slot``, no sort) -> faces. ``slot`` (all -1 on entry and on exit) is the only array indexed by edge
    id. On syn12's band, in one process: 1.05 ms; the version before (four edge-indexed arrays and a sort, all
    allocated inside) 2.4 ms on its first calls and 1.2 ms once the allocator had adapted. In the syn12 run the
    mesh stage went from 3.2-3.8 to 2.5-2.8 ms/step."""
    Tb = tets_bx4.shape[0]
    Nb = s_n.shape[0]
    n_edges = slot.shape[0]
    cross = scratch[:Tb]
    case = scratch[Tb:2 * Tb]
    found_a = scratch[2 * Tb:8 * Tb]
    found_b = scratch[8 * Tb:14 * Tb]
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
    local = np.full(Nb, -1, dtype=np.int64)  # 0 marks a vertex of a crossing tet, then its index in vc
    n_e = 0
    for i in range(n_c):
        t = cross[i]
        for k in range(4):
            local[tets_bx4[t, k]] = 0
        for j in range(6):
            a = tets_bx4[t, tet_edges[j, 0]]
            b = tets_bx4[t, tet_edges[j, 1]]
            if (s_n[a] < 0) != (s_n[b] < 0):
                e = edges_bx6[t, j]
                if slot[e] < 0:  # crossing edge -> its number in the order found
                    slot[e] = n_e
                    found_a[n_e] = min(a, b)
                    found_b[n_e] = max(a, b)
                    n_e += 1
    vc = np.empty(Nb, dtype=np.int64)
    n_v = 0
    for v in range(Nb):
        if local[v] == 0:
            local[v] = n_v
            vc[n_v] = v
            n_v += 1
    rank = np.empty(n_e, dtype=np.int64)  # found number -> position by increasing edge id
    ids = np.empty(n_e, dtype=np.int64)
    ea = np.empty(n_e, dtype=np.int64)
    eb = np.empty(n_e, dtype=np.int64)
    m = 0
    for e in range(n_edges):
        q = slot[e]
        if q >= 0:
            rank[q] = m
            ids[m] = e
            ea[m] = local[found_a[q]]
            eb[m] = local[found_b[q]]
            m += 1
    faces = np.empty((n_faces, 3), dtype=np.int64)
    f = 0
    for want in (1, 2):
        for i in range(n_c):
            c = case[i]
            if num[c] != want:
                continue
            t = cross[i]
            for q in range(3 * want):
                faces[f + q // 3, q % 3] = rank[slot[edges_bx6[t, table[c, q]]]]
            f += want
    for m in range(n_e):
        slot[ids[m]] = -1
    return vc[:n_v], ea, eb, faces


def band_march(s_n: np.ndarray | torch.Tensor, tets_bx4: np.ndarray, edges_bx6: np.ndarray,
               n_edges: int, work: BandMarchWork | None = None) -> BandMesh:
    """Surface topology of the zero level set of ``s_n`` on the band tets.

    Args:
        s_n: (Nb,) SDF (any unit; only signs are read, ``s < 0`` inside) of the band's vertices.
        tets_bx4: (Tb, 4) int64 band tets as indices into ``s_n``, positively oriented, vertex order of the grid
            (indices increasing with the grid's vertex ids, e.g. the positions in a sorted id list).
        edges_bx6: (Tb, 6) int64 ids in ``[0, n_edges)`` of each tet's edges in ``TET_EDGES_6x2`` order
            (:attr:`TetGrid.tet_edges_tx6` of the band tets).
        n_edges: number of edges of the grid.
        work: buffers to reuse across calls on the same grid (:class:`BandMarchWork` of ``n_edges``); fresh ones
            when None.

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
    if work is None:
        work = BandMarchWork(n_edges)
    elif work.n_edges != int(n_edges):
        raise ValueError(f"band_march: the work buffers are for {work.n_edges} edges, this grid has {n_edges}; "
                         "make a BandMarchWork(n_edges) per grid")
    vc, ea, eb, faces = _band_march_kernel(np.ascontiguousarray(s), tets, edges, work.slot,
                                           work.scratch(len(tets)), _TET_EDGES, _TABLE, _NUM)
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


def surface_points(verts_cx3: torch.Tensor, sdf_c: torch.Tensor, edge_a_m: np.ndarray,
                   edge_b_m: np.ndarray) -> torch.Tensor:
    """:func:`interpolate_surface` (same arguments, same values up to rounding) as one compiled pass forward and one
    backward, for float32 CPU tensors: about 10 torch ops and their backward on every surface vertex replaced
    (syn12: 14k surface vertices a step). The SDF's unit does not matter (the formula is scale-invariant). Other
    dtypes or devices take :func:`interpolate_surface`."""
    if verts_cx3.dtype != torch.float32 or sdf_c.dtype != torch.float32 or verts_cx3.device.type != "cpu":
        return interpolate_surface(verts_cx3, sdf_c, edge_a_m, edge_b_m)
    return _SurfacePoints.apply(verts_cx3, sdf_c, np.ascontiguousarray(edge_a_m, dtype=np.int64),
                                np.ascontiguousarray(edge_b_m, dtype=np.int64))


class _SurfacePoints(torch.autograd.Function):
    """v = (v_a s_b - v_b s_a) / (s_b - s_a) per crossing edge; backward: dv/dv_a = s_b / D, dv/dv_b = -s_a / D,
    dv/ds_a = (v - v_b) / D, dv/ds_b = (v_a - v) / D with D = s_b - s_a."""

    @staticmethod
    def forward(ctx, verts_cx3, sdf_c, ea, eb):  # noqa: D102
        V = verts_cx3.detach().numpy()
        S = sdf_c.detach().numpy()
        mv = _surface_points_fwd(V, S, ea, eb)
        ctx.save_for_backward(verts_cx3.detach(), sdf_c.detach(), torch.from_numpy(mv))
        ctx.ea, ctx.eb = ea, eb
        return torch.from_numpy(mv)

    @staticmethod
    def backward(ctx, g_mx3):  # noqa: D102
        V, S, mv = ctx.saved_tensors
        gv, gs = _surface_points_bwd(V.numpy(), S.numpy(), mv.numpy(), ctx.ea, ctx.eb,
                                     np.ascontiguousarray(g_mx3.detach().numpy(), dtype=np.float32))
        return torch.from_numpy(gv), torch.from_numpy(gs), None, None


@nb.njit(cache=True, nogil=True)
def _surface_points_fwd(V, S, ea, eb):  # pragma: no cover - compiled
    M = ea.shape[0]
    out = np.empty((M, 3), dtype=np.float32)
    for m in range(M):
        a = ea[m]
        b = eb[m]
        sa = S[a]
        sb = S[b]
        d = sb - sa
        for k in range(3):
            out[m, k] = (V[a, k] * sb - V[b, k] * sa) / d
    return out


@nb.njit(cache=True, nogil=True)
def _surface_points_bwd(V, S, mv, ea, eb, g):  # pragma: no cover - compiled
    C = V.shape[0]
    gv = np.zeros((C, 3), dtype=np.float64)
    gs = np.zeros(C, dtype=np.float64)
    for m in range(ea.shape[0]):
        if g[m, 0] == 0.0 and g[m, 1] == 0.0 and g[m, 2] == 0.0:
            continue
        a = ea[m]
        b = eb[m]
        sa = np.float64(S[a])
        sb = np.float64(S[b])
        d = sb - sa
        for k in range(3):
            gk = np.float64(g[m, k])
            gv[a, k] += gk * sb / d
            gv[b, k] -= gk * sa / d
            gs[a] += gk * (np.float64(mv[m, k]) - V[b, k]) / d
            gs[b] += gk * (V[a, k] - np.float64(mv[m, k])) / d
    return gv.astype(np.float32), gs.astype(np.float32)


__all__ = ["BandMarchWork", "BandMesh", "band_march", "interpolate_surface", "surface_points"]
