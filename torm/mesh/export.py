"""Write meshes (PLY, OBJ, GLB, STL via trimesh) and point clouds with normals (binary PLY)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torm.errors import ReconstructionError
from torm.types import ObjectPointCloud, TriMesh

MESH_FORMATS = ("ply", "obj", "glb", "stl")


def write_mesh(mesh: TriMesh, path: str | Path) -> Path:
    """Write ``mesh`` to ``path``; the format follows the suffix (``.ply``, ``.obj``, ``.glb``, ``.stl``).

    Vertices are written as-is (metres, world frame), faces with their winding; parent folders are
    created. Returns the path.
    """
    p = Path(path)
    fmt = p.suffix.lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ReconstructionError(f"cannot write a mesh as {p.suffix!r}; use one of {', '.join(MESH_FORMATS)}")
    p.parent.mkdir(parents=True, exist_ok=True)
    mesh.to_trimesh().export(p, file_type=fmt)
    return p


def write_point_cloud(cloud: ObjectPointCloud | np.ndarray, path: str | Path,
                      normals_nx3: np.ndarray | None = None) -> Path:
    """Write points (and normals) as a binary little-endian PLY (float32 x y z [nx ny nz]).

    ``cloud`` is an :class:`ObjectPointCloud` (its normals are written) or an (N, 3) array with
    optional ``normals_nx3``. Returns the path.
    """
    if isinstance(cloud, ObjectPointCloud):
        pts, nrm = cloud.points_nx3, cloud.normals_nx3
    else:
        pts, nrm = np.asarray(cloud, dtype=np.float64), normals_nx3
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if nrm is not None:
        nrm = np.asarray(nrm, dtype=np.float64).reshape(-1, 3)
        if nrm.shape != pts.shape:
            raise ReconstructionError(f"point cloud normals {nrm.shape} do not match the points {pts.shape}")
    p = Path(path)
    if p.suffix.lower() != ".ply":
        raise ReconstructionError(f"point clouds are written as .ply, got {p.suffix!r}")
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if nrm is not None else [])
    data = np.empty(len(pts), dtype=[(n, "<f4") for n in names])
    for i, n in enumerate("xyz"):
        data[n] = pts[:, i]
    if nrm is not None:
        for i, n in enumerate(("nx", "ny", "nz")):
            data[n] = nrm[:, i]
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {len(pts)}\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(data.tobytes())
    return p
