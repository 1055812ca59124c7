"""Adaptive (coarse-to-fine) tet grid: a signed field evaluated only near its zero level set (the narrow-band hull).

Level 0 is the whole Kuhn lattice over the box (``base_res`` cells along the longest axis, see
:func:`torm.reconstruction.tetgrid.cells_per_axis`); the field is evaluated at all its vertices. Each
further level keeps the cells whose corner values change sign or lie within ``band`` cell diagonals of
zero, splits every kept cell into 8 and evaluates the field only at the new corners (corners shared
with the coarser level keep their values). After ``levels`` splits the cells are ``2**levels`` times
smaller than at level 0, and only cells with a sign change are kept.

Why this is safe: the projective hull SDF is a lateral distance per view, so it changes by about one
metre per metre near its surface (Lipschitz ~1); a cell whose corners all lie farther from zero than
its diagonal cannot hold the surface. Where the field jumps (a view's image border, where that view
stops voting), a closure pass adds every neighbour across a cell face whose four corners change sign
until there is none, so the extracted surface is always closed.

Tets: every band cell is split into the 6 Kuhn tets of the regular lattice (the same split as
:func:`torm.reconstruction.tetgrid.build_tet_grid`), so neighbouring cells share faces and marching
tets yields a watertight surface. Lattice vertex ``(i, j, k)`` of a lattice with ``n = (nx, ny, nz)``
cells has key ``(i * (ny + 1) + j) * (nz + 1) + k`` and position ``bounds[0] + (i, j, k) * cell_size``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from torm.errors import ReconstructionError
from torm.reconstruction.marching_tets import marching_tets
from torm.reconstruction.tetgrid import CUBE_CORNERS_8x3, KUHN_TETS_6x4, cells_per_axis
from torm.reconstruction.visual_hull import ProjectiveSDF, box_sdf
from torm.types import TriMesh

log = logging.getLogger(__name__)

#: For each cube face (axis a, side s) as index 2 * a + s: the 4 corner indices on it.
_FACE_CORNERS_6x4 = np.array([np.flatnonzero(CUBE_CORNERS_8x3[:, a] == s) for a in range(3) for s in (0, 1)])


@dataclass(frozen=True, eq=False)
class BandGrid:
    """The finest level of a narrow band: a sparse, conforming tet grid with the field at its vertices.

    Attributes:
        verts_vx3: (N, 3) float32 vertex positions (m, world frame).
        tets_tx4: (T, 4) int64 positively oriented tets (6 per cell).
        sdf_v: (N, C) float64 values of the C fields at the vertices (m, negative inside).
        cells_cx3: (C, 3) int64 lattice coordinates of the band cells.
        res: cells per axis of the finest lattice.
        bounds: (2, 3) box (m).
        cell_size: (3,) cell edges (m) at the finest level.
        stats: per level ``cells`` kept, ``evaluated`` field evaluations, ``s`` seconds; ``closure_cells``.
    """

    verts_vx3: torch.Tensor
    tets_tx4: torch.Tensor
    sdf_v: np.ndarray
    cells_cx3: np.ndarray
    res: tuple[int, int, int]
    bounds: np.ndarray
    cell_size: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def n_verts(self) -> int:
        return int(self.verts_vx3.shape[0])


def _vkeys(ijk: np.ndarray, n: np.ndarray) -> np.ndarray:
    return (ijk[..., 0] * (n[1] + 1) + ijk[..., 1]) * (n[2] + 1) + ijk[..., 2]


def _decode(keys: np.ndarray, n: np.ndarray) -> np.ndarray:
    k = keys % (n[2] + 1)
    rest = keys // (n[2] + 1)
    return np.stack([rest // (n[1] + 1), rest % (n[1] + 1), k], axis=-1)


def _ckeys(cells: np.ndarray, n: np.ndarray) -> np.ndarray:
    return (cells[:, 0] * n[1] + cells[:, 1]) * n[2] + cells[:, 2]


class _Store:
    """Field values (M, C) at lattice vertices, found by key through a dense slot map over the lattice.

    ``slot[key]`` is the row of the vertex in ``vals`` or -1; lookups and inserts are O(1) per key (no sort),
    for 4 bytes per lattice vertex (8 MB at 192 cells over the sim box).
    """

    def __init__(self, n_total: int, keys: np.ndarray, vals: np.ndarray) -> None:
        self.slot = np.full(int(n_total), -1, dtype=np.int32 if n_total < 2**31 else np.int64)
        self.slot[keys] = np.arange(len(keys))
        self.vals = vals

    def get(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values keys.shape + (C,), found keys.shape) for ``keys`` of any shape (missing keys: NaN)."""
        s = self.slot[keys]
        found = s >= 0
        out = self.vals[np.where(found, s, 0)] if len(self.vals) else np.zeros(keys.shape + self.vals.shape[1:])
        out[~found] = np.nan
        return out, found

    def add(self, keys: np.ndarray, vals: np.ndarray) -> None:
        if len(keys):
            self.slot[keys] = len(self.vals) + np.arange(len(keys))
            self.vals = np.concatenate([self.vals, vals])


