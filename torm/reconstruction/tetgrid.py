"""Regular tetrahedral grid (Kuhn/Freudenthal split) over an axis-aligned box, with caching.

Each grid cell (a small box) is split into 6 tetrahedra that all share the cell's main diagonal
(corner (0,0,0) -> corner (1,1,1)); because every cell uses the same diagonal direction, the split
is conforming (neighbouring cells agree on the triangulation of their shared faces). Every tet is
positively oriented: ``det([v1 - v0, v2 - v0, v3 - v0]) > 0``.

Vertex layout: the grid has ``n_cells = (nx, ny, nz)`` cells and ``(nx+1)*(ny+1)*(nz+1)`` vertices;
vertex ``(i, j, k)`` has index ``(i * (ny + 1) + j) * (nz + 1) + k`` and position
``bounds[0] + (i, j, k) * cell_size`` (metres), i.e. ``verts_vx3.reshape(nx+1, ny+1, nz+1, 3)``
is the grid in ``ij`` indexing.

Grids are cached in memory (LRU, keyed by the rounded bounds and the per-axis cell counts) and on
disk as ``.npz`` files in ``$TORM_CACHE_DIR/tetgrids`` (or ``~/.cache/torm/tetgrids``); a corrupt or
mismatching cache file is rebuilt and overwritten, never trusted.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from itertools import permutations
from pathlib import Path

import numpy as np
import torch

from torm.errors import ReconstructionError

log = logging.getLogger(__name__)

#: Local (di, dj, dk) offsets of the 8 cube corners; corner c has bits (c>>2 & 1, c>>1 & 1, c & 1).
_CORNERS_8x3 = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=np.int64)

#: Bump when the on-disk layout or the tet ordering changes (invalidates old cache files).
_CACHE_VERSION = 1
_MEM_CACHE_SIZE = 4
_mem_cache: OrderedDict[tuple, TetGrid] = OrderedDict()
_mem_lock = threading.Lock()

#: The 6 local edges of a tet as pairs of local vertex indices (used by edges and marching tets).
TET_EDGES_6x2 = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)


def _kuhn_templates() -> np.ndarray:
    """(6, 4) local corner indices of the 6 Kuhn tets of a unit cube, each positively oriented.

    Tet for the axis permutation (p0, p1, p2): corners 000, e_p0, e_p0 + e_p1, 111. Odd
    permutations come out negatively oriented and get their last two vertices swapped.
    """
    out = []
    for perm in permutations(range(3)):
        path = [np.zeros(3, dtype=np.int64)]
        for axis in perm:
            nxt = path[-1].copy()
            nxt[axis] = 1
            path.append(nxt)
        ids = [int(p[0] * 4 + p[1] * 2 + p[2]) for p in path]
        pts = _CORNERS_8x3[ids].astype(np.float64)
        if np.linalg.det(pts[1:] - pts[0]) < 0:
            ids[2], ids[3] = ids[3], ids[2]
        out.append(ids)
    return np.array(out, dtype=np.int64)


_TEMPLATES_6x4 = _kuhn_templates()
#: Public names: the 8 cube-corner offsets and the 6 Kuhn tets of a cell as corner indices (sparse grids use them).
CUBE_CORNERS_8x3 = _CORNERS_8x3
KUHN_TETS_6x4 = _TEMPLATES_6x4


@dataclass(frozen=True, eq=False)
class TetGrid:
    """A conforming tetrahedral grid over a box.

    Attributes:
        verts_vx3: (V, 3) float32 vertex positions in metres (world frame), CPU unless moved with :meth:`to`.
        tets_tx4: (T, 4) int64 vertex indices, every tet positively oriented.
        res: (3,) tuple of cells per axis ``(nx, ny, nz)``.
        bounds: (2, 3) float64 ``[min, max]`` corners in metres.
        cell_size: (3,) float64 cell edge lengths per axis in metres.
    """

    verts_vx3: torch.Tensor
    tets_tx4: torch.Tensor
    res: tuple[int, int, int]
    bounds: np.ndarray
    cell_size: np.ndarray

    @property
    def n_verts(self) -> int:
        return int(self.verts_vx3.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets_tx4.shape[0])

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """Vertices per axis ``(nx + 1, ny + 1, nz + 1)``; ``verts_vx3.reshape(*grid_shape, 3)`` is the lattice."""
        return (self.res[0] + 1, self.res[1] + 1, self.res[2] + 1)

    @property
    def device(self) -> torch.device:
        return self.verts_vx3.device

    @cached_property
    def edges_ex2(self) -> torch.Tensor:
        """(E, 2) int64 unique tet edges ``(a, b)`` with ``a < b``, sorted by ``a * V + b``; computed once.

        In a Kuhn grid every edge joins lattice point ``p`` to ``p + d`` with ``d`` in ``{0, 1}^3 \\ {0}``
        (3 axis edges, 3 face diagonals, 1 main diagonal), so the list is generated directly from the
        lattice instead of deduplicating the ``6 T`` tet edges.
        """
        return torch.from_numpy(kuhn_edges(self.res)).to(self.tets_tx4.device)

    @cached_property
    def tet_edges_tx6(self) -> torch.Tensor:
        """(T, 6) int64 index into :attr:`edges_ex2` of each tet's 6 edges, in the order of ``TET_EDGES_6x2``;
        computed once (lets :func:`torm.reconstruction.marching_tets.marching_tets` skip its sort)."""
        e = self.edges_ex2
        n_v = self.n_verts
        keys = e[:, 0] * n_v + e[:, 1]
        te = self.tets_tx4.long()[:, torch.as_tensor(TET_EDGES_6x2, device=e.device)]  # (T, 6, 2)
        q = torch.minimum(te[..., 0], te[..., 1]) * n_v + torch.maximum(te[..., 0], te[..., 1])
        return torch.searchsorted(keys, q.reshape(-1)).reshape(-1, 6)

    def to(self, device: torch.device | str) -> TetGrid:
        """A copy with the tensors on ``device`` (the same object when already there)."""
        device = torch.device(device)
        if self.verts_vx3.device == device:
            return self
        return TetGrid(self.verts_vx3.to(device), self.tets_tx4.to(device), self.res, self.bounds, self.cell_size)

    def tet_volumes_t(self) -> torch.Tensor:
        """(T,) signed tet volumes in m^3 (all positive for a freshly built grid)."""
        v = self.verts_vx3.double()[self.tets_tx4]
        return torch.linalg.det(v[:, 1:] - v[:, :1]) / 6.0


def kuhn_edges(res: tuple[int, int, int]) -> np.ndarray:
    """(E, 2) int64 unique edges of the Kuhn grid with ``res`` cells per axis, ``a < b``, sorted by ``(a, b)``."""
    nx, ny, nz = res
    gi, gj, gk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    out = []
    for d in _CORNERS_8x3[1:]:
        ok = (gi + d[0] <= nx) & (gj + d[1] <= ny) & (gk + d[2] <= nz)
        i, j, k = gi[ok], gj[ok], gk[ok]
        a = (i * (ny + 1) + j) * (nz + 1) + k
        b = ((i + d[0]) * (ny + 1) + j + d[1]) * (nz + 1) + k + d[2]
        out.append(np.stack([a, b], axis=1))
    e = np.concatenate(out).astype(np.int64)
    n_v = (nx + 1) * (ny + 1) * (nz + 1)
    return e[np.argsort(e[:, 0] * n_v + e[:, 1], kind="stable")]


def cells_per_axis(bounds_2x3: np.ndarray, res: int | Sequence[int]) -> tuple[int, int, int]:
    """Cells per axis for ``res``.

    An int ``res`` is the number of cells along the box's longest axis; the other axes get
    ``max(1, round(res * extent / longest_extent))`` cells, so cells are close to cubes. A sequence
    of three ints is taken as the per-axis counts ``(nx, ny, nz)`` directly.
    """
    b = np.asarray(bounds_2x3, dtype=np.float64)
    ext = b[1] - b[0]
    if isinstance(res, (int, np.integer)):
        if res < 1:
            raise ReconstructionError(f"tet grid res must be >= 1 cell, got {res}")
        n = np.maximum(1, np.round(int(res) * ext / ext.max())).astype(int)
        return int(n[0]), int(n[1]), int(n[2])
    r = tuple(int(x) for x in res)
    if len(r) != 3 or min(r) < 1:
        raise ReconstructionError(f"tet grid res must be an int or three ints >= 1 (nx, ny, nz), got {res!r}")
    return r  # type: ignore[return-value]


def _build_arrays(bounds: np.ndarray, n: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float32 and tets (T, 4) int64 of the Kuhn grid with ``n`` cells per axis."""
    nx, ny, nz = n
    cell = (bounds[1] - bounds[0]) / np.asarray(n, dtype=np.float64)
    ii, jj, kk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    ijk = np.stack([ii, jj, kk], axis=-1).reshape(-1, 3)
    verts = (bounds[0] + ijk * cell).astype(np.float32)
    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    base = ((ci * (ny + 1) + cj) * (nz + 1) + ck).reshape(-1)  # (C,) index of each cell's 000 corner
    corner_off = (_CORNERS_8x3[:, 0] * (ny + 1) + _CORNERS_8x3[:, 1]) * (nz + 1) + _CORNERS_8x3[:, 2]  # (8,)
    tet_off = corner_off[_TEMPLATES_6x4]  # (6, 4)
    tets = (base[:, None, None] + tet_off[None]).reshape(-1, 4)
    return verts, tets.astype(np.int64)


