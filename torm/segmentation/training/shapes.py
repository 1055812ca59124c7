"""Procedural glass shapes for the segmenter's training set, and which library shapes are held out.

Three families, each drawn from a seeded ``numpy.random.Generator`` (sizes in m, object frame: z up,
lowest point at z = 0, footprint centred; every mesh is a watertight volume via ``meshes.finalize``):

``revolved``  solid of revolution of a smooth random radius profile r(z) (bottles, vases, bulbs, cones),
              or an open vessel (tumbler / tapered glass with a wall of 2-5 mm and a 4-10 mm base);
``extruded``  a star-shaped outline (regular 3-8-gon, ellipse, rounded rectangle or a radial Fourier blob)
              extruded straight up;
``primitive`` boxes of random aspect, spheres, cylinders / prisms, rounded boxes.

Footprint widths stay within 20-75 mm and heights within 15-130 mm (the library's range: the 25 mm heart to
the 100 mm cylinder; everything fits the 85 mm gripper like the library objects). About 10 % are opaque
(diffuse) so the network also segments opaque objects like the ceramic cup.

Held out from training entirely (measured as "unseen shapes"): :data:`HELD_OUT_SHAPES`.
"""

from __future__ import annotations

import numpy as np
import trimesh

from sim.scenes import meshes
from sim.scenes.objects import get_object, list_objects, register_object

#: Library shapes never seen in training (non-convex flat heart; sloped-face frustum).
HELD_OUT_SHAPES: tuple[str, ...] = ("heart", "pyramidal_frustum")
FAMILIES: tuple[str, ...] = ("revolved", "extruded", "primitive")


def train_library_objects() -> tuple[str, ...]:
    """Library object names allowed in training (all but :data:`HELD_OUT_SHAPES` by shape)."""
    return tuple(n for n in list_objects() if get_object(n).shape not in HELD_OUT_SHAPES and not n.startswith("proc_"))


def _smooth_profile(rng: np.random.Generator, height: float, r_max: float, n: int = 24) -> np.ndarray:
    """(n, 2) radius/height samples of a smooth positive profile (cubic through 3-5 random knots)."""
    k = int(rng.integers(3, 6))
    zk = np.linspace(0.0, 1.0, k)
    rk = rng.uniform(0.35, 1.0, k) * r_max
    z = np.linspace(0.0, 1.0, n)
    coef = np.polyfit(zk, rk, min(3, k - 1))
    r = np.clip(np.polyval(coef, z), 0.25 * r_max, r_max)
    return np.stack([r, z * height], axis=1)


def revolved(rng: np.random.Generator) -> trimesh.Trimesh:
    """A solid of revolution or an open vessel (see the module docstring)."""
    h = rng.uniform(0.03, 0.13)
    r_max = rng.uniform(0.012, 0.036)
    if rng.random() < 0.35:  # open vessel: straight or tapered wall
        r0 = r_max * rng.uniform(0.65, 1.0)
        wall, bottom = rng.uniform(0.002, 0.005), rng.uniform(0.004, 0.010)
        prof = np.array([[0.0, 0.0], [r0, 0.0], [r_max, h], [r_max - wall, h],
                         [r0 - wall * 1.2, bottom], [0.0, bottom]])
    else:
        rz = _smooth_profile(rng, h, r_max)
        prof = np.vstack([[0.0, 0.0], rz, [0.0, h]])
    return meshes.finalize(trimesh.creation.revolve(prof, sections=40))


def _outline(rng: np.random.Generator, size: float) -> np.ndarray:
    kind = rng.integers(4)
    n = 64
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    if kind == 0:  # regular polygon
        m = int(rng.integers(3, 9))
        t = np.linspace(0.0, 2 * np.pi, m, endpoint=False)
        return size / 2 * np.stack([np.cos(t), np.sin(t)], axis=1)
    if kind == 1:  # ellipse
        a = rng.uniform(0.5, 1.0)
        return size / 2 * np.stack([np.cos(t), a * np.sin(t)], axis=1)
    if kind == 2:  # rounded rectangle (superellipse)
        a, p = rng.uniform(0.45, 1.0), rng.uniform(3.0, 8.0)
        c, s = np.cos(t), np.sin(t)
        return size / 2 * np.stack([np.sign(c) * np.abs(c) ** (2 / p), a * np.sign(s) * np.abs(s) ** (2 / p)], axis=1)
    # radial Fourier blob (star-shaped by construction)
    r = np.ones(n)
    for f in range(2, 6):
        r += rng.uniform(-0.12, 0.12) * np.cos(f * t + rng.uniform(0, 2 * np.pi))
    return size / 2 * (r / r.max())[:, None] * np.stack([np.cos(t), np.sin(t)], axis=1)


def extruded(rng: np.random.Generator) -> trimesh.Trimesh:
    """A star-shaped outline 20-70 mm across extruded 15-110 mm."""
    return meshes.extrude_star_polygon(_outline(rng, rng.uniform(0.02, 0.07)), rng.uniform(0.015, 0.11))


def primitive(rng: np.random.Generator) -> trimesh.Trimesh:
    """A box, sphere, cylinder / prism or rounded box of random size."""
    kind = rng.integers(4)
    if kind == 0:
        ex = (rng.uniform(0.02, 0.06), rng.uniform(0.02, 0.06), rng.uniform(0.015, 0.12))
        return meshes.box(ex)
    if kind == 1:
        return meshes.ball(rng.uniform(0.012, 0.035))
    if kind == 2:
        return meshes.cylinder(rng.uniform(0.01, 0.035), rng.uniform(0.015, 0.12), int(rng.choice([5, 8, 12, 48])))
    side = rng.uniform(0.025, 0.06)
    return meshes.rounded_box(side, rng.uniform(0.002, 0.3 * side / 2 + 0.002))


_MAKERS = {"revolved": revolved, "extruded": extruded, "primitive": primitive}


def procedural_shape(index: int, seed: int = 0) -> tuple[str, trimesh.Trimesh, str, str]:
    """Shape ``index`` of the procedural set: (name ``proc_<index>``, mesh, family, material)."""
    rng = np.random.default_rng([seed, index])
    family = FAMILIES[index % len(FAMILIES)]
    mesh = _MAKERS[family](rng)
    material = "opaque" if rng.random() < 0.1 else "glass"
    return f"proc_{index:03d}", mesh, family, material


def register_procedural(n: int, seed: int = 0) -> list[str]:
    """Register ``proc_000 .. proc_<n-1>`` in the object library (idempotent); returns their names."""
    names = []
    for i in range(n):
        name, mesh, family, material = procedural_shape(i, seed)
        collision = "sphere" if family == "primitive" and _is_sphere(mesh) else "convex"
        register_object(name, mesh, material, collision, f"procedural {family} training shape")
        names.append(name)
    return names


def _is_sphere(mesh: trimesh.Trimesh) -> bool:
    ext = mesh.extents
    return bool(np.allclose(ext, ext[0], rtol=0.02)) and abs(mesh.volume / (np.pi / 6 * ext[0] ** 3) - 1) < 0.05
