"""Seeded 2D placement of a scenario's objects on the table (x, y, yaw per object).

Objects are represented by their convex footprints (xy convex hull of the mesh, rotated by yaw). The
gap between two objects is the exact distance between their footprint polygons (m). For a pair with
mean footprint width ``w`` (see :attr:`ObjectAsset.width`, ~60 mm for the cylinder):

- ``moderate``: every gap >= max(min_gap, 1.0 w); each new object sits within 2.0 w of an anchor;
- ``dense``:    every gap >= max(min_gap, 0.35 w); each new object sits within max(30 mm, 0.6 w) of an
  anchor (about half an object width, so views occlude each other), with ``min_gap`` = 20 mm so a
  gripper finger still fits between objects.
- ``packed``:   gaps between 0.15 w (at least 5 mm) and 0.45 w: below half an object width, often
  narrower than a 2F-85 finger (the ``syn_hard`` suite and lab trays).

Fixture scenes (``Scenario.fixture``): the fixture's pose is drawn first (its footprint inside the
workspace), its objects go into random rack slots or are placed in the tray's inside like a scene of
their own, then the other objects are placed on the table at least ``min_gap`` from the fixture.

Objects are placed one by one next to a random already-placed anchor (the first uniformly in the
workspace). Every footprint lies fully inside the workspace rectangle. A failed object gets
``tries_per_object`` attempts, then the whole layout is re-sampled, up to ``max_layouts`` times, and
finally SceneError names the scenario and the attempts made.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sim.scenes.fixtures import get_fixture
from sim.scenes.objects import ObjectAsset, get_object
from sim.scenes.scenario import Scenario, get_scenario
from torm.errors import ConfigError, SceneError

WORKSPACE_XY = np.array([[0.35, -0.20], [0.75, 0.20]])  # [[x_min, y_min], [x_max, y_max]] (m)


@dataclass(frozen=True)
class GapRule:
    """Gap range relative to the pair's mean footprint width ``w``: [max(min_gap, lo*w), max(hi_floor, hi*w)] (m)."""

    lo: float
    hi: float
    hi_floor: float = 0.0
    min_gap: float | None = None  # overrides PlacementConfig.min_gap for this rule (m)

    def __post_init__(self) -> None:
        if not 0.0 <= self.lo <= self.hi:
            raise ConfigError(f"GapRule: need 0 <= lo <= hi, got lo={self.lo}, hi={self.hi}")
        if self.min_gap is not None and self.min_gap < 0:
            raise ConfigError(f"GapRule.min_gap must be >= 0 m, got {self.min_gap}")


@dataclass(frozen=True)
class PlacementConfig:
    """Placement parameters (m, rad); ``workspace_xy`` is [[x_min, y_min], [x_max, y_max]]."""

    moderate: GapRule = GapRule(1.0, 2.0)
    dense: GapRule = GapRule(0.35, 0.6, hi_floor=0.030)
    packed: GapRule = GapRule(0.15, 0.45, min_gap=0.005)
    min_gap: float = 0.020
    workspace_xy: tuple[tuple[float, float], tuple[float, float]] = ((0.35, -0.20), (0.75, 0.20))
    tries_per_object: int = 200
    max_layouts: int = 200

    def __post_init__(self) -> None:
        (x0, y0), (x1, y1) = self.workspace_xy
        if not (x0 < x1 and y0 < y1):
            raise ConfigError(f"PlacementConfig.workspace_xy: min must be < max, got {self.workspace_xy}")
        if self.min_gap < 0 or self.tries_per_object < 1 or self.max_layouts < 1:
            raise ConfigError("PlacementConfig: min_gap >= 0, tries_per_object >= 1 and max_layouts >= 1 required")

    def gap_range(self, spacing: str, width: float) -> tuple[float, float]:
        """(minimum gap, anchor gap upper bound) in m for a pair of mean footprint width ``width`` (m)."""
        rule = {"dense": self.dense, "packed": self.packed}.get(spacing, self.moderate)
        lo = max(self.min_gap if rule.min_gap is None else rule.min_gap, rule.lo * width)
        return lo, max(lo, rule.hi_floor, rule.hi * width)


@dataclass(frozen=True)
class Placement:
    """Table pose of one object: its frame origin at (x, y, 0) in the world, rotated by ``yaw`` about z (m, rad)."""

    x: float
    y: float
    yaw: float
    z: float = 0.0  # height of the surface it stands on above the table top (m): a fixture's floor, else 0


@dataclass(frozen=True)
class Layout:
    """A placed scene: one :class:`Placement` per object (scenario order) and the fixture's pose (None without)."""

    objects: list[Placement]
    fixture: Placement | None = None


def footprint_world(asset: ObjectAsset, pose: Placement) -> np.ndarray:
    """The object's convex footprint (k, 2) in world xy (m) at ``pose``."""
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    R = np.array([[c, -s], [s, c]])
    return asset.footprint_kx2 @ R.T + np.array([pose.x, pose.y])


