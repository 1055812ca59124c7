"""Opaque look-alikes and room surfaces added to a PBR training scene (segmenter v4 data; never labelled).

Real photos put glass beside things a segmenter trained on glass-on-a-table confuses with glass: glossy black spray
cans, metal tins, painted bottles, mugs, phone cases, books, and walls, floors and furniture beyond the table
(`../shared/facts/PERCEPTION.md`: 74 % of v3's false-positive pixels on real photos lay on glossy opaque cans).
:func:`clutter_entries` draws such things as Mitsuba scene-dict entries, to be passed to
:meth:`sim.render.MitsubaRenderer.render` as ``extra_emitters``. They are not in the MuJoCo model and not in the
renderer's ``shape_instances``, so the renderer's exact first-hit id pass gives them id 0: they are background in
the masks and occlude the glass behind them exactly.

Distractors (``kind``; sizes in m):

``can``      cylinder, radius 0.02-0.045, height 0.06-0.22, standing or (30 %) lying on its side
``box``      box, sides 0.03-0.16, height 0.01-0.12 (books, phone cases, packaging)
``blob``     squashed sphere, radii 0.025-0.07 (fruit, cases, pouches)
``twin``     an opaque copy of one of the scene's glass meshes (ClearGrasp's painted twins: the glass shape,
             opaque), scaled 0.8-1.2
``mug``      cylinder, radius 0.035-0.05, height 0.08-0.12, with a torus handle (``print`` mix only)
``book``     flat box, 0.12-0.26 x 0.09-0.20, 0.005-0.04 thick: notebooks, folders (``print`` mix only)

Materials (drawn per distractor): ``roughplastic`` (painted or glossy plastic; dark colours in a third of the
draws, alpha 0.02-0.35), ``plastic`` (smooth lacquer), ``roughconductor`` (aluminium, chrome, copper, gold,
alpha 0.02-0.4), ``textured`` (diffuse with a procedural stripe / noise / tile image: labels, book covers).
Colours are sRGB HSV draws converted to linear.

Mixes (``DataRecipe.distractor_mix``, :data:`MIXES`): ``v4`` draws the kinds and materials above with v4's weights
(its data is reproduced exactly). ``print`` (segmenter v5) answers what v4 still marks as glass on real photos
(ClearGrasp frames: a patterned notebook, a mug with a printed spiral, glossy red and black cases): mugs and books
join the kinds, and half of the materials are printed: ``textured`` (20 %) and ``glossy_print`` (30 %: the same
print under a GGX clear coat, alpha 0.02-0.2) read :func:`print_image` (stripes, rings and spirals, line art,
text-like rows, dots, tiles, noise) through UV coordinates (:func:`uv_soup`: cylindrical on can and mug sides,
cube-mapped elsewhere). In the ``v4`` mix the meshes carry no UVs, so its ``textured`` draws show Mitsuba's
per-triangle barycentric lookup of the label, not a print.

Room (``room=True``): a textured floor rectangle (6 x 6 m) at the MuJoCo floor's height and 1-2 walls (5 m wide,
3 m high) 0.6-2.0 m from the workspace centre, facing it; each surface gets a procedural texture
(:func:`sim.render.textures.table_texture` of another seed: wood, stone, checker or solid).

Everything is drawn from ``rng`` (``numpy.random.Generator``); the same generator state gives the same entries.
"""

from __future__ import annotations

import colorsys
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ConfigError

