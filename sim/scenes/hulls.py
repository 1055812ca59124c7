"""Convex decomposition (CoACD) of object meshes, cached on disk and never recomputed per trial.

Cache key: SHA-256 of (vertex bytes as float64, face bytes as int64, the CoACD parameters as sorted
JSON, the installed coacd version). Lookup order:

1. ``sim/scenes/hull_cache/<name>_<key16>.npz`` shipped in the repository (so CI never runs CoACD);
2. the user cache ``$TORM_CACHE_DIR/hulls`` or ``~/.cache/torm/hulls`` (new or changed meshes).

A miss runs CoACD once and writes the result to the user cache; ``write_repo_cache=True`` (used when
regenerating the shipped cache) writes it next to this module instead. Each file stores
``n_hulls`` and ``verts_<i>`` (float64 (v, 3), m) / ``faces_<i>`` (int64 (f, 3)) per hull.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from torm.errors import SceneError

log = logging.getLogger(__name__)

REPO_CACHE_DIR = Path(__file__).resolve().parent / "hull_cache"


@dataclass(frozen=True)
class CoacdParams:
    """CoACD parameters that change the decomposition (all part of the cache key)."""

    threshold: float = 0.05  # concavity threshold (CoACD default); lower = more, smaller hulls
    max_convex_hull: int = -1  # -1 = no limit
    preprocess_mode: str = "auto"
    preprocess_resolution: int = 50
    resolution: int = 2000
    mcts_nodes: int = 20
    mcts_iterations: int = 150
    mcts_max_depth: int = 3
    merge: bool = True
    max_ch_vertex: int = 256
    seed: int = 0


def coacd_version() -> str:
    """Installed coacd version (part of the cache key); 'missing' when coacd is not installed."""
    try:
        return importlib.metadata.version("coacd")
    except importlib.metadata.PackageNotFoundError:
        return "missing"


def user_cache_dir() -> Path:
    """``$TORM_CACHE_DIR/hulls`` when set, else ``~/.cache/torm/hulls``."""
    root = os.environ.get("TORM_CACHE_DIR")
    return Path(root) / "hulls" if root else Path.home() / ".cache" / "torm" / "hulls"


def cache_key(mesh: trimesh.Trimesh, params: CoacdParams) -> str:
    """Hex SHA-256 of the mesh bytes, the CoACD parameters and the coacd version."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(json.dumps(dataclasses.asdict(params), sort_keys=True).encode())
    h.update(coacd_version().encode())
    return h.hexdigest()


def _run_coacd(mesh: trimesh.Trimesh, params: CoacdParams) -> list[trimesh.Trimesh]:
    """Run CoACD (seconds; the cup takes ~10 s on 2 cores)."""
    try:
        import coacd
    except ImportError as exc:  # pragma: no cover - coacd is a project dependency
        raise SceneError("coacd is not installed and this mesh has no cached hulls; pip install coacd") from exc
    coacd.set_log_level("error")
    cm = coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    parts = coacd.run_coacd(cm, **dataclasses.asdict(params))
    hulls = [trimesh.Trimesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)) for v, f in parts]
    if not hulls:
        raise SceneError("CoACD returned no convex hulls; check the mesh is a watertight volume")
    return hulls


