"""Build the Mitsuba 3 scene of a :class:`sim.world.World` at its current state (objects where physics put them).

Two steps, both public so other modules can extend them:

1. :func:`describe_world` reads the MuJoCo model/data into a plain, JSON-ready :class:`SceneDescription`: one
   entry per rendered geom (the rig's groups 0 environment, 2 glass, 4 opaque objects; the robot's group 1 and
   the collision group 3 are excluded exactly as the MuJoCo rig excludes them) with its world pose, shape,
   material and instance id, plus the layout seed that randomises the table texture and the lighting.
   Its :meth:`~SceneDescription.digest` is what the render cache keys on.
2. :func:`build_scene_dict` turns a description into a Mitsuba scene dict (``mi.load_dict``-ready). Keys:
   ``integrator`` (``path``), ``env`` (``envmap`` emitter), ``area_light_<i>`` (emitting rectangles),
   ``table_top`` (textured diffuse rectangle) and ``table_body``, then ``geom_<name>`` for every other geom.
   Extra entries (a projector emitter, another light) can be added before loading. Load it with
   :func:`load_scene` (``mi.load_dict(d, optimize=False)``): Mitsuba's default optimisation merges shapes with
   identical BSDFs into one, which would merge the objects and lose their ids.

Materials: glass geoms (group 2) are smooth ``dielectric`` BSDFs with the object's index of refraction
(``ObjectAsset.ior``: soda-lime glass 1.5, borosilicate 1.47) against air (1.000277); opaque object geoms
(group 4, e.g. the ceramic cup) and the other environment geoms are ``diffuse`` with the geom's MuJoCo colour
(sRGB -> linear); the table top gets a procedural texture drawn from the layout seed
(:mod:`sim.render.textures`). Meshes are the MuJoCo model's own vertices and faces (so PBR silhouettes equal
the MuJoCo masks), written once as PLY files under the cache folder with crease-split vertex normals (smooth
within 30 deg, sharp across edges: a cube keeps its edges, a cylinder renders round).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from sim.render.cache import cache_root
from sim.render.lighting import Lighting, sample_lighting
from sim.render.textures import srgb_to_linear, table_texture

log = logging.getLogger(__name__)

#: Bump when the scene builder changes what it renders (part of every cache key).
SCENE_BUILDER_VERSION = 1
#: Geom groups the rig renders (environment, glass, opaque objects); see sim/cameras/rig.py.
RENDERED_GROUPS = (0, 2, 4)
GROUP_GLASS = 2
#: Index of refraction of glass when the object names none (soda-lime glass; the issue's value).
DEFAULT_IOR = 1.5
AIR_IOR = 1.000277
#: Crease angle (deg) below which mesh normals are smoothed.
CREASE_DEG = 30.0
#: Half-size (m) of the rectangle standing in for an infinite MuJoCo plane.
INFINITE_PLANE_HALF = 10.0
TABLE_GEOM = "table"


@dataclass(frozen=True, eq=False)
class GeomEntry:
    """One rendered geom: ``kind`` (box | sphere | plane | mesh), world pose ``T_world_geom`` (4, 4) m, MuJoCo
    ``size`` (3,), ``mesh`` (vertices (V, 3), faces (F, 3)) for meshes, ``material`` (glass | diffuse | table),
    ``rgb`` (linear diffuse colour), ``ior`` (glass), ``instance`` (0 or the object's id)."""

    name: str
    kind: str
    T_world_geom: np.ndarray
    size: np.ndarray
    material: str
    rgb: tuple[float, float, float]
    ior: float
    instance: int
    mesh: tuple[np.ndarray, np.ndarray] | None = None

    def mesh_digest(self) -> str:
        if self.mesh is None:
            return ""
        v, f = self.mesh
        return hashlib.sha1(np.ascontiguousarray(v, np.float32).tobytes()
                            + np.ascontiguousarray(f, np.int32).tobytes()).hexdigest()

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "T": np.round(self.T_world_geom, 7).tolist(),
                "size": np.round(self.size, 7).tolist(), "material": self.material,
                "rgb": [round(c, 6) for c in self.rgb], "ior": self.ior, "instance": self.instance,
                "mesh": self.mesh_digest()}