#: distractor kinds and materials (see the module docstring)
KINDS = ("can", "box", "blob", "twin", "mug", "book")
MATERIALS = ("roughplastic", "plastic", "roughconductor", "textured", "glossy_print")
#: per mix: draw weights of :data:`KINDS` and of :data:`MATERIALS` (zeros appended to v4's weights leave its
#: draws unchanged: numpy's weighted choice inverts the cumulative sum)
MIXES: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "v4": ((0.35, 0.25, 0.15, 0.25, 0.0, 0.0), (0.4, 0.2, 0.25, 0.15, 0.0)),
    "print": ((0.25, 0.1, 0.1, 0.15, 0.2, 0.2), (0.25, 0.1, 0.15, 0.2, 0.3)),
}
#: Mitsuba's built-in conductor names used for metals
METALS = ("Al", "Cr", "Cu", "Au")
#: xy half-extent (m) around the workspace centre where distractors stand
SPREAD_M = 0.28
#: clearance (m) kept between a distractor's footprint and any object's
GAP_M = 0.005


@dataclass(frozen=True)
class Footprint:
    """A circle on the table: centre ``xy`` (m, world) and ``radius`` (m)."""

    xy: tuple[float, float]
    radius: float

    def clear_of(self, other: Footprint, gap: float = GAP_M) -> bool:
        d = float(np.hypot(self.xy[0] - other.xy[0], self.xy[1] - other.xy[1]))
        return d >= self.radius + other.radius + gap


def _colour(rng: np.random.Generator, dark: bool) -> list[float]:
    h = rng.uniform(0, 1)
    s = rng.uniform(0.0, 0.9)
    v = rng.uniform(0.02, 0.15) if dark else rng.uniform(0.2, 0.95)
    srgb = np.array(colorsys.hsv_to_rgb(h, s, v))
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return [float(c) for c in lin]


