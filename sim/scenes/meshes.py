"""Procedural, watertight meshes of the paper's objects (trimesh only; no shapely/earcut needed).

Every generator returns a ``trimesh.Trimesh`` in the object's own frame: z up, lowest point at z = 0,
footprint centred on x = y = 0 (centre of the axis-aligned bounding box). Units are metres.
Vertices are rounded to 1e-7 m so that the mesh bytes (and the hull-cache key derived from them)
are identical across machines.
"""

from __future__ import annotations

import numpy as np
import trimesh

_ROUND_DECIMALS = 7


def finalize(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre the footprint on x = y = 0, put the lowest point at z = 0, round vertices, check watertightness."""
    verts_vx3 = np.asarray(mesh.vertices, dtype=np.float64).copy()
    lo, hi = verts_vx3.min(axis=0), verts_vx3.max(axis=0)
    verts_vx3 -= np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    verts_vx3 = np.round(verts_vx3, _ROUND_DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0
    out = trimesh.Trimesh(verts_vx3, np.asarray(mesh.faces, dtype=np.int64), process=True)
    trimesh.repair.fix_normals(out)
    if not out.is_watertight or not out.is_volume:
        raise ValueError("generated mesh is not a watertight volume")
    return out


def cylinder(radius: float, height: float, sections: int = 48) -> trimesh.Trimesh:
    """Solid right circular cylinder (``sections`` = 6 gives a hexagonal prism of circumradius ``radius``)."""
    return finalize(trimesh.creation.cylinder(radius=radius, height=height, sections=sections))


def ball(radius: float, subdivisions: int = 3) -> trimesh.Trimesh:
    """Solid sphere (icosphere)."""
    return finalize(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius))


def box(extents_xyz: tuple[float, float, float]) -> trimesh.Trimesh:
    """Solid axis-aligned box with edge lengths ``extents_xyz`` (m)."""
    return finalize(trimesh.creation.box(extents=extents_xyz))


def closed_box_shell(extents_xyz: tuple[float, float, float], wall: float) -> trimesh.Trimesh:
    """Closed hollow box (a lidded container): outer box minus an inner cavity ``wall`` thinner on every side.

    The result is one watertight volume with two shells (outer normals out, cavity normals in), so its
    trimesh volume is the glass volume only.
    """
    ex = np.asarray(extents_xyz, dtype=np.float64)
    outer = trimesh.creation.box(extents=ex)
    inner = trimesh.creation.box(extents=ex - 2.0 * wall)
    inner.invert()  # cavity faces point into the cavity
    merged = trimesh.util.concatenate([outer, inner])
    out = finalize(merged)
    return out


def frustum(bottom_side: float, top_side: float, height: float) -> trimesh.Trimesh:
    """Square pyramidal frustum (bottom square ``bottom_side``, top square ``top_side``)."""
    b, t = bottom_side / 2.0, top_side / 2.0
    pts = np.array(
        [[-b, -b, 0], [b, -b, 0], [b, b, 0], [-b, b, 0], [-t, -t, height], [t, -t, height], [t, t, height],
         [-t, t, height]],
        dtype=np.float64,
    )
    return finalize(trimesh.convex.convex_hull(pts))


def rounded_box(side: float, corner_radius: float, sections: int = 2) -> trimesh.Trimesh:
    """Cube of edge ``side`` with rounded edges/corners of radius ``corner_radius`` (convex hull of 8 spheres)."""
    sphere = trimesh.creation.icosphere(subdivisions=sections, radius=corner_radius)
    c = side / 2.0 - corner_radius
    corners = np.array([[sx, sy, sz] for sx in (-c, c) for sy in (-c, c) for sz in (-c, c)])
    pts = (corners[:, None, :] + sphere.vertices[None, :, :]).reshape(-1, 3)
    return finalize(trimesh.convex.convex_hull(pts))


def open_cup(radius: float, height: float, wall: float, bottom: float, sections: int = 48) -> trimesh.Trimesh:
    """Open-top hollow cup: revolved profile with outer radius ``radius``, side ``wall`` and base ``bottom`` (m)."""
    r_in = radius - wall
    profile_px2 = np.array(
        [[0.0, 0.0], [radius, 0.0], [radius, height], [r_in, height], [r_in, bottom], [0.0, bottom]],
        dtype=np.float64,
    )
    mesh = trimesh.creation.revolve(profile_px2, sections=sections)
    return finalize(mesh)


def heart_outline(width: float, n: int = 96) -> np.ndarray:
    """Closed heart outline (n, 2), counter-clockwise, ``width`` across (m); the classic parametric heart."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    x = 16.0 * np.sin(t) ** 3
    y = 13.0 * np.cos(t) - 5.0 * np.cos(2 * t) - 2.0 * np.cos(3 * t) - np.cos(4 * t)
    pts_nx2 = np.stack([x, y], axis=1)
    pts_nx2 *= width / (x.max() - x.min())
    area2 = np.sum(pts_nx2[:, 0] * np.roll(pts_nx2[:, 1], -1) - np.roll(pts_nx2[:, 0], -1) * pts_nx2[:, 1])
    if area2 < 0:
        pts_nx2 = pts_nx2[::-1].copy()
    return pts_nx2


def extrude_star_polygon(outline_nx2: np.ndarray, height: float) -> trimesh.Trimesh:
    """Extrude a polygon that is star-shaped about its vertex mean (fan-triangulated caps) to ``height`` (m)."""
    pts = np.asarray(outline_nx2, dtype=np.float64)
    centre = pts.mean(axis=0)
    ang = np.unwrap(np.arctan2(pts[:, 1] - centre[1], pts[:, 0] - centre[0]))
    if not np.all(np.diff(ang) > 0):
        raise ValueError("outline is not star-shaped about its vertex mean; cannot fan-triangulate")
    n = len(pts)
    bottom = np.column_stack([pts, np.zeros(n)])
    top = np.column_stack([pts, np.full(n, height)])
    verts = np.vstack([bottom, top, [[*centre, 0.0]], [[*centre, height]]])
    cb, ct = 2 * n, 2 * n + 1
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces.append([cb, j, i])  # bottom cap, normal -z
        faces.append([ct, n + i, n + j])  # top cap, normal +z
        faces.append([i, j, n + j])  # side
        faces.append([i, n + j, n + i])
    return finalize(trimesh.Trimesh(verts, np.asarray(faces, dtype=np.int64), process=True))


def heart(width: float, thickness: float) -> trimesh.Trimesh:
    """Extruded heart ``width`` across and ``thickness`` tall, lying flat on the table."""
    return extrude_star_polygon(heart_outline(width), thickness)