def _unique_keys(keys: np.ndarray, n_total: int) -> np.ndarray:
    """Sorted unique lattice keys (a dense mark-and-scan: linear, no sort)."""
    mark = np.zeros(int(n_total), dtype=bool)
    mark[keys.ravel()] = True
    return np.flatnonzero(mark)


def _n_verts(n: np.ndarray) -> int:
    return int(np.prod(n + 1))


def build_band(
    sdf_fn: Callable[[np.ndarray], np.ndarray],
    bounds_2x3: np.ndarray,
    base_res: int,
    levels: int,
    *,
    band: float = 0.4,
    max_closure_iters: int = 64,
    max_cells: int | None = None,
) -> BandGrid:
    """Evaluate ``sdf_fn`` coarse-to-fine in a narrow band around its zero set (see the module docstring).

    Args:
        sdf_fn: maps (M, 3) float64 world points (m) to (M,) or (M, C) float64 signed values (m, negative
            inside): C fields at once, refined where any of them is near zero. Every field must be positive
            on the box boundary (e.g. intersected with the box shrunk by a margin).
        bounds_2x3: the box (m).
        base_res: cells along the longest box axis at level 0.
        levels: number of 2x refinements (0 = a dense grid at ``base_res``, only sign-change cells kept).
        band: cells within ``band`` cell diagonals of zero are refined at each level.
        max_closure_iters: closure passes at the finest level (each adds the missing face neighbours).
        max_cells: refine no further once the next level would hold more surface cells than this (the
            cost of the band, of marching tets and of everything downstream grows with them); None = no cap.

    Returns:
        :class:`BandGrid` of the finest level (it may hold no cell when the field has no zero crossing).
    """
    b = np.asarray(bounds_2x3, dtype=np.float64)
    if levels < 0 or band <= 0:
        raise ReconstructionError(f"narrow band: need levels >= 0 and band > 0, got {levels}, {band}")
    n = np.asarray(cells_per_axis(b, base_res), dtype=np.int64)
    if np.prod((n << levels).astype(np.float64) + 1) > 2**62:
        raise ReconstructionError(f"narrow band: {base_res} cells x 2^{levels} is too fine; lower the levels")
    stats: dict = {"levels": []}

    def positions(ijk: np.ndarray, nn: np.ndarray) -> np.ndarray:
        return b[0] + ijk * ((b[1] - b[0]) / nn)

    t = time.perf_counter()
    gi, gj, gk = np.meshgrid(*(np.arange(x + 1) for x in n), indexing="ij")
    ijk = np.stack([gi, gj, gk], axis=-1).reshape(-1, 3)
    def evaluate(pts: np.ndarray) -> np.ndarray:
        v = np.asarray(sdf_fn(pts), dtype=np.float64)
        return v.reshape(len(pts), -1)

    store = _Store(_n_verts(n), _vkeys(ijk, n), evaluate(positions(ijk, n)))
    ci, cj, ck = np.meshgrid(*(np.arange(x) for x in n), indexing="ij")
    cells = np.stack([ci, cj, ck], axis=-1).reshape(-1, 3)
    evaluated = len(ijk)
    for level in range(levels + 1):
        cell = (b[1] - b[0]) / n
        vals, _ = store.get(_vkeys(cells[:, None, :] + CUBE_CORNERS_8x3[None], n))
        neg = vals < 0  # (C, 8, fields)
        mixed = (neg.any(1) & ~neg.all(1)).any(-1)
        # a surface crossing C cells crosses about 4 C cells of half the size: stop before max_cells
        last = level == levels or (max_cells is not None and 4 * int(mixed.sum()) > max_cells)
        keep = mixed if last else mixed | (np.abs(vals).min((1, 2)) < band * float(np.linalg.norm(cell)))
        cells = cells[keep]
        stats["levels"].append({"res": n.tolist(), "cells": int(len(cells)), "evaluated": int(evaluated),
                                "s": time.perf_counter() - t})
        if last or len(cells) == 0:
            stats["levels_used"] = level
            break
        t = time.perf_counter()
        cells = (cells[:, None, :] * 2 + CUBE_CORNERS_8x3[None]).reshape(-1, 3)
        n_old, n = n, n * 2
        keys = _unique_keys(_vkeys(cells[:, None, :] + CUBE_CORNERS_8x3[None], n), _n_verts(n))
        ijk = _decode(keys, n)
        even = np.all(ijk % 2 == 0, axis=1)
        new_vals = np.empty((len(keys), store.vals.shape[1]))
        new_vals[even] = store.get(_vkeys(ijk[even] // 2, n_old))[0]
        new_vals[~even] = evaluate(positions(ijk[~even], n))
        evaluated = int((~even).sum())
        store = _Store(_n_verts(n), keys, new_vals)
    if len(cells) == 0:  # no surface: report the finest lattice anyway
        n = np.asarray(cells_per_axis(b, base_res), dtype=np.int64) << levels
        stats["levels_used"] = levels
    # closure: a sign change across a face means the neighbour holds surface too. Only the cells added last
    # can have neighbours still missing (the set only grows), so each pass checks that frontier.
    t = time.perf_counter()
    added = 0
    step = np.zeros((6, 3), dtype=np.int64)
    step[np.arange(6), np.arange(6) // 2] = 2 * (np.arange(6) % 2) - 1
    frontier = cells
    for _ in range(max_closure_iters):
        if len(frontier) == 0:
            break
        vals, _ = store.get(_vkeys(frontier[:, None, :] + CUBE_CORNERS_8x3[None], n))
        fneg = (vals < 0)[:, _FACE_CORNERS_6x4]  # (cells, 6, 4, fields)
        fmixed = (fneg.any(2) & ~fneg.all(2)).any(-1)
        ci, fi = np.nonzero(fmixed)
        nb = frontier[ci] + step[fi]
        nb = nb[np.all((nb >= 0) & (nb < n), axis=1)]
        have = np.zeros(int(np.prod(n)), dtype=bool)
        have[_ckeys(cells, n)] = True
        nbk = _unique_keys(_ckeys(nb, n), int(np.prod(n)))
        nbk = nbk[~have[nbk]]
        if len(nbk) == 0:
            break
        frontier = np.stack([nbk // (n[1] * n[2]), (nbk // n[2]) % n[1], nbk % n[2]], axis=1)
        ck = _unique_keys(_vkeys(frontier[:, None, :] + CUBE_CORNERS_8x3[None], n), _n_verts(n))
        _, found = store.get(ck)
        miss = ck[~found]
        store.add(miss, evaluate(positions(_decode(miss, n), n)))
        cells = np.concatenate([cells, frontier])
        added += len(frontier)
    else:
        log.warning("narrow band: the closure did not converge in %d passes; the surface may be open",
                    max_closure_iters)
    stats["closure_cells"] = int(added)
    stats["closure_s"] = time.perf_counter() - t
    cell = (b[1] - b[0]) / n
    ck = _vkeys(cells[:, None, :] + CUBE_CORNERS_8x3[None], n)  # (C, 8)
    keys = _unique_keys(ck, _n_verts(n))
    index = np.full(_n_verts(n), -1, dtype=np.int64)
    index[keys] = np.arange(len(keys))
    inverse = index[ck]
    tets = inverse[:, KUHN_TETS_6x4].reshape(-1, 4)
    sdf_v = store.get(keys)[0]
    verts = positions(_decode(keys, n), n).astype(np.float32)
    return BandGrid(verts_vx3=torch.from_numpy(verts), tets_tx4=torch.from_numpy(tets.astype(np.int64)),
                    sdf_v=sdf_v, cells_cx3=cells, res=(int(n[0]), int(n[1]), int(n[2])), bounds=b,
                    cell_size=cell, stats=stats)


def hull_field(field: ProjectiveSDF, bounds_2x3: np.ndarray, margin: float, table_z: float | None,
               tolerances: tuple[int, ...] | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """The visual-hull SDF (m) as a function of points: ``field`` intersected with the table half-space
    (when ``table_z`` is given) and the box shrunk by ``margin`` (so the box boundary is outside); points no
    view sees are outside (+ the box size). With ``tolerances`` (view counts, see
    :meth:`ProjectiveSDF.values`) it returns one column per tolerance."""
    b = np.asarray(bounds_2x3, dtype=np.float64)
    unseen = float((b[1] - b[0]).max())

    def fn(points_mx3: np.ndarray) -> np.ndarray:
        if tolerances is None:
            val, n_seen = field(points_mx3)
            val = val[:, None]
        else:
            val, n_seen = field.values(points_mx3, tolerances)
        val[n_seen == 0] = unseen
        if table_z is not None:
            val = np.maximum(val, float(table_z) - points_mx3[:, 2:3])
        return np.maximum(val, (box_sdf(points_mx3, b) + margin)[:, None])

    return fn


def narrow_band_hull(field: ProjectiveSDF, bounds_2x3: np.ndarray, base_res: int, levels: int, *,
                     table_z: float | None = None, band: float = 0.4, tolerances: tuple[int, ...] | None = None,
                     max_cells: int | None = None) -> tuple[list[TriMesh], BandGrid]:
    """The projective hull's surface extracted on a narrow-band tet grid (marching tets).

    Args:
        field: the silhouettes' projective SDF (:class:`ProjectiveSDF`).
        bounds_2x3: the reconstruction box (m); its boundary is held outside by half a finest cell.
        base_res, levels, band: see :func:`build_band`.
        table_z: table height (m); nothing below it. None: no table.
        tolerances: several vote tolerances (views) evaluated in the same pass, one mesh each; None = the
            field's own tolerance.
        max_cells: see :func:`build_band` (the box margin is half a cell of the finest possible level, so it
            holds at whichever level the band stops).

    Returns:
        (closed outward-wound meshes in metres, one per tolerance, the band grid with ``stats``).
    """
    b = np.asarray(bounds_2x3, dtype=np.float64)
    n = np.asarray(cells_per_axis(b, base_res)) << levels
    margin = 0.5 * float(((b[1] - b[0]) / n).min())
    grid = build_band(hull_field(field, b, margin, table_z, tolerances), b, base_res, levels, band=band,
                      max_cells=max_cells)
    t = time.perf_counter()
    meshes = []
    with torch.no_grad():
        for c in range(grid.sdf_v.shape[1]):
            mv, mf = marching_tets(grid.verts_vx3, grid.tets_tx4, torch.from_numpy(grid.sdf_v[:, c].astype(np.float32)))
            meshes.append(TriMesh(mv.numpy().astype(np.float64), mf.numpy()))
    grid.stats["marching_tets_s"] = time.perf_counter() - t
    return meshes, grid


__all__ = ["BandGrid", "build_band", "hull_field", "narrow_band_hull"]