@dataclass(frozen=True, eq=False)
class SceneDescription:
    """What a PBR render of a world depends on: scenario, layout seed, workspace centre and the geoms."""

    scenario: str
    layout_seed: int
    centre: tuple[float, float, float]
    geoms: tuple[GeomEntry, ...]
    builder_version: int = SCENE_BUILDER_VERSION

    def to_json(self) -> dict[str, Any]:
        return {"scenario": self.scenario, "layout_seed": self.layout_seed, "centre": list(self.centre),
                "builder_version": self.builder_version, "geoms": [g.to_json() for g in self.geoms]}

    def digest(self) -> str:
        """sha256 of the JSON form (object poses rounded to 1e-7 m / 1e-7)."""
        return hashlib.sha256(json.dumps(self.to_json(), sort_keys=True).encode()).hexdigest()


def _ior_of(world: Any, instance: int) -> float:
    objects = list(getattr(world, "objects", None) or [])
    if not 1 <= instance <= len(objects):
        return DEFAULT_IOR
    o = objects[instance - 1]
    ior = getattr(o, "ior", None)
    if ior is None:
        try:
            from sim.scenes.objects import get_object

            ior = getattr(get_object(o.name), "ior", None)
        except Exception:  # a custom object outside the library
            ior = None
    return float(ior) if ior is not None else DEFAULT_IOR


def _geom_rgb(model: mujoco.MjModel, g: int) -> tuple[float, float, float]:
    mat = int(model.geom_matid[g])
    rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
    lin = srgb_to_linear(np.clip(np.asarray(rgba[:3], dtype=np.float64), 0.0, 1.0))
    return (float(lin[0]), float(lin[1]), float(lin[2]))


def describe_world(world: Any, layout_seed: int | None = None, centre: tuple[float, float, float] = (0.55, 0.0, 0.0),
                   groups: tuple[int, ...] = RENDERED_GROUPS) -> SceneDescription:
    """The rendered geoms of ``world`` (``model``, ``data``, ``geom_to_instance``) at its current state.

    ``layout_seed`` defaults to ``world.seed``; ``centre`` (m) is the workspace centre the lights face; ``groups``
    the geom groups described (default: those rendered).
    Geom types other than box, sphere, plane and mesh (cylinder, capsule, ellipsoid) are triangulated.
    """
    model, data = world.model, world.data
    mujoco.mj_forward(model, data)
    g2i = np.asarray(getattr(world, "geom_to_instance", None) if getattr(world, "geom_to_instance", None) is not None
                     else np.zeros(model.ngeom, np.int32))
    seed = int(layout_seed if layout_seed is not None else (getattr(world, "seed", 0) or 0))
    entries = []
    for g in range(model.ngeom):
        if int(model.geom_group[g]) not in groups or model.geom_rgba[g][3] == 0:
            continue
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        T = np.eye(4)
        T[:3, :3] = data.geom_xmat[g].reshape(3, 3)
        T[:3, 3] = data.geom_xpos[g]
        t = int(model.geom_type[g])
        size = np.asarray(model.geom_size[g], dtype=np.float64).copy()
        mesh = None
        if t == mujoco.mjtGeom.mjGEOM_BOX:
            kind = "box"
        elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
            kind = "sphere"
        elif t == mujoco.mjtGeom.mjGEOM_PLANE:
            kind = "plane"
        elif t == mujoco.mjtGeom.mjGEOM_MESH:
            kind = "mesh"
            m = int(model.geom_dataid[g])
            va, vn = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
            fa, fn = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
            mesh = (np.asarray(model.mesh_vert[va:va + vn], np.float64), np.asarray(model.mesh_face[fa:fa + fn]))
        elif t in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_ELLIPSOID):
            kind = "mesh"
            mesh = _primitive_mesh(t, size)
        else:
            log.debug("geom %s of type %d is not rendered by the PBR renderer", name, t)
            continue
        inst = int(g2i[g]) if g < len(g2i) else 0
        glass = int(model.geom_group[g]) == GROUP_GLASS
        material = "glass" if glass else ("table" if name == TABLE_GEOM else "diffuse")
        entries.append(GeomEntry(name=name, kind=kind, T_world_geom=T, size=size, material=material,
                                 rgb=_geom_rgb(model, g), ior=_ior_of(world, inst) if glass else 1.0,
                                 instance=inst, mesh=mesh))
    scenario = getattr(world, "scenario", "")
    return SceneDescription(scenario=str(getattr(scenario, "name", scenario)), layout_seed=seed,
                            centre=tuple(float(c) for c in centre), geoms=tuple(entries))


