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


# ------------------------------------------------------------------------------------------------ glassware
def offset_polyline(points_px2: np.ndarray, thickness_p: np.ndarray | float) -> np.ndarray:
    """Offset an (r, z) profile polyline to its inner side (left of the walking direction) by ``thickness`` (m).

    Segment i is moved by ``thickness[i]`` along its left normal (-dz, dr); neighbouring offset segments are joined
    at their intersection (mitre). Walking up an outer wall (dz > 0) the left side is towards the axis, walking
    outwards along a base (dr > 0) it is upwards: the inner surface of a vessel. Returns (P, 2).
    """
    p = np.asarray(points_px2, dtype=np.float64)
    n_seg = len(p) - 1
    t = np.broadcast_to(np.asarray(thickness_p, dtype=np.float64), (n_seg,))
    d = np.diff(p, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    a = p[:-1] + nrm * t[:, None]  # offset segment starts
    out = [a[0]]
    for i in range(1, n_seg):
        # intersect line (a[i-1] + s d[i-1]) with (a[i] + u d[i])
        m = np.array([d[i - 1], -d[i]]).T
        if abs(np.linalg.det(m)) < 1e-12:
            out.append(a[i])
            continue
        s, _ = np.linalg.solve(m, a[i] - a[i - 1])
        out.append(a[i - 1] + s * d[i - 1])
    out.append(p[-1] + nrm[-1] * t[-1])
    return np.asarray(out)


def revolve_closed_profile(profile_px2: np.ndarray, sections: int = 48) -> trimesh.Trimesh:
    """Revolve an (r, z) profile that starts and ends on the axis (r = 0) about z into a watertight solid."""
    prof = np.asarray(profile_px2, dtype=np.float64)
    if abs(prof[0, 0]) > 1e-12 or abs(prof[-1, 0]) > 1e-12:
        raise ValueError("a revolved profile must start and end on the axis (r = 0)")
    if np.any(prof[:, 0] < -1e-12):
        raise ValueError("a revolved profile must stay at r >= 0")
    return finalize(trimesh.creation.revolve(prof, sections=sections))


def open_vessel(outer_px2: np.ndarray, wall: float, base: float, sections: int = 48) -> trimesh.Trimesh:
    """Thin-walled open vessel from its outer (r, z) profile: (0, 0) along the base out and up to the rim.

    The base segment (the first) is ``base`` thick, every other segment ``wall`` thick (offset inward, mitred);
    the rim is the flat ring between the outer and the inner wall at the last point.
    """
    outer = np.asarray(outer_px2, dtype=np.float64)
    if abs(outer[0, 0]) > 1e-12 or abs(outer[0, 1]) > 1e-12 or outer[1, 1] != 0.0:
        raise ValueError("the outer profile must start at (0, 0) and run along the base (z = 0) first")
    thick = np.full(len(outer) - 1, float(wall))
    thick[0] = base
    inner = offset_polyline(outer, thick)
    inner[0, 0] = 0.0
    profile = np.vstack([outer, inner[::-1]])
    return revolve_closed_profile(profile, sections)


def beaker(outer_diameter: float, height: float, wall: float, base: float) -> trimesh.Trimesh:
    """Low-form (Griffin) beaker without spout: straight wall, flat base and rim (m)."""
    r = outer_diameter / 2.0
    return open_vessel(np.array([[0.0, 0.0], [r, 0.0], [r, height]]), wall, base)


def erlenmeyer(base_diameter: float, height: float, neck_diameter: float, neck_height: float, wall: float,
               base: float, heel: float = 0.006) -> trimesh.Trimesh:
    """Narrow-neck conical (Erlenmeyer) flask: base, a short rounded heel, cone, cylindrical neck (m)."""
    rb, rn = base_diameter / 2.0, neck_diameter / 2.0
    z_shoulder = height - neck_height
    outer = np.array([[0.0, 0.0], [rb - heel, 0.0], [rb, heel], [rn, z_shoulder], [rn, height]])
    return open_vessel(outer, wall, base)


def test_tube(outer_diameter: float, length: float, wall: float, n_arc: int = 8) -> trimesh.Trimesh:
    """Round-bottom test tube (hemispherical bottom, straight wall, flat rim), standing on its bottom pole (m)."""
    r = outer_diameter / 2.0
    phi = np.linspace(-np.pi / 2, 0.0, n_arc + 1)[1:]  # the arc from the pole up to the equator
    arc = np.column_stack([r * np.cos(phi), r + r * np.sin(phi)])
    outer = np.vstack([[0.0, 0.0], arc, [r, length]])
    inner = offset_polyline(outer, wall)
    inner[0] = [0.0, wall]
    return revolve_closed_profile(np.vstack([outer, inner[::-1]]))


def vial(outer_diameter: float, height: float, neck_diameter: float, neck_height: float, wall: float,
         base: float) -> trimesh.Trimesh:
    """Screw-neck vial (scintillation-vial shape, no cap, thread omitted): body, shoulder, neck (m)."""
    r, rn = outer_diameter / 2.0, neck_diameter / 2.0
    z_neck = height - neck_height
    outer = np.array([[0.0, 0.0], [r, 0.0], [r, z_neck - 0.003], [rn, z_neck], [rn, height]])
    return open_vessel(outer, wall, base)


def measuring_cylinder(tube_diameter: float, height: float, foot_diameter: float, foot_height: float,
                       wall: float) -> trimesh.Trimesh:
    """Graduated cylinder: a solid round glass foot with a thin-walled tube on it (spout omitted) (m)."""
    rf, rt = foot_diameter / 2.0, tube_diameter / 2.0
    outer = np.array([[0.0, 0.0], [rf, 0.0], [rf, foot_height], [rt, foot_height], [rt, height]])
    thick = np.array([foot_height + wall, wall, wall, wall])  # the cavity's floor is the foot's top + one wall
    inner = offset_polyline(outer, thick)
    inner = inner[[0, -2, -1]]  # the foot is solid: the cavity runs from its floor straight up the tube
    inner[0] = [0.0, foot_height + wall]
    inner[1] = [rt - wall, foot_height + wall]
    return revolve_closed_profile(np.vstack([outer, inner[::-1]]))


def stemmed_glass(foot_diameter: float, foot_height: float, stem_diameter: float, stem_height: float,
                  bowl_diameter: float, bowl_height: float, rim_diameter: float, wall: float,
                  n_arc: int = 16) -> trimesh.Trimesh:
    """Stemmed wine glass: disc foot, solid stem, thin ellipsoidal bowl cut at the rim (m).

    The bowl's inner surface is an ellipse (semi-axes bowl_diameter/2 - wall, ``bowl_height``-scaled) from its
    bottom on the axis up to the rim radius; the outer surface is the same ellipse grown by ``wall``.
    """
    rf, rs = foot_diameter / 2.0, stem_diameter / 2.0
    a_o = bowl_diameter / 2.0
    a_i = a_o - wall
    # inner ellipse: r = a_i cos(t), z = zc + b_i sin(t); the rim at r = rim_radius - wall on the upper half
    r_rim_in = rim_diameter / 2.0 - wall
    t_rim = np.arccos(r_rim_in / a_i)
    b_i = bowl_height / (1.0 + np.sin(t_rim))  # bowl_height = cavity depth from its bottom to the rim
    b_o = b_i + wall
    z_stem_top = foot_height + stem_height
    t_stem = -np.arccos(rs / a_o)  # where the outer ellipse meets the stem
    zc = z_stem_top - b_o * np.sin(t_stem)
    t_o = np.linspace(t_stem, t_rim, n_arc)
    outer_bowl = np.column_stack([a_o * np.cos(t_o), zc + b_o * np.sin(t_o)])
    t_i = np.linspace(t_rim, -np.pi / 2, n_arc)
    inner_bowl = np.column_stack([a_i * np.cos(t_i), zc + b_i * np.sin(t_i)])
    inner_bowl[-1, 0] = 0.0
    rim_top = zc + b_i * np.sin(t_rim)
    outer_bowl[-1] = [r_rim_in + wall, rim_top]
    profile = np.vstack([[[0.0, 0.0], [rf, 0.0], [rf, foot_height], [rs + 0.002, foot_height + 0.002],
                          [rs, foot_height + 0.006]], outer_bowl, inner_bowl])
    return revolve_closed_profile(profile)


def closed_dish(diameter: float, height: float, wall_top: float, wall_bottom: float, wall_side: float,
                sections: int = 48) -> trimesh.Trimesh:
    """A lidded dish (a Petri dish with its lid on) as one closed shell: outer disc minus a sealed cavity (m)."""
    r = diameter / 2.0
    outer = trimesh.creation.cylinder(radius=r, height=height, sections=sections)
    inner = trimesh.creation.cylinder(radius=r - wall_side, height=height - wall_top - wall_bottom,
                                      sections=sections)
    inner.apply_translation([0.0, 0.0, (wall_bottom - wall_top) / 2.0])
    inner.invert()
    return finalize(trimesh.util.concatenate([outer, inner]))
