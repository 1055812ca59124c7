"""Object library: the paper's glass objects (plus an opaque ceramic cup) with realistic sizes.

All objects fit an 85 mm parallel-jaw gripper (narrowest footprint width <= 70 mm). Each object is a
watertight trimesh in its own frame (z up, lowest point at z = 0, footprint centred on x = y = 0).
Mass = mesh volume x density (glass 2500 kg/m^3, ceramic 2300 kg/m^3); the inertia tensor comes
from the same mesh (trimesh, uniform density), so simulated mass properties match the geometry.

Collision geometry (``collision`` field):

- ``"sphere"``: a sphere primitive (the ball: rolls and rests like a real sphere);
- ``"convex"``: the mesh's own convex hull. Used for convex solids (cylinder, cube, hexagonal prism,
  pyramidal frustum, ice cube) and for the lidded toothpick box, whose cavity is closed and so
  unreachable; CoACD would only return the same hull;
- ``"coacd"``: CoACD convex decomposition, cached on disk (see :mod:`sim.scenes.hulls`). Used where
  concavities matter: the open cup (a ball dropped in must stay inside) and the heart's notch.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh

from sim.scenes import meshes
from sim.scenes.hulls import CoacdParams, convex_decomposition
from torm.errors import UnknownNameError

GLASS_DENSITY = 2500.0  # kg/m^3 (soda-lime glass)
BOROSILICATE_DENSITY = 2230.0  # kg/m^3 (borosilicate 3.3: DURAN / Pyrex laboratory glass)
CERAMIC_DENSITY = 2300.0  # kg/m^3 (porcelain/stoneware)
#: Index of refraction of the glass objects (soda-lime, the usual rounded 1.5) and of borosilicate lab glassware
#: (SCHOTT DURAN data sheet: n_d = 1.473); used by the physically based renderer.
GLASS_IOR = 1.5
BOROSILICATE_IOR = 1.473


@dataclass(frozen=True)
class Substance:
    """What an object is made of: density (kg/m^3) and, for glass, the refractive index n_d a renderer reads.

    Sources: soda-lime glass 2.5 g/cm^3 (REALISM.md), n_d 1.5 (soda-lime float glass is 1.52; the renderer's
    issue fixes the rounded 1.5); borosilicate 3.3
    2.23 g/cm^3 and n_d 1.473 (SCHOTT DURAN data sheet, REALISM.md); ceramic 2.3 g/cm^3 (porcelain/stoneware).
    """

    name: str
    density: float
    ior: float | None
    transparent: bool


SUBSTANCES: dict[str, Substance] = {
    "soda_lime": Substance("soda_lime", GLASS_DENSITY, GLASS_IOR, True),
    "borosilicate": Substance("borosilicate", BOROSILICATE_DENSITY, BOROSILICATE_IOR, True),
    "ceramic": Substance("ceramic", CERAMIC_DENSITY, None, False),
}

Material = Literal["glass", "opaque"]
Collision = Literal["sphere", "convex", "coacd"]


@dataclass(frozen=True, eq=False)
class ObjectAsset:
    """One library object. ``mesh`` is in the object frame (m); derived mass properties in kg, m, kg m^2."""

    name: str
    shape: str  # geometry id (objects sharing a shape share meshes and cached hulls, e.g. cup / opaque_cup)
    mesh: trimesh.Trimesh
    material: Material
    density: float  # kg/m^3
    collision: Collision
    description: str = ""
    hollow: bool = False  # thin-walled (a vessel or a closed shell), not a solid piece of glass
    substance: str = "soda_lime"  # key of SUBSTANCES (density, refractive index)

    @property
    def ior(self) -> float | None:
        """Refractive index n_d of the object's glass (None for opaque objects), for physically based renderers."""
        return SUBSTANCES[self.substance].ior

    @property
    def transparent(self) -> bool:
        """True for glass objects (rendered in geom group 2; opaque ones in group 4)."""
        return self.material == "glass"

    @property
    def volume(self) -> float:
        """Material volume (m^3); for the cup and the toothpick box the cavity is excluded."""
        return float(self.mesh.volume)

    @property
    def mass(self) -> float:
        """Mass (kg) = volume x density."""
        return self.volume * self.density

    @property
    def com(self) -> np.ndarray:
        """Centre of mass (3,) in the object frame (m)."""
        return np.asarray(self.mesh.center_mass, dtype=np.float64)

    @property
    def inertia_3x3(self) -> np.ndarray:
        """Inertia tensor (3, 3) about the centre of mass, object-frame axes (kg m^2)."""
        return np.asarray(self.mesh.moment_inertia, dtype=np.float64) * self.density

    @property
    def height(self) -> float:
        """Height above the table when standing upright (m)."""
        return float(self.mesh.bounds[1, 2])

    @property
    def footprint_kx2(self) -> np.ndarray:
        """Convex footprint polygon (k, 2), counter-clockwise, object frame (m)."""
        return footprint_polygon(self.mesh)

    @property
    def width(self) -> float:
        """Footprint width (m): diameter of the circle with the footprint's area (cylinder 60 mm)."""
        return float(2.0 * np.sqrt(polygon_area(self.footprint_kx2) / np.pi))

    def collision_hulls(self) -> list[trimesh.Trimesh]:
        """Convex collision pieces in the object frame (cached; CoACD only for ``collision == "coacd"``)."""
        return list(_collision_hulls(self.name))


