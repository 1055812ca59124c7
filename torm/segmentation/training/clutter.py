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

Materials (drawn per distractor): ``roughplastic`` (painted or glossy plastic; dark colours in a third of the
draws, alpha 0.02-0.35), ``plastic`` (smooth lacquer), ``roughconductor`` (aluminium, chrome, copper, gold,
alpha 0.02-0.4), ``textured`` (diffuse with a procedural stripe / noise / tile image: labels, book covers).
Colours are sRGB HSV draws converted to linear.

Room (``room=True``): a textured floor rectangle (6 x 6 m) at the MuJoCo floor's height and 1-2 walls (5 m wide,
3 m high) 0.6-2.0 m from the workspace centre, facing it; each surface gets a procedural texture
(:func:`sim.render.textures.table_texture` of another seed: wood, stone, checker or solid).

Everything is drawn from ``rng`` (``numpy.random.Generator``); the same generator state gives the same entries.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: distractor kinds and materials (see the module docstring)
KINDS = ("can", "box", "blob", "twin")
MATERIALS = ("roughplastic", "plastic", "roughconductor", "textured")
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


def bsdf(rng: np.random.Generator, mi: Any) -> tuple[dict[str, Any], str]:
    """A random opaque Mitsuba BSDF dict and its material name (one of :data:`MATERIALS`)."""
    kind = str(rng.choice(MATERIALS, p=[0.4, 0.2, 0.25, 0.15]))
    dark = bool(rng.random() < 0.33)
    if kind == "roughplastic":
        return {"type": "roughplastic", "distribution": "ggx", "alpha": float(rng.uniform(0.02, 0.35)),
                "diffuse_reflectance": {"type": "rgb", "value": _colour(rng, dark)}}, kind
    if kind == "plastic":
        return {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": _colour(rng, dark)}}, kind
    if kind == "roughconductor":
        return {"type": "roughconductor", "material": str(rng.choice(METALS)), "distribution": "ggx",
                "alpha": float(rng.uniform(0.02, 0.4))}, kind
    img = label_image(rng)
    return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img)),
                                               "raw": True, "filter_type": "bilinear"}}, kind


def _mesh_entry_file(vertices_vx3: np.ndarray, faces_fx3: np.ndarray, folder: Path) -> Path:
    """A PLY of the mesh (crease-split normals), written once per mesh digest under ``folder``."""
    from sim.render.scene import GeomEntry, mesh_ply

    e = GeomEntry(name="d", kind="mesh", T_world_geom=np.eye(4), size=np.zeros(3), material="diffuse",
                  rgb=(0.5, 0.5, 0.5), ior=1.0, instance=0, mesh=(np.asarray(vertices_vx3, np.float64),
                                                                   np.asarray(faces_fx3, np.int64)))
    return mesh_ply(e, folder)


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
                    folder: Path) -> tuple[dict[str, dict], dict[str, Any]]:
    """Mitsuba entries (``distractor_<i>``, ``room_floor``, ``room_wall_<i>``) for the scene ``desc``
    (:func:`sim.render.scene.describe_world`) and what was drawn (JSON-ready).

    Distractors stand on the table top (the ``table`` geom's top face) within :data:`SPREAD_M` of the workspace
    centre, clear of every object's footprint (its mesh's xy radius) and of each other by :data:`GAP_M`; one
    that does not fit after 40 draws is skipped. ``folder`` holds the PLY files.
    """
    from sim.render.textures import table_texture

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
        kind = str(rng.choice(KINDS, p=[0.35, 0.25, 0.15, 0.25]))
        v, f = distractor_mesh(kind, rng, twins)
        radius = float(np.max(np.hypot(v[:, 0], v[:, 1])))
        fp = place(radius, taken, centre, rng)
        if fp is None:
            continue
        taken.append(fp)
        T = _yaw(rng.uniform(0, 2 * np.pi))
        T[:3, 3] = [fp.xy[0], fp.xy[1], top_z + 1e-4]
        b, mat = bsdf(rng, mi)
        entries[f"distractor_{i}"] = {"type": "ply", "filename": str(_mesh_entry_file(v, f, folder)),
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