def _cache_dir() -> Path:
    root = os.environ.get("TORM_CACHE_DIR")
    return (Path(root) / "tetgrids") if root else Path.home() / ".cache" / "torm" / "tetgrids"


def _cache_key(bounds: np.ndarray, n: tuple[int, int, int]) -> tuple:
    return (tuple(np.round(bounds.reshape(-1), 6).tolist()), n)


def _disk_path(key: tuple) -> Path:
    h = hashlib.sha1(repr((key, _CACHE_VERSION)).encode()).hexdigest()[:16]
    return _cache_dir() / f"kuhn_{key[1][0]}x{key[1][1]}x{key[1][2]}_{h}.npz"


def _load_disk(path: Path, bounds: np.ndarray, n: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            verts = np.asarray(z["verts"], dtype=np.float32)
            tets = np.asarray(z["tets"]).astype(np.int64)
            meta = np.asarray(z["meta"], dtype=np.float64)
        n_v = (n[0] + 1) * (n[1] + 1) * (n[2] + 1)
        ok = (
            verts.shape == (n_v, 3)
            and tets.shape == (6 * n[0] * n[1] * n[2], 4)
            and meta.shape == (10,)
            and int(meta[0]) == _CACHE_VERSION
            and np.allclose(meta[1:7], bounds.reshape(-1), atol=1e-6)
            and tuple(int(x) for x in meta[7:10]) == n
            and tets.min() >= 0
            and tets.max() < n_v
        )
        if ok:
            return verts, tets
        log.warning("tet grid cache file %s does not match the request; rebuilding it", path)
    except Exception as exc:  # noqa: BLE001 - any unreadable cache file is rebuilt
        log.warning("tet grid cache file %s is unreadable (%s); rebuilding it", path, exc)
    return None


def _save_disk(path: Path, verts: np.ndarray, tets: np.ndarray, bounds: np.ndarray, n: tuple[int, int, int]) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = np.concatenate([[_CACHE_VERSION], bounds.reshape(-1), n]).astype(np.float64)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, verts=verts, tets=tets.astype(np.int32), meta=meta)
        os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the complete new one
    except OSError as exc:
        log.warning("could not write the tet grid cache %s (%s); continuing without it", path, exc)