def footprint_polygon(mesh: trimesh.Trimesh) -> np.ndarray:
    """Counter-clockwise convex hull (k, 2) of the mesh vertices projected on the xy plane (m)."""
    pts = np.unique(np.round(np.asarray(mesh.vertices)[:, :2], 9), axis=0)
    return _convex_hull_2d(pts)


def _convex_hull_2d(pts_nx2: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain; returns counter-clockwise hull vertices (k, 2)."""
    pts = sorted(map(tuple, pts_nx2))

    def cross(o: tuple, a: tuple, b: tuple) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.asarray(lower[:-1] + upper[:-1], dtype=np.float64)


def polygon_area(poly_kx2: np.ndarray) -> float:
    """Signed area (m^2) of a polygon (positive when counter-clockwise)."""
    x, y = poly_kx2[:, 0], poly_kx2[:, 1]
    return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


@dataclass(frozen=True)
class _Entry:
    shape: str
    make: Callable[[], trimesh.Trimesh]
    material: Material
    density: float
    collision: Collision
    description: str
    hollow: bool = False
    substance: str = "soda_lime"
    coacd: CoacdParams | None = None  # None: the defaults (CoacdParams())


_CUP_MESH = functools.partial(meshes.open_cup, radius=0.035, height=0.090, wall=0.003, bottom=0.006)

_LIBRARY: dict[str, _Entry] = {
    "cylinder": _Entry("cylinder", functools.partial(meshes.cylinder, 0.030, 0.100), "glass", GLASS_DENSITY,
                       "convex", "solid glass cylinder, r 30 mm, h 100 mm"),
    "cup": _Entry("cup", _CUP_MESH, "glass", GLASS_DENSITY, "coacd",
                  "open-top glass cup, r 35 mm, h 90 mm, 3 mm wall, 6 mm base", hollow=True),
    "opaque_cup": _Entry("cup", _CUP_MESH, "opaque", CERAMIC_DENSITY, "coacd",
                         "opaque ceramic cup, same geometry as 'cup'", hollow=True, substance="ceramic"),
    "ball": _Entry("ball", functools.partial(meshes.ball, 0.030), "glass", GLASS_DENSITY, "sphere",
                   "solid glass ball, r 30 mm"),
    "cube": _Entry("cube", functools.partial(meshes.box, (0.050, 0.050, 0.050)), "glass", GLASS_DENSITY, "convex",
                   "solid glass cube, 50 mm"),
    "hexagonal_prism": _Entry("hexagonal_prism", functools.partial(meshes.cylinder, 0.030, 0.080, 6), "glass",
                              GLASS_DENSITY, "convex",
                              "solid glass hexagonal prism, 60 mm across corners (52 mm across flats), h 80 mm"),
    "pyramidal_frustum": _Entry("pyramidal_frustum", functools.partial(meshes.frustum, 0.060, 0.030, 0.060), "glass",
                                GLASS_DENSITY, "convex",
                                "solid glass square frustum, base 60 mm, top 30 mm, h 60 mm"),
    "heart": _Entry("heart", functools.partial(meshes.heart, 0.050, 0.025), "glass", GLASS_DENSITY, "coacd",
                    "solid glass heart lying flat, 50 mm wide, 25 mm thick"),
    "ice_cube": _Entry("ice_cube", functools.partial(meshes.rounded_box, 0.035, 0.006), "glass", GLASS_DENSITY,
                       "convex", "solid glass ice cube, 35 mm, 6 mm edge radius"),
    "toothpick_box": _Entry("toothpick_box", functools.partial(meshes.closed_box_shell, (0.060, 0.040, 0.080), 0.003),
                            "glass", GLASS_DENSITY, "convex",
                            "closed (lidded) glass toothpick box, 60 x 40 x 80 mm, 3 mm walls", hollow=True),
}

# Laboratory glassware (borosilicate 3.3 unless named). Dimensions from catalogue data: DURAN low-form beakers
# (DIN EN ISO 3819): 50 mL 42 x 60 mm, 100 mL 50 x 70 mm, 250 mL 70 x 95 mm (outer diameter x height); walls chosen
# so the 50 mL beaker weighs 37 g (REALISM.md: 35-45 g). Narrow-neck Erlenmeyer 100 mL (DIN EN ISO 1773): 64 mm
# base, 105 mm high, 22 mm neck. Test tubes 12 x 100 mm and 16 x 160 mm on DURAN tubing walls 1.0 and 1.2 mm.
# 20 mL scintillation vial 28 x 61 mm, 24 mm neck. Graduated cylinder 25 mL (ISO 4788 tall form): 22 mm tube,
# 170 mm high, 55 mm round glass foot (under the 0.20 m reconstruction box). Petri dish 60 x 15 mm with its lid on.
# White-wine glass (soda-lime): 70 mm foot, 8 mm stem, 70 mm bowl, 56 mm rim, about 170 mm high. Spouts, rim beads
# and threads are omitted.
_THIN = CoacdParams(threshold=0.02)  # thin walls: a finer concavity threshold keeps the cavities open
_LIBRARY.update({
    "beaker_50ml": _Entry("beaker_50ml", functools.partial(meshes.beaker, 0.042, 0.060, 0.0018, 0.0025), "glass",
                          BOROSILICATE_DENSITY, "coacd", "50 mL low-form beaker, 42 x 60 mm, 1.8 mm wall",
                          hollow=True, substance="borosilicate", coacd=_THIN),
    "beaker_100ml": _Entry("beaker_100ml", functools.partial(meshes.beaker, 0.050, 0.070, 0.0018, 0.0025), "glass",
                           BOROSILICATE_DENSITY, "coacd", "100 mL low-form beaker, 50 x 70 mm, 1.8 mm wall",
                           hollow=True, substance="borosilicate", coacd=_THIN),
    "beaker_250ml": _Entry("beaker_250ml", functools.partial(meshes.beaker, 0.070, 0.095, 0.0018, 0.0026), "glass",
                           BOROSILICATE_DENSITY, "coacd", "250 mL low-form beaker, 70 x 95 mm, 1.8 mm wall",
                           hollow=True, substance="borosilicate", coacd=_THIN),
    "erlenmeyer_100ml": _Entry("erlenmeyer_100ml",
                               functools.partial(meshes.erlenmeyer, 0.064, 0.105, 0.022, 0.025, 0.0015, 0.002),
                               "glass", BOROSILICATE_DENSITY, "coacd",
                               "100 mL narrow-neck Erlenmeyer flask, 64 mm base, 105 mm high, 22 mm neck, 1.5 mm wall",
                               hollow=True, substance="borosilicate", coacd=_THIN),
    "test_tube_12x100": _Entry("test_tube_12x100", functools.partial(meshes.test_tube, 0.012, 0.100, 0.0010), "glass",
                               BOROSILICATE_DENSITY, "coacd", "round-bottom test tube 12 x 100 mm, 1.0 mm wall",
                               hollow=True, substance="borosilicate", coacd=_THIN),
    "test_tube_16x160": _Entry("test_tube_16x160", functools.partial(meshes.test_tube, 0.016, 0.160, 0.0012), "glass",
                               BOROSILICATE_DENSITY, "coacd", "round-bottom test tube 16 x 160 mm, 1.2 mm wall",
                               hollow=True, substance="borosilicate", coacd=_THIN),
    "vial_20ml": _Entry("vial_20ml", functools.partial(meshes.vial, 0.028, 0.061, 0.024, 0.010, 0.0012, 0.0015),
                        "glass", BOROSILICATE_DENSITY, "coacd", "20 mL screw-neck vial, 28 x 61 mm, 24 mm neck, no cap",
                        hollow=True, substance="borosilicate", coacd=_THIN),
    "measuring_cylinder_25ml": _Entry("measuring_cylinder_25ml",
                                      functools.partial(meshes.measuring_cylinder, 0.022, 0.170, 0.055, 0.006, 0.0015),
                                      "glass", BOROSILICATE_DENSITY, "coacd",
                                      "25 mL graduated cylinder, 22 mm tube, 170 mm high, 55 mm round glass foot",
                                      hollow=True, substance="borosilicate", coacd=_THIN),
    "petri_dish_60": _Entry("petri_dish_60", functools.partial(meshes.closed_dish, 0.060, 0.015, 0.0015, 0.0015, 0.003),
                            "glass", BOROSILICATE_DENSITY, "convex", "60 x 15 mm glass Petri dish with its lid on",
                            hollow=True, substance="borosilicate"),
    "wine_glass": _Entry("wine_glass",
                         functools.partial(meshes.stemmed_glass, 0.070, 0.004, 0.008, 0.070, 0.070, 0.095, 0.056,
                                           0.0012),
                         "glass", GLASS_DENSITY, "coacd",
                         "stemmed white-wine glass, 70 mm bowl, 56 mm rim, 8 mm stem, 1.2 mm wall, about 170 mm high",
                         hollow=True, coacd=_THIN),
})

#: The laboratory glassware of the library (the ``lab`` suite uses these).
GLASSWARE: tuple[str, ...] = ("beaker_50ml", "beaker_100ml", "beaker_250ml", "erlenmeyer_100ml", "test_tube_12x100",
                              "test_tube_16x160", "vial_20ml", "measuring_cylinder_25ml", "petri_dish_60",
                              "wine_glass")


def list_objects() -> list[str]:
    """Names of all library objects, sorted."""
    return sorted(_LIBRARY)


@functools.cache
def _shape_mesh(name: str) -> trimesh.Trimesh:
    return _LIBRARY[name].make()


def get_object(name: str) -> ObjectAsset:
    """The library object ``name``; raises UnknownNameError listing valid names."""
    if name not in _LIBRARY:
        raise UnknownNameError("object", name, _LIBRARY)
    e = _LIBRARY[name]
    return ObjectAsset(name=name, shape=e.shape, mesh=_shape_mesh(name).copy(), material=e.material,
                       density=e.density, collision=e.collision, description=e.description, hollow=e.hollow,
                       substance=e.substance)


@functools.cache
def _collision_hulls(name: str) -> tuple[trimesh.Trimesh, ...]:
    e = _LIBRARY[name]
    mesh = _shape_mesh(name)
    if e.collision == "coacd":
        return tuple(convex_decomposition(e.shape, mesh, e.coacd))
    if e.collision == "convex":
        return (mesh.convex_hull,)
    return ()  # "sphere": the world builder adds a primitive


def build_hull_cache(write_repo_cache: bool = True) -> dict[str, int]:
    """(Re)build the CoACD hull cache of every "coacd" shape; returns {shape: number of hulls}.

    Run after changing a mesh or the CoACD parameters, then commit ``sim/scenes/hull_cache/``:
    ``python -c "from sim.scenes.objects import build_hull_cache; print(build_hull_cache())"``.
    """
    out: dict[str, int] = {}
    for name, e in _LIBRARY.items():
        if e.collision == "coacd" and e.shape not in out:
            out[e.shape] = len(convex_decomposition(e.shape, _shape_mesh(name), e.coacd,
                                                    write_repo_cache=write_repo_cache))
    return out


def register_object(name: str, mesh: trimesh.Trimesh, material: Material = "glass", collision: Collision = "convex",
                    description: str = "", density: float | None = None) -> None:
    """Add a generated object (e.g. a procedural training shape) to the library under ``name``.

    ``mesh`` must be a watertight volume in the object frame (run it through ``meshes.finalize``); density
    defaults to glass / ceramic by ``material``. Re-registering a name with an identical mesh is a no-op;
    a different mesh under an existing name raises ValueError (the mesh and hull caches are keyed by name).
    Only ``"convex"`` and ``"sphere"`` collisions are allowed (CoACD hulls are cached for library shapes only).
    """
    if collision not in ("convex", "sphere"):
        raise ValueError(f"register_object({name!r}): collision must be 'convex' or 'sphere', got {collision!r}")
    if name in _LIBRARY:
        old = _shape_mesh(name)
        if old.vertices.shape == mesh.vertices.shape and np.allclose(old.vertices, mesh.vertices):
            return
        raise ValueError(f"object {name!r} is already in the library with a different mesh")
    frozen = mesh.copy()
    rho = density if density is not None else (GLASS_DENSITY if material == "glass" else CERAMIC_DENSITY)
    _LIBRARY[name] = _Entry(name, lambda: frozen.copy(), material, rho, collision, description)