def polygons_intersect(a_kx2: np.ndarray, b_mx2: np.ndarray) -> bool:
    """Separating-axis test for two convex polygons (touching counts as intersecting)."""
    for poly in (a_kx2, b_mx2):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
        pa, pb = a_kx2 @ normals.T, b_mx2 @ normals.T
        if np.any((pa.max(axis=0) < pb.min(axis=0)) | (pb.max(axis=0) < pa.min(axis=0))):
            return False
    return True


def _point_segment_dist(p_nx2: np.ndarray, a_mx2: np.ndarray, b_mx2: np.ndarray) -> np.ndarray:
    ab = b_mx2 - a_mx2  # (m, 2)
    ap = p_nx2[:, None, :] - a_mx2[None, :, :]  # (n, m, 2)
    t = np.clip(np.sum(ap * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-18), 0.0, 1.0)
    d = ap - t[..., None] * ab
    return np.sqrt(np.sum(d * d, axis=-1))  # (n, m)


def polygon_gap(a_kx2: np.ndarray, b_mx2: np.ndarray) -> float:
    """Distance (m) between two convex polygons; 0 when they touch or overlap."""
    if polygons_intersect(a_kx2, b_mx2):
        return 0.0
    d1 = _point_segment_dist(a_kx2, b_mx2, np.roll(b_mx2, -1, axis=0)).min()
    d2 = _point_segment_dist(b_mx2, a_kx2, np.roll(a_kx2, -1, axis=0)).min()
    return float(min(d1, d2))