def build_tet_grid(bounds_2x3: np.ndarray | Sequence[Sequence[float]], res: int | Sequence[int],
                   *, use_cache: bool = True) -> TetGrid:
    """Build (or fetch from cache) the Kuhn tet grid over ``bounds_2x3``.

    Args:
        bounds_2x3: ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in metres, max > min on every axis.
        res: cells along the longest axis (int), or per-axis cell counts ``(nx, ny, nz)``;
            see :func:`cells_per_axis`.
        use_cache: look up / store the grid in the in-memory LRU and the on-disk ``.npz`` cache.

    Returns:
        The :class:`TetGrid` (CPU tensors). Cached grids are shared objects: do not modify their tensors
        in place.
    """
    b = np.asarray(bounds_2x3, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)) or not np.all(b[1] > b[0]):
        raise ReconstructionError(
            f"tet grid bounds must be finite [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {b.tolist()}"
        )
    n = cells_per_axis(b, res)
    if 6 * n[0] * n[1] * n[2] > 2**31 - 1:
        raise ReconstructionError(f"tet grid {n} is too large; lower the resolution")
    key = _cache_key(b, n)
    if use_cache:
        with _mem_lock:
            if key in _mem_cache:
                _mem_cache.move_to_end(key)
                return _mem_cache[key]
    arrays = _load_disk(_disk_path(key), b, n) if use_cache else None
    if arrays is None:
        arrays = _build_arrays(b, n)
        if use_cache:
            _save_disk(_disk_path(key), arrays[0], arrays[1], b, n)
    verts, tets = arrays
    grid = TetGrid(
        verts_vx3=torch.from_numpy(verts),
        tets_tx4=torch.from_numpy(tets),
        res=n,
        bounds=b.copy(),
        cell_size=(b[1] - b[0]) / np.asarray(n, dtype=np.float64),
    )
    if use_cache:
        with _mem_lock:
            _mem_cache[key] = grid
            _mem_cache.move_to_end(key)
            while len(_mem_cache) > _MEM_CACHE_SIZE:
                _mem_cache.popitem(last=False)
    return grid


def clear_tet_grid_cache(disk: bool = False) -> None:
    """Empty the in-memory LRU (and, with ``disk=True``, delete the on-disk cache files)."""
    with _mem_lock:
        _mem_cache.clear()
    if disk:
        d = _cache_dir()
        if d.is_dir():
            for p in d.glob("kuhn_*.npz"):
                p.unlink(missing_ok=True)