def label_image(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """(size, size, 3) float32 linear RGB: stripes, value noise or tiles in 2-4 random colours (a label or cover)."""
    from sim.render.textures import _fbm

    cols = np.array([_colour(rng, rng.random() < 0.3) for _ in range(int(rng.integers(2, 5)))])
    kind = int(rng.integers(0, 3))
    yy, xx = np.mgrid[0:size, 0:size] / size
    if kind == 0:  # stripes at a random angle and period
        a = rng.uniform(0, np.pi)
        t = (np.cos(a) * xx + np.sin(a) * yy) * rng.uniform(2, 12)
        idx = np.floor(t).astype(int) % len(cols)
    elif kind == 1:  # smooth noise quantised into the colours
        f = _fbm(rng, size, size, (int(rng.integers(2, 8)),) * 2, 3)
        idx = np.clip((f * len(cols)).astype(int), 0, len(cols) - 1)
    else:  # tiles
        n = int(rng.integers(2, 9))
        idx = (np.floor(xx * n) + np.floor(yy * n)).astype(int) % len(cols)
    return cols[idx].astype(np.float32)


def print_image(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """(size, size, 3) float32 linear RGB print on a background colour: stripes, rings or a spiral, line art,
    text-like rows, dots, or :func:`label_image`'s tiles / noise (what covers mugs, notebooks and packaging)."""
    import cv2

    bg = np.array(_colour(rng, rng.random() < 0.25), np.float32)
    inks = [tuple(float(c) for c in _colour(rng, rng.random() < 0.5)) for _ in range(int(rng.integers(1, 4)))]
    img = np.empty((size, size, 3), np.float32)
    img[:] = bg
    kind = int(rng.integers(0, 6))
    yy, xx = np.mgrid[0:size, 0:size] / size
    if kind == 0:  # stripes, fine to coarse
        a = rng.uniform(0, np.pi)
        t = (np.cos(a) * xx + np.sin(a) * yy) * rng.uniform(3, 40)
        on = (t % 1.0) < rng.uniform(0.2, 0.6)
        img[on] = inks[0]
    elif kind == 1:  # concentric rings or a spiral around a random centre
        cy, cx = rng.uniform(0.2, 0.8, 2)
        r = np.hypot(yy - cy, xx - cx) * rng.uniform(6, 30)
        t = r + (np.arctan2(yy - cy, xx - cx) / (2 * np.pi) if rng.random() < 0.5 else 0.0)
        on = (t % 1.0) < rng.uniform(0.2, 0.5)
        img[on] = inks[0]
    elif kind == 2:  # line art: random polylines and curves
        for _ in range(int(rng.integers(8, 60))):
            pts = np.cumsum(rng.normal(0, size * 0.06, (int(rng.integers(3, 12)), 2)), axis=0)
            pts += rng.uniform(0, size, 2)
            cv2.polylines(img, [pts.astype(np.int32)], False, inks[int(rng.integers(0, len(inks)))],
                          int(rng.integers(1, 4)), cv2.LINE_AA)
    elif kind == 3:  # text-like rows of word blocks
        row_h = int(rng.integers(5, 16))
        y = int(rng.integers(2, row_h + 2))
        while y + row_h < size:
            x = int(rng.integers(2, 20))
            while x < size - 4:
                w = int(rng.integers(row_h, 6 * row_h))
                cv2.rectangle(img, (x, y), (min(x + w, size - 1), y + int(0.6 * row_h)), inks[0], -1)
                x += w + int(rng.integers(row_h // 2 + 1, row_h + 2))
            y += int(row_h * rng.uniform(1.3, 2.2))
    elif kind == 4:  # dots
        for _ in range(int(rng.integers(10, 120))):
            c = (int(rng.integers(0, size)), int(rng.integers(0, size)))
            cv2.circle(img, c, int(rng.integers(2, 14)), inks[int(rng.integers(0, len(inks)))], -1, cv2.LINE_AA)
    else:
        img = label_image(rng, size)
    return np.ascontiguousarray(img, np.float32)


def bsdf(rng: np.random.Generator, mi: Any, mix: str = "v4") -> tuple[dict[str, Any], str]:
    """A random opaque Mitsuba BSDF dict and its material name (one of :data:`MATERIALS`, weighted by ``mix``)."""
    kind = str(rng.choice(MATERIALS, p=list(MIXES[mix][1])))
    dark = bool(rng.random() < 0.33)
    if kind == "roughplastic":
        return {"type": "roughplastic", "distribution": "ggx", "alpha": float(rng.uniform(0.02, 0.35)),
                "diffuse_reflectance": {"type": "rgb", "value": _colour(rng, dark)}}, kind
    if kind == "plastic":
        return {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": _colour(rng, dark)}}, kind
    if kind == "roughconductor":
        return {"type": "roughconductor", "material": str(rng.choice(METALS)), "distribution": "ggx",
                "alpha": float(rng.uniform(0.02, 0.4))}, kind
    img = label_image(rng) if mix == "v4" else print_image(rng)
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img)), "raw": True, "filter_type": "bilinear"}
    if kind == "glossy_print":
        return {"type": "roughplastic", "distribution": "ggx", "alpha": float(rng.uniform(0.02, 0.2)),
                "diffuse_reflectance": tex}, kind
    return {"type": "diffuse", "reflectance": tex}, kind


def _mesh_entry_file(vertices_vx3: np.ndarray, faces_fx3: np.ndarray, folder: Path) -> Path:
    """A PLY of the mesh (crease-split normals), written once per mesh digest under ``folder``."""
    from sim.render.scene import GeomEntry, mesh_ply

    e = GeomEntry(name="d", kind="mesh", T_world_geom=np.eye(4), size=np.zeros(3), material="diffuse",
                  rgb=(0.5, 0.5, 0.5), ior=1.0, instance=0, mesh=(np.asarray(vertices_vx3, np.float64),
                                                                   np.asarray(faces_fx3, np.int64)))
    return mesh_ply(e, folder)


def uv_soup(vertices_vx3: np.ndarray, faces_fx3: np.ndarray, cylindrical: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle soup of a mesh with UV coordinates: (corners (3F, 3) m, normals (3F, 3), uv (3F, 2)).

    Normals: crease-split smooth shading (as :func:`sim.render.scene.mesh_ply`). UV: cube mapping by each
    corner's dominant normal axis (the two other coordinates / the largest extent); with ``cylindrical``, corners
    whose normal is within 45 deg of horizontal take (azimuth / 2 pi, height / circumference) instead, and a face
    across the azimuth seam is unwrapped so that it does not squeeze the whole print into one triangle.
    """
    import math

    import trimesh

    from sim.render.scene import CREASE_DEG

    tm = trimesh.Trimesh(np.asarray(vertices_vx3, np.float64), np.asarray(faces_fx3, np.int64), process=False)
    shaded = trimesh.graph.smooth_shade(tm, angle=math.radians(CREASE_DEG), facet_minarea=None)
    v = np.asarray(shaded.vertices)[shaded.faces]  # (F, 3, 3)
    n = np.asarray(shaded.vertex_normals)[shaded.faces]
    lo, ext = v.reshape(-1, 3).min(axis=0), max(float(np.ptp(v.reshape(-1, 3), axis=0).max()), 1e-6)
    p = (v - lo) / ext
    axis = np.argmax(np.abs(n), axis=-1)  # (F, 3)
    uv = np.where((axis == 0)[..., None], p[..., [1, 2]], np.where((axis == 1)[..., None], p[..., [0, 2]],
                                                                   p[..., [0, 1]]))
    if cylindrical:
        side = np.abs(n[..., 2]) < np.sqrt(0.5)
        az = (np.arctan2(v[..., 1], v[..., 0]) / (2 * np.pi)) % 1.0
        wrap = (az.max(axis=1, keepdims=True) - az.min(axis=1, keepdims=True)) > 0.5
        az = np.where(wrap & (az < 0.5), az + 1.0, az)
        r = max(float(np.hypot(v[..., 0], v[..., 1]).max()), 1e-6)
        cyl = np.stack([az, (v[..., 2] - lo[2]) / (2 * np.pi * r)], axis=-1)
        uv = np.where(side[..., None], cyl, uv)
    return v.reshape(-1, 3), n.reshape(-1, 3), uv.reshape(-1, 2)


def _uv_mesh_file(vertices_vx3: np.ndarray, faces_fx3: np.ndarray, cylindrical: bool, folder: Path) -> Path:
    """A binary PLY of :func:`uv_soup` (x y z nx ny nz u v), written once per content digest under ``folder``."""
    import hashlib

    v, n, uv = uv_soup(vertices_vx3, faces_fx3, cylindrical)
    vert = np.empty(len(v), dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "u", "v")])
    for k, col in zip(("x", "y", "z"), v.T, strict=True):
        vert[k] = col
    for k, col in zip(("nx", "ny", "nz"), n.T, strict=True):
        vert[k] = col
    vert["u"], vert["v"] = uv[:, 0], uv[:, 1]
    faces = np.empty(len(v) // 3, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    body = vert.tobytes() + faces.tobytes()
    path = Path(folder) / f"uv_{hashlib.sha256(body).hexdigest()[:20]}.ply"
    if path.exists():
        return path
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(v)}\n" + "".join(f"property float {k}\n" for k in vert.dtype.names)
              + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")  # shard workers may write the same mesh at once
    tmp.write_bytes(header.encode("ascii") + body)
    tmp.replace(path)
    return path


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    R = np.eye(4)
    R[:2, :2] = [[c, -s], [s, c]]
    return R


def distractor_mesh(kind: str, rng: np.random.Generator, twins: list[tuple[np.ndarray, np.ndarray]]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) m, faces (F, 3)) of one distractor in its own frame, resting on z = 0 (its lowest point),
    centred in x, y. ``twin`` copies (and rescales) a random mesh of ``twins``; without twins it is a can."""
    import trimesh

    if kind == "twin" and twins:
        v, f = twins[int(rng.integers(0, len(twins)))]
        v = np.asarray(v, np.float64) * rng.uniform(0.8, 1.2)
        m = trimesh.Trimesh(v, f, process=False)
    elif kind == "box":
        m = trimesh.creation.box([rng.uniform(0.03, 0.16), rng.uniform(0.03, 0.16), rng.uniform(0.01, 0.12)])
    elif kind == "book":
        m = trimesh.creation.box([rng.uniform(0.12, 0.26), rng.uniform(0.09, 0.2), rng.uniform(0.005, 0.04)])
    elif kind == "mug":
        r, h = rng.uniform(0.035, 0.05), rng.uniform(0.08, 0.12)
        body = trimesh.creation.cylinder(radius=r, height=h, sections=48)
        handle = trimesh.creation.torus(major_radius=0.3 * h, minor_radius=rng.uniform(0.006, 0.011),
                                        major_sections=32, minor_sections=12)
        handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # upright ring
        handle.apply_translation([r + 0.1 * h, 0.0, 0.0])
        m = trimesh.util.concatenate([body, handle])
    elif kind == "blob":
        m = trimesh.creation.icosphere(subdivisions=3)
        r = rng.uniform(0.025, 0.07)
        m.apply_scale([r * rng.uniform(0.8, 1.3), r * rng.uniform(0.8, 1.3), r * rng.uniform(0.4, 1.0)])
    else:
        r, h = rng.uniform(0.02, 0.045), rng.uniform(0.06, 0.22)
        m = trimesh.creation.cylinder(radius=r, height=h, sections=48)
        if rng.random() < 0.3:  # lying on its side
            m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    v = np.asarray(m.vertices, np.float64).copy()
    v[:, :2] -= 0.5 * (v[:, :2].min(axis=0) + v[:, :2].max(axis=0))
    v[:, 2] -= v[:, 2].min()
    return v, np.asarray(m.faces)


def place(footprint_radius: float, taken: list[Footprint], centre_xy: tuple[float, float],
          rng: np.random.Generator, attempts: int = 40) -> Footprint | None:
    """A footprint of ``footprint_radius`` m within :data:`SPREAD_M` of ``centre_xy`` clear of every ``taken`` one
    (rejection sampling, ``attempts`` draws); None when none fits."""
    for _ in range(attempts):
        xy = (centre_xy[0] + rng.uniform(-SPREAD_M, SPREAD_M), centre_xy[1] + rng.uniform(-SPREAD_M, SPREAD_M))
        fp = Footprint(xy, footprint_radius)
        if all(fp.clear_of(t) for t in taken):
            return fp
    return None


def clutter_entries(desc: Any, rng: np.random.Generator, n_distractors: int, room: bool, mi: Any,
                    folder: Path, mix: str = "v4") -> tuple[dict[str, dict], dict[str, Any]]:
    """Mitsuba entries (``distractor_<i>``, ``room_floor``, ``room_wall_<i>``) for the scene ``desc``
    (:func:`sim.render.scene.describe_world`) and what was drawn (JSON-ready). ``mix``: a key of :data:`MIXES`.

    Distractors stand on the table top (the ``table`` geom's top face) within :data:`SPREAD_M` of the workspace
    centre, clear of every object's footprint (its mesh's xy radius) and of each other by :data:`GAP_M`; one
    that does not fit after 40 draws is skipped. ``folder`` holds the PLY files.
    """
    from sim.render.textures import table_texture

    if mix not in MIXES:
        raise ConfigError(f"distractor mix {mix!r}; valid choices: {', '.join(MIXES)}")
    kind_p, _ = MIXES[mix]
    table = next((g for g in desc.geoms if g.material == "table"), None)
    top_z = float(table.T_world_geom[2, 3] + table.size[2]) if table is not None else 0.0
    taken: list[Footprint] = []
    twins: list[tuple[np.ndarray, np.ndarray]] = []
    for g in desc.geoms:
        if g.instance > 0:
            r = 0.05
            if g.mesh is not None:
                v = g.mesh[0]
                r = float(np.max(np.hypot(v[:, 0], v[:, 1]))) if len(v) else r
                twins.append(g.mesh)
            elif g.kind in ("sphere", "box"):
                r = float(np.hypot(g.size[0], g.size[1 if g.kind == "box" else 0]))
            taken.append(Footprint((float(g.T_world_geom[0, 3]), float(g.T_world_geom[1, 3])), r))
    centre = (float(desc.centre[0]), float(desc.centre[1]))
    entries: dict[str, dict] = {}
    drawn: list[dict[str, Any]] = []
    for i in range(n_distractors):
        kind = str(rng.choice(KINDS, p=list(kind_p)))
        v, f = distractor_mesh(kind, rng, twins)
        radius = float(np.max(np.hypot(v[:, 0], v[:, 1])))
        fp = place(radius, taken, centre, rng)
        if fp is None:
            continue
        taken.append(fp)
        T = _yaw(rng.uniform(0, 2 * np.pi))
        T[:3, 3] = [fp.xy[0], fp.xy[1], top_z + 1e-4]
        b, mat = bsdf(rng, mi, mix)
        mesh_file = _mesh_entry_file(v, f, folder) if mix == "v4" else _uv_mesh_file(v, f, kind in ("can", "mug"),
                                                                                      folder)
        entries[f"distractor_{i}"] = {"type": "ply", "filename": str(mesh_file),
                                      "to_world": mi.ScalarTransform4f(T.tolist()), "face_normals": False,
                                      "bsdf": b, "id": f"distractor_{i}"}
        drawn.append({"kind": kind, "material": mat, "xy_m": [round(c, 4) for c in fp.xy],
                      "radius_m": round(radius, 4)})
    info: dict[str, Any] = {"distractors": drawn}
    if room:
        floor = next((g for g in desc.geoms if g.kind == "plane"), None)
        floor_z = float(floor.T_world_geom[2, 3]) if floor is not None else top_z - 0.75
        seed = int(rng.integers(0, 2**31 - 1))
        tex = table_texture(seed, (4.0, 4.0), px_per_m=128)
        T = np.diag([3.0, 3.0, 1.0, 1.0])
        T[:3, 3] = [centre[0], centre[1], floor_z + 1e-3]
        entries["room_floor"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(T.tolist()), "id": "room_floor",
                                 "bsdf": {"type": "diffuse", "reflectance": {
                                     "type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(tex.image_hxwx3)),
                                     "raw": True, "filter_type": "bilinear"}}}
        walls = []
        for w in range(int(rng.integers(1, 3))):
            az = rng.uniform(0, 2 * np.pi)
            dist = rng.uniform(0.6, 2.0)
            n = -np.array([np.cos(az), np.sin(az), 0.0])  # faces the workspace
            c = np.array([centre[0], centre[1], 0.0]) - dist * n
            c[2] = floor_z + 1.5
            x = np.cross([0.0, 0.0, 1.0], n)
            T = np.eye(4)
            T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x * 2.5, [0.0, 0.0, 1.5], n, c
            wt = table_texture(int(rng.integers(0, 2**31 - 1)), (5.0, 3.0), px_per_m=96)
            entries[f"room_wall_{w}"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(T.tolist()),
                                         "id": f"room_wall_{w}", "bsdf": {"type": "twosided", "bsdf": {
                                             "type": "diffuse", "reflectance": {
                                                 "type": "bitmap",
                                                 "bitmap": mi.Bitmap(np.ascontiguousarray(wt.image_hxwx3)),
                                                 "raw": True, "filter_type": "bilinear"}}}}
            walls.append({"azimuth_deg": round(float(np.degrees(az)), 1), "distance_m": round(float(dist), 3),
                          "pattern": wt.pattern})
        info["room"] = {"floor": tex.pattern, "walls": walls}
    return entries, info

