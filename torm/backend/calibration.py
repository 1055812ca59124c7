"""Declared calibration: what a lab states about its cell, the only scene knowledge the decision loop gets
besides its own sensors.

A real cell declares its table height (measured once, with a stated error) and the static fixtures bolted to it
(a rack, a tray: a model and a pose, from drawings or a measurement). The simulated backend declares the same
things from the scenario file, never from the simulator's state, so the loop sees the same kind of input on
both backends. Units: m; frames: world = robot base frame, z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ConfigError


@dataclass(frozen=True)
class FixtureDeclaration:
    """A static fixture the lab declares: its shape in its own frame and its pose in the world.

    Attributes:
        name: a label (``rack``, ``tray``, ...).
        T_world_fixture: (4, 4) pose of the fixture frame in the world (m).
        boxes: the shape as boxes ``((centre_xyz, half_extents_xyz), ...)`` in the fixture frame (m); or
        mesh_path: a mesh file (STL / OBJ / PLY, m, fixture frame) read with trimesh. Exactly one of the two.
    """

    name: str
    T_world_fixture: np.ndarray
    boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()
    mesh_path: str | None = None

    def __post_init__(self) -> None:
        T = np.asarray(self.T_world_fixture, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ConfigError(f"fixture {self.name!r}: T_world_fixture must be a finite (4, 4) rigid transform")
        if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise ConfigError(f"fixture {self.name!r}: T_world_fixture's rotation is not orthonormal")
        object.__setattr__(self, "T_world_fixture", T)
        boxes = tuple((tuple(float(v) for v in c), tuple(float(v) for v in h)) for c, h in self.boxes)
        object.__setattr__(self, "boxes", boxes)
        if bool(boxes) == (self.mesh_path is not None):
            raise ConfigError(f"fixture {self.name!r}: declare its shape as boxes or as mesh_path, exactly one")
        for c, h in boxes:
            if len(c) != 3 or len(h) != 3 or min(h) <= 0:
                raise ConfigError(f"fixture {self.name!r}: a box is ((cx, cy, cz), (hx, hy, hz)) with half extents > 0 "
                                  f"(m), got {(c, h)}")
        if self.mesh_path is not None and not Path(self.mesh_path).is_file():
            raise ConfigError(f"fixture {self.name!r}: mesh_path {self.mesh_path!r} is not a file; give the path of "
                              "an STL/OBJ/PLY mesh in metres, fixture frame")

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> FixtureDeclaration:
        """From YAML: ``{name, pose: [x, y, z, yaw_deg] | 4x4, boxes: [[[cx,cy,cz],[hx,hy,hz]], ...] | mesh: path}``."""
        unknown = set(doc) - {"name", "pose", "boxes", "mesh"}
        if unknown:
            raise ConfigError(f"fixture declaration: unknown keys {sorted(unknown)}; valid: name, pose, boxes, mesh")
        pose = np.asarray(doc.get("pose", [0, 0, 0, 0]), dtype=np.float64)
        if pose.shape == (4,):
            T = np.eye(4)
            yaw = np.deg2rad(pose[3])
            T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            T[:3, 3] = pose[:3]
        elif pose.shape == (4, 4):
            T = pose
        else:
            raise ConfigError(f"fixture declaration: pose must be [x, y, z, yaw_deg] (m, deg) or a 4x4 matrix, got "
                              f"shape {pose.shape}")
        return cls(str(doc.get("name", "fixture")), T, tuple(doc.get("boxes") or ()), doc.get("mesh"))

    def surface_points(self, spacing: float = 0.004) -> np.ndarray:
        """(M, 3) points on the fixture's surface in the world frame (m), at most about ``spacing`` apart."""
        if spacing <= 0:
            raise ConfigError("surface_points: spacing must be > 0 (m)")
        if self.mesh_path is not None:
            import trimesh

            mesh = trimesh.load(self.mesh_path, force="mesh")
            n = int(np.clip(mesh.area / spacing**2, 100, 200_000))
            p, _ = trimesh.sample.sample_surface_even(mesh, n, seed=0)
        else:
            p = np.unique(np.round(np.concatenate(
                [box_surface_points(np.asarray(c), np.asarray(h), spacing) for c, h in self.boxes]), 6), axis=0)
        T = self.T_world_fixture
        return np.asarray(p, float) @ T[:3, :3].T + T[:3, 3]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready record (pose as a 4x4 list)."""
        return {"name": self.name, "T_world_fixture": self.T_world_fixture.tolist(),
                "boxes": [list(map(list, b)) for b in self.boxes], "mesh_path": self.mesh_path}


def box_surface_points(c: np.ndarray, h: np.ndarray, spacing: float) -> np.ndarray:
    """(M, 3) grid points at most ``spacing`` apart on the six faces of the box centred at ``c`` (3,) with half
    extents ``h`` (3,), in the box's frame (m)."""
    pts = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        nu = max(2, int(np.ceil(2 * h[u] / spacing)) + 1)
        nv = max(2, int(np.ceil(2 * h[v] / spacing)) + 1)
        gu, gv = np.meshgrid(np.linspace(-h[u], h[u], nu), np.linspace(-h[v], h[v], nv), indexing="ij")
        for sgn in (-1.0, 1.0):
            p = np.zeros((gu.size, 3))
            p[:, u], p[:, v], p[:, axis] = gu.ravel(), gv.ravel(), sgn * h[axis]
            pts.append(p + c)
    return np.unique(np.round(np.concatenate(pts), 6), axis=0)


@dataclass(frozen=True)
class Calibration:
    """What the cell declares to the decision loop.

    Attributes:
        table_height: z of the table top in the world (m), as measured by the lab.
        table_height_error: the stated (1-sigma) error of that measurement (m).
        source: where the numbers come from (``hardware config <path>``, ``scenario <name> declaration``).
        fixtures: the declared static fixtures.
    """

    table_height: float = 0.0
    table_height_error: float = 0.0
    source: str = ""
    fixtures: tuple[FixtureDeclaration, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if not np.isfinite(self.table_height) or not (np.isfinite(self.table_height_error)
                                                      and self.table_height_error >= 0):
            raise ConfigError("calibration: table_height must be finite and table_height_error >= 0 (m)")
        object.__setattr__(self, "fixtures", tuple(self.fixtures))

    def obstacle_points(self, spacing: float = 0.004) -> np.ndarray | None:
        """(M, 3) surface points of every declared fixture in the world (m), or None without fixtures."""
        if not self.fixtures:
            return None
        return np.concatenate([f.surface_points(spacing) for f in self.fixtures])

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready record for trial results."""
        return {"table_height_m": self.table_height, "table_height_error_m": self.table_height_error,
                "declared_by": self.source, "fixtures": [f.name for f in self.fixtures]}