def _save(path: Path, hulls: list[trimesh.Trimesh]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {"n_hulls": np.array(len(hulls))}
    for i, h in enumerate(hulls):
        arrays[f"verts_{i}"] = np.asarray(h.vertices, dtype=np.float64)
        arrays[f"faces_{i}"] = np.asarray(h.faces, dtype=np.int64)
    tmp = path.with_name(path.stem + f".tmp{os.getpid()}.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


def _load(path: Path) -> list[trimesh.Trimesh]:
    with np.load(path) as z:
        n = int(z["n_hulls"])
        return [trimesh.Trimesh(z[f"verts_{i}"], z[f"faces_{i}"], process=False) for i in range(n)]


def convex_decomposition(
    name: str, mesh: trimesh.Trimesh, params: CoacdParams | None = None, write_repo_cache: bool = False
) -> list[trimesh.Trimesh]:
    """Convex hulls (object frame, m) of ``mesh``, from the repo cache, the user cache, or CoACD (then cached)."""
    params = params or CoacdParams()
    fname = f"{name}_{cache_key(mesh, params)[:16]}.npz"
    for d in (REPO_CACHE_DIR, user_cache_dir()):
        p = d / fname
        if p.is_file():
            try:
                return _load(p)
            except (OSError, KeyError, ValueError) as exc:
                log.warning("ignoring unreadable hull cache %s (%s)", p, exc)
    log.info("CoACD: decomposing %s (not cached: %s)", name, fname)
    hulls = _run_coacd(mesh, params)
    target = (REPO_CACHE_DIR if write_repo_cache else user_cache_dir()) / fname
    try:
        _save(target, hulls)
    except OSError as exc:
        log.warning("could not write hull cache %s (%s); hulls will be recomputed next process", target, exc)
    return hulls


# ------------------------------------------------------------------------------------------------ checks
def points_inside_mesh(mesh: trimesh.Trimesh, points_nx3: np.ndarray) -> np.ndarray:
    """(N,) bool: inside the closed mesh, by the parity of ray crossings (numpy Moller-Trumbore, no rtree needed).

    The ray direction is skewed so that it almost never grazes an edge or a vertex of a mesh built on a grid.
    """
    p = np.asarray(points_nx3, dtype=np.float64).reshape(-1, 3)
    d = np.array([0.5773, 0.5774, 0.5775])
    d /= np.linalg.norm(d)
    tri = np.asarray(mesh.triangles, dtype=np.float64)  # (F, 3, 3)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)  # (F, 3)
    a = np.einsum("fi,fi->f", e1, h)
    ok = np.abs(a) > 1e-14
    v0, e1, e2, h, a = v0[ok], e1[ok], e2[ok], h[ok], a[ok]
    inv = 1.0 / a
    out = np.zeros(len(p), dtype=bool)
    for s in range(0, len(p), 256):
        q = p[s:s + 256, None, :] - v0[None]  # (B, F, 3)
        u = np.einsum("bfi,fi->bf", q, h) * inv
        qq = np.cross(q, e1[None])
        v = np.einsum("i,bfi->bf", d, qq) * inv
        t = np.einsum("fi,bfi->bf", e2, qq) * inv
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        out[s:s + 256] = (hit.sum(axis=1) % 2) == 1
    return out


def points_inside_convex(hull: trimesh.Trimesh, points_nx3: np.ndarray, tol: float = 0.0) -> np.ndarray:
    """(N,) bool: inside the convex hull of ``hull`` (every face plane, grown by ``tol`` m)."""
    ch = hull.convex_hull
    n = np.asarray(ch.face_normals)
    off = np.einsum("fi,fi->f", n, np.asarray(ch.triangles)[:, 0])
    return np.all(np.asarray(points_nx3) @ n.T <= off + tol, axis=1)


def cavity_probe_points(mesh: trimesh.Trimesh, spacing: float = 0.002, clearance: float = 0.002) -> np.ndarray:
    """(N, 3) points of the air a vessel holds: inside its convex hull, outside the glass, at least ``clearance``
    (m, checked along the 6 axis directions) from the glass and from the hull's open side; empty for solids."""
    lo, hi = mesh.bounds
    axes = [np.arange(lo[i] + clearance, hi[i] - clearance + 1e-12, spacing) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid[points_inside_convex(mesh, grid, tol=-clearance)]
    if not len(grid):
        return grid
    free = ~points_inside_mesh(mesh, grid)
    for axis in range(3):
        for sgn in (-1.0, 1.0):
            if not free.any():
                break
            shifted = grid[free].copy()
            shifted[:, axis] += sgn * clearance
            sub = np.nonzero(free)[0]
            free[sub[points_inside_mesh(mesh, shifted)]] = False
    return grid[free]


def cavity_open_fraction(mesh: trimesh.Trimesh, hulls: list[trimesh.Trimesh], spacing: float = 0.002,
                         clearance: float = 0.002) -> float:
    """Share of the vessel's cavity probes (see :func:`cavity_probe_points`) that no collision hull covers (1.0 when
    there is no cavity): how much of a vessel's inside the convex decomposition keeps open."""
    probes = cavity_probe_points(mesh, spacing, clearance)
    if not len(probes):
        return 1.0
    covered = np.zeros(len(probes), dtype=bool)
    for h in hulls:
        covered |= points_inside_convex(h, probes)
    return float(1.0 - covered.mean())
