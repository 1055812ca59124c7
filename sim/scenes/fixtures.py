"""Opaque lab fixtures that hold glassware: a test-tube rack and a tray (static boxes, known to the planner).

A fixture is a set of axis-aligned boxes in its own frame (z up, bottom on the table at z = 0, footprint centred
on x = y = 0), a ``floor`` (z of the surface its objects stand on) and where the objects go: ``slots`` (a rack's
holes, xy in the fixture frame) or an ``area`` (a tray's inside, [[x_min, y_min], [x_max, y_max]]). The world
builder adds it as a static body (rendered opaque, colliding), the placement puts the scenario's first
``fixture_objects`` objects into it, and the planner and the drop-off get its surface points as known obstacles
(a lab knows the geometry of its racks and trays). Units: metres.

- ``tube_rack``: one row of five 17 x 17 mm holes at a 35 mm pitch for 12-16 mm test tubes; 4 mm floor, a
  4 mm top plate at 56-60 mm, end walls. One row, so two fingers can close across it (a 2F-85 finger is 22 mm wide).
- ``tray``: a 208 x 148 mm tray (200 x 140 mm inside), 4 mm floor, 10 mm lip.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from torm.errors import UnknownNameError

if TYPE_CHECKING:
    from torm.backend.calibration import FixtureDeclaration

Box = tuple[tuple[float, float, float], tuple[float, float, float]]  # (centre xyz, half extents xyz), m


@dataclass(frozen=True)
class Fixture:
    """One fixture (see the module docstring); ``boxes`` are (centre, half extents) in the fixture frame (m)."""

    name: str
    boxes: tuple[Box, ...]
    floor: float
    slots: tuple[tuple[float, float], ...] = ()
    area: tuple[tuple[float, float], tuple[float, float]] | None = None
    description: str = ""

    @property
    def footprint(self) -> np.ndarray:
        """(4, 2) counter-clockwise rectangle around every box, fixture frame (m)."""
        lo = np.min([np.subtract(c, h)[:2] for c, h in self.boxes], axis=0)
        hi = np.max([np.add(c, h)[:2] for c, h in self.boxes], axis=0)
        return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])

    def surface_points(self, spacing: float = 0.004) -> np.ndarray:
        """(M, 3) points on every box face, at most ``spacing`` apart, fixture frame (m)."""
        from torm.backend.calibration import box_surface_points

        pts = [box_surface_points(np.asarray(c), np.asarray(h), spacing) for c, h in self.boxes]
        return np.unique(np.round(np.concatenate(pts), 6), axis=0)


def _tube_rack() -> Fixture:
    n, pitch, hole, wall, width = 5, 0.035, 0.017, 0.005, 0.040
    length = n * pitch + 2 * wall
    floor_t, top_lo, top_hi, end_h = 0.004, 0.056, 0.060, 0.060
    xs = (np.arange(n) - (n - 1) / 2) * pitch
    boxes: list[Box] = [((0.0, 0.0, floor_t / 2), (length / 2, width / 2, floor_t / 2))]
    for sx in (-1.0, 1.0):  # end walls
        boxes.append(((sx * (length / 2 - wall / 2), 0.0, end_h / 2), (wall / 2, width / 2, end_h / 2)))
    zc, hz = (top_lo + top_hi) / 2, (top_hi - top_lo) / 2
    rail = (width - hole) / 4  # half width of each long rail beside the holes
    for sy in (-1.0, 1.0):
        boxes.append(((0.0, sy * (hole / 2 + rail), zc), (length / 2, rail, hz)))
    # cross bars between (and outside) the holes
    edges = [-length / 2] + [float(v) for x in xs for v in (x - hole / 2, x + hole / 2)] + [length / 2]
    for x0, x1 in zip(edges[0::2], edges[1::2], strict=True):
        boxes.append((((x0 + x1) / 2, 0.0, zc), ((x1 - x0) / 2, hole / 2, hz)))
    return Fixture("tube_rack", tuple(boxes), floor=floor_t, slots=tuple((float(x), 0.0) for x in xs),
                   description="test-tube rack, one row of 5 holes (17 mm, pitch 35 mm), top plate at 56-60 mm")


def _tray() -> Fixture:
    ix, iy, wall, floor_t, lip = 0.200, 0.140, 0.004, 0.004, 0.010
    ox, oy = ix + 2 * wall, iy + 2 * wall
    boxes: list[Box] = [((0.0, 0.0, floor_t / 2), (ox / 2, oy / 2, floor_t / 2))]
    zc, hz = floor_t + lip / 2, lip / 2
    for s in (-1.0, 1.0):
        boxes.append(((s * (ox / 2 - wall / 2), 0.0, zc), (wall / 2, oy / 2, hz)))
        boxes.append(((0.0, s * (oy / 2 - wall / 2), zc), (ix / 2, wall / 2, hz)))
    return Fixture("tray", tuple(boxes), floor=floor_t, area=((-ix / 2, -iy / 2), (ix / 2, iy / 2)),
                   description="lab tray 208 x 148 mm (200 x 140 mm inside), 4 mm floor, 10 mm lip")


_FIXTURES = {"tube_rack": _tube_rack, "tray": _tray}


def list_fixtures() -> list[str]:
    """Names of the fixtures, sorted."""
    return sorted(_FIXTURES)


@functools.cache
def get_fixture(name: str) -> Fixture:
    """The fixture ``name``; UnknownNameError lists the valid names."""
    if name not in _FIXTURES:
        raise UnknownNameError("fixture", name, _FIXTURES)
    return _FIXTURES[name]()


def pose_matrix(x: float, y: float, yaw: float) -> np.ndarray:
    """(4, 4) ``T_world_fixture`` of a fixture standing on the table top (z = 0) at (x, y) turned by ``yaw``."""
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, 0.0]
    return T


@dataclass(frozen=True, eq=False)
class PlacedFixture:
    """A fixture standing on the table: its definition and ``T_world_fixture`` (4, 4)."""

    fixture: Fixture
    T_world_fixture: np.ndarray

    @property
    def name(self) -> str:
        return self.fixture.name

    def declaration(self) -> FixtureDeclaration:
        """What a lab declares about this fixture: its boxes (from its drawing) and its pose on the table."""
        from torm.backend.calibration import FixtureDeclaration

        return FixtureDeclaration(self.name, self.T_world_fixture, boxes=self.fixture.boxes)

    def surface_points(self, spacing: float = 0.004) -> np.ndarray:
        """(M, 3) points on its faces in the world frame (m): the known obstacle the planner avoids."""
        p = self.fixture.surface_points(spacing)
        return p @ self.T_world_fixture[:3, :3].T + self.T_world_fixture[:3, 3]

    def footprint_world(self) -> np.ndarray:
        """(4, 2) its footprint rectangle in world xy (m)."""
        return self.fixture.footprint @ self.T_world_fixture[:2, :2].T + self.T_world_fixture[:2, 3]