def _primitive_mesh(t: int, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        m = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=48)
    elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        m = trimesh.creation.capsule(radius=size[0], height=2 * size[1], count=[24, 24])
    else:
        m = trimesh.creation.icosphere(subdivisions=3)
        m.apply_scale(size[:3])
    return np.asarray(m.vertices), np.asarray(m.faces)


def mesh_ply(entry: GeomEntry, folder: Path | None = None) -> Path:
    """The PLY file (geom frame, crease-split vertex normals) of a mesh entry, written once per mesh digest."""
    import trimesh

    folder = Path(folder) if folder is not None else cache_root() / "meshes"
    path = folder / f"{entry.mesh_digest()}_c{int(CREASE_DEG)}.ply"
    if path.exists():
        return path
    v, f = entry.mesh
    tm = trimesh.Trimesh(v, f, process=False)
    shaded = trimesh.graph.smooth_shade(tm, angle=math.radians(CREASE_DEG), facet_minarea=None)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{id(entry)}")
    tmp.write_bytes(trimesh.exchange.ply.export_ply(shaded, vertex_normal=True))
    tmp.replace(path)
    return path


@dataclass(eq=False)
class PbrScene:
    """A Mitsuba scene dict with what built it: ``scene_dict`` (edit before loading), ``shape_instances`` (dict
    key -> instance id of each object geom), ``description``, ``lighting`` and the table texture parameters."""

    scene_dict: dict[str, Any]
    shape_instances: dict[str, int]
    description: SceneDescription
    lighting: Lighting
    table: dict[str, Any] = field(default_factory=dict)


def _transform(mi: Any, T: np.ndarray) -> Any:
    return mi.ScalarTransform4f(np.asarray(T, dtype=np.float64).tolist())


