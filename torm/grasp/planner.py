"""Collision-aware, batched per-object grasp planning (TORM Sec. III-C) and GraspNet export.

:func:`plan_grasps` plans grasps for every object of a reconstruction at once: antipodal candidates for
all objects in one vectorised pass (:mod:`torm.grasp.antipodal`), scores (:mod:`torm.grasp.score`), a
table check for all candidates, then per object, best first, the point-collision check against every
object's points (:mod:`torm.grasp.collision`) and greedy pose-space NMS until ``top_k`` grasps are found.
Scoring first and checking collisions lazily gives the same result as checking every candidate.

Output: one list per input point cloud (same order), best first. ``Grasp.object_id`` is the cloud's
``ObjectPointCloud.object_index``. An object without a collision-free grasp gets an empty list (a
recorded outcome downstream, never an exception). Grasp frame: origin at the grasp centre (contacts'
midpoint), x approach, y closing, z finger height (right-handed); ``width`` is the opening to command
before the approach (contact distance + ``width_margin``; collisions are checked at that opening),
``height`` the pad width, ``depth`` the fingertip position beyond the centre along x (m).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Protocol, runtime_checkable

import numpy as np
from scipy.spatial import cKDTree

from torm.config import Range, check_finite
from torm.errors import ConfigError, GraspError
from torm.grasp.antipodal import GraspCandidates, enumerate_grasps, sample_contact_pairs
from torm.grasp.collision import points_collision_free, table_collision_free
from torm.grasp.gripper import GripperGeometry
from torm.grasp.score import GreedyNMS, approach_quality, centre_quality, clearance_quality, depth_quality
from torm.resources import check_fits, grasp_bytes
from torm.types import Grasp, ObjectPointCloud, TriMesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GraspPlannerConfig:
    """Antipodal planner settings (metres, degrees where named ``_deg``).

    Attributes:
        n_samples: contact points drawn per object.
        friction_coef: Coulomb mu; both contact normals must lie within atan(mu) of the closing axis.
        n_approach_angles: approach directions per contact pair (rotations about the closing axis).
        max_tilt_deg: largest angle between the approach and straight down (90 = horizontal side grasps).
        depths: fingertip positions beyond the grasp centre along the approach (m); each <= finger_length.
        width_margin: opening = contact distance + this (m), clipped to the stroke.
        min_width_margin: pairs need contact distance <= max_opening - this (m).
        min_contact_distance: smallest accepted contact distance (m) (also >= the gripper's min_opening).
        search_radius: line-search radius (m) for the opposite contact in a point cloud.
        lateral_tolerance: largest offset (m) of the opposite contact from the closing line.
        use_meshes: cast rays against the meshes when they are given (else search the points).
        far_contacts: also pair contacts with the last exit within the stroke (grasps across cavities).
        table_clearance: every box must stay this far (m) above the table top.
        collision_margin: boxes are inflated by this (m) for the point-containment test.
        check_approach_sweep: also check the volume swept during the approach.
        w_antipodal, w_approach, w_centre, w_clearance, w_depth: score weights (>= 0, not all zero).
        clearance_scale: pad-to-obstacle distance (m) that earns a full clearance score.
        nms_translation: grasps closer than this (m) ...
        nms_angle_deg: ... and this rotation angle (deg) are duplicates.
        top_k: grasps kept per object.
        batch_size: candidates per collision-check block.
        seed: default seed of the contact sampling (a Generator passed to plan() wins).
    """

    n_samples: Annotated[int, Range(1, 65_536, "contacts per object; ~1 kB per sample, angle and depth")] = 256
    friction_coef: float = 0.5
    n_approach_angles: Annotated[int, Range(1, 360, "1 deg apart at 360; the duplicate filter merges 20 deg")] = 16
    max_tilt_deg: float = 90.0
    depths: tuple[float, ...] = (0.005, 0.01, 0.01875, 0.03)
    width_margin: float = 0.01
    min_width_margin: float = 0.002
    min_contact_distance: float = 0.002
    search_radius: float = 0.004
    lateral_tolerance: float = 0.006
    use_meshes: bool = True
    far_contacts: bool = True
    table_clearance: float = 0.002
    collision_margin: float = 0.001
    check_approach_sweep: bool = True
    w_antipodal: float = 1.0
    w_approach: float = 0.5
    w_centre: float = 0.3
    w_clearance: float = 0.3
    w_depth: float = 0.1
    clearance_scale: float = 0.03
    nms_translation: float = 0.01
    nms_angle_deg: float = 20.0
    top_k: Annotated[int, Range(1, 1000, "grasps kept per object")] = 5
    batch_size: Annotated[int, Range(1, 1 << 20, "candidates per collision block")] = 256
    seed: int = 0

    def __post_init__(self) -> None:
        check_finite(self, "GraspPlannerConfig")  # ranges and NaN / inf (torm.config), also when built in Python
        def positive(name: str, integer: bool = False) -> None:
            v = getattr(self, name)
            if (integer and (isinstance(v, bool) or not isinstance(v, int))) or not np.isfinite(v) or v <= 0:
                raise ConfigError(f"GraspPlannerConfig.{name} must be a positive {'integer' if integer else 'number'}"
                                  f", got {v!r}")

        for n in ("n_samples", "n_approach_angles", "top_k", "batch_size"):
            positive(n, integer=True)
        for n in ("friction_coef", "search_radius", "lateral_tolerance", "clearance_scale", "nms_translation"):
            positive(n)
        for n in ("width_margin", "min_width_margin", "min_contact_distance", "table_clearance", "collision_margin",
                  "w_antipodal", "w_approach", "w_centre", "w_clearance", "w_depth", "nms_angle_deg"):
            v = getattr(self, n)
            if not np.isfinite(v) or v < 0:
                raise ConfigError(f"GraspPlannerConfig.{n} must be a non-negative number, got {v!r}")
        if not 0.0 < self.max_tilt_deg <= 180.0:
            raise ConfigError(f"GraspPlannerConfig.max_tilt_deg must be in (0, 180], got {self.max_tilt_deg}")
        depths = tuple(float(d) for d in self.depths)
        if len(depths) > 64:
            raise ConfigError(f"GraspPlannerConfig.depths has {len(depths)} entries; give at most 64 depths "
                              "(default 4)")
        if not depths or any(not np.isfinite(d) or d < 0 for d in depths):
            raise ConfigError(f"GraspPlannerConfig.depths must be a non-empty list of non-negative metres, "
                              f"got {depths}")
        object.__setattr__(self, "depths", depths)
        if self.weight_sum <= 0:
            raise ConfigError("GraspPlannerConfig: at least one score weight (w_*) must be positive")

    @property
    def weight_sum(self) -> float:
        return self.w_antipodal + self.w_approach + self.w_centre + self.w_clearance + self.w_depth


@runtime_checkable
class GraspPlanner(Protocol):
    """Anything that turns per-object point clouds (and optional meshes) into per-object grasp lists."""

    def plan(self, point_clouds: Sequence[ObjectPointCloud], meshes: Sequence[TriMesh | None] | None = None,
             table_height: float = 0.0) -> list[list[Grasp]]:
        """One list per point cloud (input order), best first; empty when no collision-free grasp exists."""
        ...


@dataclass(eq=False)
class SceneGeometry:
    """Validated, stacked scene arrays shared by the planners.

    ``points`` / ``normals`` (K, N, 3) m; ``all_points`` (K*N, 3); ``com`` (K, 3) centre of mass (mesh
    volume centroid when a closed mesh is given, else the points' centroid); ``radius`` (K,) largest
    point distance from ``com``; ``others[k]`` a KD-tree of every other object's points (None when alone).
    """

    points: np.ndarray
    normals: np.ndarray
    object_ids: list[int]
    com: np.ndarray
    radius: np.ndarray
    others: list[cKDTree | None] = field(default_factory=list)

    @property
    def all_points(self) -> np.ndarray:
        return self.points.reshape(-1, 3)


def prepare_scene(point_clouds: Sequence[ObjectPointCloud], meshes: Sequence[TriMesh | None] | None = None,
                  ) -> SceneGeometry:
    """Stack and validate the clouds; GraspError names the bad object and the fix."""
    if meshes is not None and len(meshes) != len(point_clouds):
        raise GraspError(f"got {len(meshes)} meshes for {len(point_clouds)} point clouds; give one mesh per object "
                         "(None entries allowed) or meshes=None")
    counts = {len(pc.points_nx3) for pc in point_clouds}
    if len(counts) > 1:
        raise GraspError(f"point clouds have different point counts {sorted(counts)}; resample every object to the "
                         "same count (torm.mesh sampling) so they can be planned in one batch")
    K = len(point_clouds)
    N = counts.pop() if counts else 0
    if K and N == 0:
        raise GraspError("point clouds are empty; sample points on the object meshes first")
    if K == 0:
        return SceneGeometry(np.zeros((0, 0, 3)), np.zeros((0, 0, 3)), [], np.zeros((0, 3)), np.zeros(0), [])
    points = np.stack([np.asarray(pc.points_nx3, dtype=np.float64) for pc in point_clouds])
    normals = np.stack([np.asarray(pc.normals_nx3, dtype=np.float64) for pc in point_clouds])
    for k in range(K):
        if not (np.all(np.isfinite(points[k])) and np.all(np.isfinite(normals[k]))):
            raise GraspError(f"object {k}: point cloud has NaN/inf points or normals; drop them before planning")
    nn = np.linalg.norm(normals, axis=-1, keepdims=True)
    if K and np.any(nn < 1e-9):
        raise GraspError("some normals are zero; give unit outward normals (e.g. from the mesh faces)")
    normals = normals / np.maximum(nn, 1e-12)
    com = points.mean(axis=1) if K else np.zeros((0, 3))
    if meshes is not None:
        for k, m in enumerate(meshes):
            if m is None or m.is_empty:
                continue
            tm = m.to_trimesh()
            if tm.is_watertight and abs(tm.volume) > 1e-12:
                com[k] = tm.center_mass
    radius = np.array([np.linalg.norm(points[k] - com[k], axis=1).max() for k in range(K)])
    others: list[cKDTree | None] = []
    for k in range(K):
        rest = np.concatenate([points[j] for j in range(K) if j != k]) if K > 1 else np.zeros((0, 3))
        others.append(cKDTree(rest) if len(rest) else None)
    return SceneGeometry(points, normals, [int(pc.object_index) for pc in point_clouds], com, radius, others)


def select_grasps(cands: GraspCandidates, score: np.ndarray, scene: SceneGeometry, gripper: GripperGeometry,
                  table_height: float, config: GraspPlannerConfig, stats: dict[str, Any] | None = None,
                  obstacles: np.ndarray | None = None) -> list[list[Grasp]]:
    """Collision-free, NMS-filtered best ``top_k`` grasps per object from scored candidates.

    Table check for all candidates at once, then per object the point check in score order (lazy,
    ``batch_size`` at a time) against every object's points near the object (and the ``obstacles`` (M, 3)
    points of known fixtures, world frame, m), until ``top_k`` survive NMS.
    """
    K = len(scene.object_ids)
    out: list[list[Grasp]] = [[] for _ in range(K)]
    table_ok = table_collision_free(cands.R, cands.t, cands.width, cands.depth, gripper, table_height,
                                    config.table_clearance, config.check_approach_sweep)
    reach = gripper.reach_radius() + config.collision_margin
    all_pts = scene.all_points
    if obstacles is not None and len(obstacles):
        all_pts = np.concatenate([all_pts, np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)])
    n_checked = np.zeros(K, dtype=np.int64)
    n_hit = np.zeros(K, dtype=np.int64)
    for k in range(K):
        idx = np.nonzero((cands.obj == k) & table_ok & np.isfinite(score))[0]
        idx = idx[np.argsort(-score[idx], kind="stable")]
        if idx.size == 0:
            continue
        near = np.linalg.norm(all_pts - scene.com[k], axis=1) <= scene.radius[k] + reach
        pts = all_pts[near]
        nms = GreedyNMS(config.nms_translation, math.radians(config.nms_angle_deg), config.top_k)
        for s in range(0, len(idx), config.batch_size):
            b = idx[s:s + config.batch_size]
            free = points_collision_free(cands.R[b], cands.t[b], cands.width[b], cands.depth[b], gripper, pts,
                                         config.collision_margin, config.check_approach_sweep)
            n_checked[k] += len(b)
            n_hit[k] += int((~free).sum())
            for i in b[free]:
                nms.offer(int(i), cands.R[i], cands.t[i])
                if nms.full:
                    break
            if nms.full:
                break
        for i in nms.accepted:
            T = np.eye(4)
            T[:3, :3] = cands.R[i]
            T[:3, 3] = cands.t[i]
            out[k].append(Grasp(T, width=float(cands.width[i]), score=float(score[i]), object_id=scene.object_ids[k],
                                height=gripper.pad_width, depth=float(cands.depth[i])))
    if stats is not None:
        stats["candidates"] = [int(np.sum(cands.obj == k)) for k in range(K)]
        stats["table_free"] = [int(np.sum((cands.obj == k) & table_ok)) for k in range(K)]
        stats["point_checked"] = n_checked.tolist()
        stats["point_collisions"] = n_hit.tolist()
        stats["grasps"] = [len(g) for g in out]
    return out


def score_candidates(cands: GraspCandidates, scene: SceneGeometry, gripper: GripperGeometry,
                     config: GraspPlannerConfig) -> np.ndarray:
    """(C,) weighted score in [0, 1] (see :mod:`torm.grasp.score`)."""
    C = len(cands)
    score = config.w_antipodal * cands.antipodal + config.w_approach * approach_quality(cands.R)
    centre = np.zeros(C)
    clear = np.zeros(C)
    for k in range(len(scene.object_ids)):
        m = cands.obj == k
        if not np.any(m):
            continue
        centre[m] = centre_quality(cands.t[m], scene.com[k], scene.radius[k])
        if cands.pair is None:
            clear[m], _ = clearance_quality(cands.R[m], cands.t[m], cands.width[m], gripper, scene.others[k],
                                            config.clearance_scale)
        else:  # once per contact pair: the term does not depend on the approach angle or the depth
            pairs, first, inverse = np.unique(cands.pair[m], return_index=True, return_inverse=True)
            mi = np.flatnonzero(m)[first]
            q, _ = clearance_quality(cands.R[mi], cands.t[mi], cands.width[mi], gripper, scene.others[k],
                                     config.clearance_scale)
            clear[m] = q[inverse]
    score = score + config.w_centre * centre + config.w_clearance * clear
    score = score + config.w_depth * depth_quality(cands.depth, gripper)
    return score / config.weight_sum


class AntipodalGraspPlanner:
    """The analytic planner behind the :class:`GraspPlanner` protocol; ``last_stats`` holds counts and timings."""

    def __init__(self, gripper: GripperGeometry | None = None, config: GraspPlannerConfig | None = None,
                 rng: np.random.Generator | int | None = None) -> None:
        self.gripper = gripper or GripperGeometry()
        self.config = config or GraspPlannerConfig()
        for d in self.config.depths:
            if d > self.gripper.finger_length:
                raise ConfigError(f"GraspPlannerConfig.depths has {d} m > the gripper's finger_length "
                                  f"{self.gripper.finger_length} m; the palm would be in front of the grasp centre")
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(
            self.config.seed if rng is None else rng)
        self.last_stats: dict[str, Any] = {}

    def plan(self, point_clouds: Sequence[ObjectPointCloud], meshes: Sequence[TriMesh | None] | None = None,
             table_height: float = 0.0, obstacles: np.ndarray | None = None) -> list[list[Grasp]]:
        """See :func:`plan_grasps`; ``obstacles`` (M, 3) are points of known fixtures the gripper must miss (m)."""
        cfg, g = self.config, self.gripper
        t0 = time.perf_counter()
        scene = prepare_scene(point_clouds, meshes)
        if not scene.object_ids:
            return []
        need = grasp_bytes(len(scene.object_ids), cfg.n_samples, cfg.n_approach_angles, len(cfg.depths))
        check_fits(need, f"grasp.n_samples={cfg.n_samples} x grasp.n_approach_angles={cfg.n_approach_angles} x "
                   f"{len(cfg.depths)} depths for {len(scene.object_ids)} objects",
                   "lower grasp.n_samples or grasp.n_approach_angles (defaults 256 and 16)")
        pairs = sample_contact_pairs(
            scene.points, scene.normals, meshes if cfg.use_meshes else None,
            n_samples=cfg.n_samples, friction_coef=cfg.friction_coef,
            min_dist=max(cfg.min_contact_distance, g.min_opening), max_dist=g.max_opening - cfg.min_width_margin,
            search_radius=cfg.search_radius, lateral_tolerance=cfg.lateral_tolerance, rng=self.rng,
            far_contacts=cfg.far_contacts)
        t1 = time.perf_counter()
        cands = enumerate_grasps(pairs, g, n_angles=cfg.n_approach_angles, max_tilt_rad=math.radians(cfg.max_tilt_deg),
                                 depths=cfg.depths, width_margin=cfg.width_margin)
        score = score_candidates(cands, scene, g, cfg)
        t2 = time.perf_counter()
        stats: dict[str, Any] = {"pairs": [int(np.sum(pairs.obj == k)) for k in range(len(scene.object_ids))]}
        out = select_grasps(cands, score, scene, g, table_height, cfg, stats, obstacles)
        t3 = time.perf_counter()
        stats["timings_s"] = {"contacts": t1 - t0, "enumerate_score": t2 - t1, "collision_nms": t3 - t2,
                              "total": t3 - t0}
        self.last_stats = stats
        log.debug("grasp planning: %s", stats)
        return out


def plan_grasps(
    point_clouds: Sequence[ObjectPointCloud],
    meshes: Sequence[TriMesh | None] | None = None,
    table_height: float = 0.0,
    gripper: GripperGeometry | None = None,
    config: GraspPlannerConfig | None = None,
    rng: np.random.Generator | int | None = None,
    obstacles: np.ndarray | None = None,
) -> list[list[Grasp]]:
    """Plan collision-free antipodal grasps for every object at once (see the module docstring).

    Args:
        point_clouds: per-object surface samples with outward normals, world frame (m), same count each.
        meshes: optional per-object meshes (None entries allowed) for exact ray casting and the centre of mass.
        table_height: z of the table top (m); every gripper box must stay above it.
        gripper: gripper geometry (default: Robotiq 2F-85).
        config: planner settings.
        rng: Generator or seed for the contact sampling (default: ``config.seed``).
        obstacles: (M, 3) surface points of known static fixtures (a rack, a tray; world frame, m) that no gripper
            box may contain; they get no grasps themselves.

    Returns:
        One list per input cloud (input order), best first, at most ``config.top_k`` each; empty when the
        object has no collision-free grasp.
    """
    return AntipodalGraspPlanner(gripper, config, rng).plan(point_clouds, meshes, table_height, obstacles)


def grasps_to_graspnet(grasps: Sequence[Grasp]) -> np.ndarray:
    """(N, 17) float64 GraspNet rows ``[score, width, height, depth, R (9), t (3), object_id]``."""
    if not grasps:
        return np.zeros((0, 17))
    return np.stack([g.to_graspnet() for g in grasps])


def graspnet_to_grasps(rows_nx17: np.ndarray) -> list[Grasp]:
    """Inverse of :func:`grasps_to_graspnet`."""
    rows = np.asarray(rows_nx17, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 17:
        raise GraspError(f"GraspNet arrays are (N, 17), got shape {rows.shape}")
    return [Grasp.from_graspnet(r) for r in rows]


def save_graspnet(path: str | Path, grasps: Sequence[Grasp]) -> Path:
    """Save grasps as a GraspNet ``.npy`` (N, 17) array (graspnetAPI ``GraspGroup().from_npy`` reads it)."""
    p = Path(path)
    if p.suffix != ".npy":
        raise GraspError(f"{p}: GraspNet grasp files are .npy; use a name ending in .npy")
    p.parent.mkdir(parents=True, exist_ok=True)
    np.save(p, grasps_to_graspnet(grasps))
    return p


def load_graspnet(path: str | Path) -> list[Grasp]:
    """Load a GraspNet ``.npy`` (N, 17) file."""
    p = Path(path)
    if not p.is_file():
        raise GraspError(f"grasp file {p} does not exist")
    return graspnet_to_grasps(np.load(p))