def pairwise_gaps(assets: list[ObjectAsset], poses: list[Placement]) -> np.ndarray:
    """Symmetric (n, n) matrix of footprint gaps (m); the diagonal is +inf."""
    fps = [footprint_world(a, p) for a, p in zip(assets, poses, strict=True)]
    n = len(fps)
    gaps = np.full((n, n), np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            gaps[i, j] = gaps[j, i] = polygon_gap(fps[i], fps[j])
    return gaps


def _inside(fp_kx2: np.ndarray, ws: np.ndarray) -> bool:
    return bool(np.all(fp_kx2 >= ws[0]) and np.all(fp_kx2 <= ws[1]))


def place_objects(
    scenario: Scenario | str, rng: np.random.Generator | int, config: PlacementConfig | None = None
) -> list[Placement]:
    """Sample one pose per scenario object (scenario order) satisfying the spacing rules; see module doc."""
    return place_scene(scenario, rng, config).objects


def place_scene(
    scenario: Scenario | str, rng: np.random.Generator | int, config: PlacementConfig | None = None
) -> Layout:
    """Sample the scene's layout: object poses (scenario order) and, for a fixture scene, the fixture's pose."""
    sc = get_scenario(scenario)
    cfg = scenario_rules(sc, config or PlacementConfig())
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    assets = [get_object(n) for n in sc.objects]
    ws = np.asarray(cfg.workspace_xy, dtype=np.float64)
    if sc.poses is not None:
        return Layout(_check_fixed(sc, assets, ws))
    n = len(assets)
    for _layout in range(cfg.max_layouts):
        if sc.fixture is None:
            poses = _place_group(list(range(n)), assets, ws, sc.spacing, rng, cfg, [])
            if poses is not None:
                return Layout([poses[k][0] for k in range(n)])
            continue
        layout = _place_fixture_scene(sc, assets, ws, rng, cfg)
        if layout is not None:
            return layout
    raise SceneError(
        f"scenario {sc.name!r}: could not place {n} objects with {sc.spacing!r} spacing in the workspace after "
        f"{cfg.max_layouts} layouts x {cfg.tries_per_object} attempts per object; use fewer or smaller objects, "
        "'moderate' spacing, or fixed poses"
    )


def scenario_rules(sc: Scenario, cfg: PlacementConfig) -> PlacementConfig:
    """``cfg`` with the scenario's own gap range (``Scenario.gap``, object widths) as its spacing class's rule."""
    if sc.gap is None:
        return cfg
    name = sc.spacing if sc.spacing in ("dense", "packed") else "moderate"
    base: GapRule = getattr(cfg, name)
    return replace(cfg, **{name: GapRule(sc.gap[0], sc.gap[1], base.hi_floor, base.min_gap)})


def _place_group(ids: list[int], assets: list[ObjectAsset], ws: np.ndarray, spacing: str, rng: np.random.Generator,
                 cfg: PlacementConfig, obstacles: list[np.ndarray]) -> dict[int, tuple[Placement, np.ndarray]] | None:
    """One attempt to place objects ``ids`` in the rectangle ``ws`` (anchor-based, module doc); None on failure.

    ``obstacles``: convex polygons (k, 2) every footprint keeps at least ``cfg.min_gap`` from (a fixture).
    """
    widths = {k: assets[k].width for k in ids}
    fps0 = {k: assets[k].footprint_kx2 for k in ids}
    order = [ids[i] for i in rng.permutation(len(ids))]
    poses: dict[int, tuple[Placement, np.ndarray]] = {}
    for k in order:
        ok = False
        for _try in range(cfg.tries_per_object):
            yaw = float(rng.uniform(0.0, 2.0 * np.pi))
            R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            local = fps0[k] @ R.T
            if not poses:
                lo, hi = ws[0] - local.min(axis=0), ws[1] - local.max(axis=0)
                if np.any(hi < lo):
                    continue
                xy = rng.uniform(lo, hi)
                anchor = None
            else:
                anchor = int(rng.choice(list(poses)))
                w = 0.5 * (widths[k] + widths[anchor])
                g = rng.uniform(*cfg.gap_range(spacing, w))
                theta = rng.uniform(0.0, 2.0 * np.pi)
                d = 0.5 * (widths[k] + widths[anchor]) + g
                xy = np.array([poses[anchor][0].x, poses[anchor][0].y]) + d * np.array([np.cos(theta), np.sin(theta)])
            fp = local + xy
            if not _inside(fp, ws):
                continue
            if anchor is not None:
                w = 0.5 * (widths[k] + widths[anchor])
                if polygon_gap(fp, poses[anchor][1]) > cfg.gap_range(spacing, w)[1]:
                    continue
            if any(polygon_gap(fp, ob) < cfg.min_gap for ob in obstacles):
                continue
            if all(
                polygon_gap(fp, poses[j][1]) >= cfg.gap_range(spacing, 0.5 * (widths[k] + widths[j]))[0]
                for j in poses
            ):
                poses[k] = (Placement(float(xy[0]), float(xy[1]), yaw), fp)
                ok = True
                break
        if not ok:
            return None
    return poses


def _to_world(T: np.ndarray, p: Placement, z: float, yaw0: float) -> Placement:
    xy = T[:2, :2] @ np.array([p.x, p.y]) + T[:2, 3]
    return Placement(float(xy[0]), float(xy[1]), float((p.yaw + yaw0) % (2.0 * np.pi)), z)


def _place_fixture_scene(sc: Scenario, assets: list[ObjectAsset], ws: np.ndarray, rng: np.random.Generator,
                         cfg: PlacementConfig) -> Layout | None:
    """One attempt at a fixture scene: the fixture, its objects, then the table objects; None on failure."""
    from sim.scenes.fixtures import pose_matrix

    fx = get_fixture(sc.fixture)
    yaw0 = float(rng.uniform(0.0, 2.0 * np.pi))
    R = np.array([[np.cos(yaw0), -np.sin(yaw0)], [np.sin(yaw0), np.cos(yaw0)]])
    local = fx.footprint @ R.T
    lo, hi = ws[0] - local.min(axis=0), ws[1] - local.max(axis=0)
    if np.any(hi < lo):
        return None
    xy0 = rng.uniform(lo, hi)
    T = pose_matrix(float(xy0[0]), float(xy0[1]), yaw0)
    fixture_fp = local + xy0
    inner = list(range(sc.fixture_objects))
    out: dict[int, Placement] = {}
    if fx.slots:
        if len(inner) > len(fx.slots):
            raise SceneError(f"scenario {sc.name!r}: {len(inner)} objects for the {len(fx.slots)} slots of "
                             f"{fx.name!r}; put fewer objects in the fixture")
        for k, s in zip(inner, rng.choice(len(fx.slots), size=len(inner), replace=False), strict=True):
            sx, sy = fx.slots[int(s)]
            out[k] = _to_world(T, Placement(sx, sy, float(rng.uniform(0.0, 2.0 * np.pi))), fx.floor, yaw0)
    elif inner:
        placed = _place_group(inner, assets, np.asarray(fx.area, dtype=np.float64), sc.spacing, rng, cfg, [])
        if placed is None:
            return None
        out.update({k: _to_world(T, p, fx.floor, yaw0) for k, (p, _) in placed.items()})
    rest = list(range(sc.fixture_objects, len(assets)))
    if rest:
        placed = _place_group(rest, assets, ws, sc.spacing, rng, cfg, [fixture_fp])
        if placed is None:
            return None
        out.update({k: p for k, (p, _) in placed.items()})
    return Layout([out[k] for k in range(len(assets))], Placement(float(xy0[0]), float(xy0[1]), yaw0))


def _check_fixed(sc: Scenario, assets: list[ObjectAsset], ws: np.ndarray) -> list[Placement]:
    poses = [Placement(float(x), float(y), float(yaw)) for x, y, yaw in sc.poses or ()]
    for k, (a, p) in enumerate(zip(assets, poses, strict=True), start=1):
        if not _inside(footprint_world(a, p), ws):
            raise SceneError(
                f"scenario {sc.name!r}: fixed pose of object {k} ({a.name}) at ({p.x:.3f}, {p.y:.3f}) leaves the "
                f"workspace x [{ws[0, 0]}, {ws[1, 0]}], y [{ws[0, 1]}, {ws[1, 1]}]; move it inside"
            )
    gaps = pairwise_gaps(assets, poses)
    i, j = np.unravel_index(np.argmin(gaps), gaps.shape) if len(poses) > 1 else (0, 0)
    if len(poses) > 1 and gaps[i, j] <= 0.0:
        raise SceneError(
            f"scenario {sc.name!r}: fixed poses of objects {i + 1} ({assets[i].name}) and {j + 1} "
            f"({assets[j].name}) overlap; move them apart"
        )
    return poses