def build_scene_dict(desc: SceneDescription, settings: Any, *, lighting: Lighting | None = None,
                     env_scale: float = 1.0, area_scale: float = 1.0) -> PbrScene:
    """The Mitsuba scene dict of ``desc`` (see the module docstring for its keys).

    Args:
        desc: from :func:`describe_world`.
        settings: a :class:`torm.capture.render_settings.PbrSettings` (integrator depth, variant).
        lighting: the lighting to use (default: drawn from ``desc.layout_seed``).
        env_scale, area_scale: multiply the environment / area-light radiance (e.g. dim the room for an IR
            projector render).
    """
    from sim.render.mitsuba_env import load_mitsuba

    mi, variant = load_mitsuba(settings.variant, settings.threads)
    light = lighting if lighting is not None else sample_lighting(desc.layout_seed, desc.centre)
    integrator = settings.integrator
    if integrator == "glass_path":
        if variant.startswith("scalar"):
            integrator = "path"  # Python integrators need a JIT variant
        else:
            from sim.render.integrator import register

            register()
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": int(settings.max_depth), "rr_depth": int(settings.rr_depth),
                       "hide_emitters": False},
    }
    if env_scale > 0:
        # lat-long map with +Y up in Mitsuba's env frame: rotate it so that +Y -> world +z, then about z
        T_env = (mi.ScalarTransform4f().rotate([0, 0, 1], float(light.env_rotation_deg))
                 @ mi.ScalarTransform4f().rotate([1, 0, 0], 90.0))
        d["env"] = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(light.env_hxwx3 * env_scale)),
                    "to_world": T_env}
    if area_scale > 0:
        for i, a in enumerate(light.area_lights):
            d[f"area_light_{i}"] = {
                "type": "rectangle", "to_world": _transform(mi, a.T_world_light()),
                "emitter": {"type": "area", "radiance": {"type": "rgb",
                                                         "value": (np.asarray(a.radiance) * area_scale).tolist()}},
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            }
    shape_instances: dict[str, int] = {}
    table_info: dict[str, Any] = {}
    for g in desc.geoms:
        key = f"geom_{g.name}"
        if g.material == "glass":
            bsdf: dict[str, Any] = {"type": "dielectric", "int_ior": float(g.ior), "ext_ior": AIR_IOR}
        else:
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(g.rgb)}}
        if g.material == "table" and g.kind == "box":
            key = "table_body"
            tex = table_texture(desc.layout_seed, (2 * g.size[0], 2 * g.size[1]))
            table_info = {"pattern": tex.pattern, **tex.params}
            T_top = g.T_world_geom @ _scale_T([g.size[0], g.size[1], 1.0], [0, 0, g.size[2]])
            d["table_top"] = {"type": "rectangle", "to_world": _transform(mi, T_top),
                              "bsdf": {"type": "diffuse", "reflectance": {
                                  "type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(tex.image_hxwx3)),
                                  "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}}}
            mean = [float(c) for c in tex.image_hxwx3.reshape(-1, 3).mean(axis=0) * 0.6]
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": mean}}
            # the body sits 0.1 mm below the textured top so the two never fight
            T = g.T_world_geom @ _scale_T(g.size, [0, 0, -1e-4])
            d[key] = {"type": "cube", "to_world": _transform(mi, T), "bsdf": bsdf}
            continue
        if g.kind == "box":
            shape = {"type": "cube", "to_world": _transform(mi, g.T_world_geom @ _scale_T(g.size))}
        elif g.kind == "sphere":
            shape = {"type": "sphere", "radius": float(g.size[0]), "to_world": _transform(mi, g.T_world_geom)}
        elif g.kind == "plane":
            hx = g.size[0] if g.size[0] > 0 else INFINITE_PLANE_HALF
            hy = g.size[1] if g.size[1] > 0 else INFINITE_PLANE_HALF
            shape = {"type": "rectangle", "to_world": _transform(mi, g.T_world_geom @ _scale_T([hx, hy, 1.0]))}
        else:
            shape = {"type": "ply", "filename": str(mesh_ply(g)), "to_world": _transform(mi, g.T_world_geom),
                     "face_normals": False}
        shape["bsdf"] = bsdf
        shape["id"] = key
        d[key] = shape
        if g.instance > 0:
            shape_instances[key] = g.instance
    for k, v in d.items():
        if isinstance(v, dict) and v.get("type") in ("rectangle", "cube", "sphere", "ply"):
            v.setdefault("id", k)
    return PbrScene(d, shape_instances, desc, light, table_info)


def load_scene(pbr: PbrScene) -> Any:
    """``mi.load_dict(pbr.scene_dict, optimize=False)``: every shape keeps its own id (no merging)."""
    import mitsuba as mi

    return mi.load_dict(pbr.scene_dict, optimize=False)


def _scale_T(scale: Any, offset: Any = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) translate(offset) @ scale(scale), in the geom frame."""
    T = np.diag([float(scale[0]), float(scale[1]), float(scale[2]), 1.0])
    T[:3, 3] = offset
    return T
