"""``torm/TormGraspSelect-v0``: choose one of the grasp planner's top-K candidates for a target object.

A high-level, one-step env for comparing grasp-selection policies with TORM's own choice. At reset the
scene (scenario + layout seed) is built, perceived (``perception``: ``oracle`` = samples of the true meshes,
fast; ``torm`` = multi-view capture -> silhouettes -> reconstruction, slow; ``depth`` = the single-view
sensor-depth baseline) and planned with :func:`torm.grasp.planner.plan_grasps` (``top_k`` = K); one target
object is chosen. The action ``Discrete(K)`` picks a candidate: **index 0 is the planner's best (TORM's
choice)**, then in the planner's order. The step executes that grasp with
:func:`torm.execution.pick.execute_pick` (pre-grasp, approach, close, lift 25 cm, translate 20 cm towards
free table space, lower, release) and judges it by the paper's success test
(:func:`torm.execution.success.judge_pick`): reward 1.0 on success, else 0.0. Every episode is one step
(``terminated`` is always True after it). Choosing an index without a candidate (``valid[i] == 0``) gives
reward 0 with ``info["invalid_choice"]`` (nothing moves).

Observation (``Dict``), world frame (robot base, z up, m):

- ``candidates`` (K, F) float32, one row per candidate (zeros for missing ones), columns
  :data:`FEATURE_NAMES`: grasp centre minus the object centroid (3, m), approach direction (3), closing
  axis (3), opening width (m), fingertip depth beyond the centre (m), planner score (0..1), grasp centre
  height above the table (m), clearance = distance from the grasp centre to the nearest point of another
  object (m, capped at ``max_clearance``), tilt of the approach from straight down (rad), planner rank / K.
- ``valid`` (K,) int8: 1 where a candidate exists.
- ``object_summary`` (10,) float32 (:data:`SUMMARY_NAMES`): centroid (3, m), bounding-box size (3, m),
  principal standard deviations of the points (3, m, descending), number of candidates / K.
- ``object_points`` (M, 3) float32: M points of the target's perceived cloud relative to its centroid (m).

Seeding: ``reset(seed=s)`` uses layout seed ``s`` and seeds the target choice and the planner's sampling
from the env RNG; the same seed gives the same observation, and the same action the same outcome.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.spatial import cKDTree

from torm.config import with_options
from torm.env.errors import InvalidActionError
from torm.errors import ConfigError, ReconstructionError, UnknownNameError
from torm.execution.pick import PickConfig
from torm.execution.success import SuccessCriteria
from torm.grasp.planner import GraspPlannerConfig
from torm.types import Grasp, ObjectPointCloud, TriMesh

log = logging.getLogger(__name__)

PERCEPTIONS = ("oracle", "torm", "depth")
FEATURE_NAMES = ("dx", "dy", "dz", "approach_x", "approach_y", "approach_z", "closing_x", "closing_y", "closing_z",
                 "width", "depth", "score", "height", "clearance", "tilt", "rank")
#: Every feature is a distance (m), a unit-vector component, an angle (rad) or a fraction: |value| <= this.
FEATURE_BOUND = 10.0
SUMMARY_NAMES = ("cx", "cy", "cz", "size_x", "size_y", "size_z", "std_0", "std_1", "std_2", "n_candidates")


@dataclass(frozen=True)
class GraspSelectEnvConfig:
    """Settings of :class:`TormGraspSelectEnv` (m, s).

    Attributes:
        scenario: scenario name, e.g. "rw1".
        robot: robot folder name.
        layout_seed: fixed layout for unseeded resets; None draws one from the env RNG per reset.
        target_object: instance id of the object to pick; 0 = a random object that has candidates.
        perception: "oracle" (true meshes), "torm" (reconstruction) or "depth" (single-view sensor depth).
        top_k: K, candidates per object (the action space size).
        n_points: points per object cloud for "oracle" / "depth" perception.
        object_points: M, points of the target's cloud in the observation.
        max_clearance: cap of the clearance feature (m).
        n_views, capture_scale: capture for "torm" / "depth" perception (views; image scale of 1280x720).
        segmenter: silhouette source for "torm" ("gt", "noisy", "grounded_sam").
        planner: grasp planner settings (its ``top_k`` is replaced by ``top_k``).
        pick: pick execution settings.
        criteria: the success test's tolerances.
        render_size: (H, W) of ``render()`` images.
        realism: the harness's realism profile (``ideal``, ``measured``, ``stress``: contact, grip force, object
            mass, calibration and execution errors drawn per layout from the sourced ranges, :mod:`sim.realism`),
            so that a grasp choice can fail the way the harness's picks do; the drawn pad force replaces
            ``pick.grip_force``.
        stress: the multiplier of the ``stress`` profile.
    """

    scenario: str = "rw1"
    robot: str = "inovo_2f85"
    layout_seed: int | None = None
    target_object: int = 0
    perception: str = "oracle"
    top_k: int = 8
    n_points: int = 1024
    object_points: int = 64
    max_clearance: float = 0.3
    n_views: int = 50
    capture_scale: float = 0.5
    segmenter: str = "gt"
    planner: GraspPlannerConfig = field(default_factory=GraspPlannerConfig)
    pick: PickConfig = field(default_factory=PickConfig)
    criteria: SuccessCriteria = field(default_factory=SuccessCriteria)
    render_size: tuple[int, int] = (240, 320)
    realism: str = "ideal"
    stress: float = 1.0

    def __post_init__(self) -> None:
        from torm.pipeline import REALISM_PROFILES

        if self.realism not in REALISM_PROFILES:
            raise UnknownNameError("realism", self.realism, REALISM_PROFILES)
        if self.perception not in PERCEPTIONS:
            raise UnknownNameError("perception", self.perception, PERCEPTIONS)
        for name in ("top_k", "n_points", "object_points", "n_views"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"GraspSelectEnvConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.target_object < 0:
            raise ConfigError(f"GraspSelectEnvConfig.target_object must be >= 0 (0 = random), got {self.target_object}")
        if not self.max_clearance > 0 or not self.capture_scale > 0:
            raise ConfigError("GraspSelectEnvConfig.max_clearance and capture_scale must be positive")
        if self.layout_seed is not None and self.layout_seed < 0:
            raise ConfigError(f"GraspSelectEnvConfig.layout_seed must be >= 0 or None, got {self.layout_seed}")
        hw = tuple(int(v) for v in self.render_size)
        if len(hw) != 2 or min(hw) < 8:
            raise ConfigError(f"GraspSelectEnvConfig.render_size must be (H, W) >= 8 pixels, got {hw}")
        object.__setattr__(self, "render_size", hw)


def candidate_features(grasps: list[Grasp], centroid: np.ndarray, others_nx3: np.ndarray, top_k: int,
                       table_height: float = 0.0, max_clearance: float = 0.3) -> np.ndarray:
    """(K, F) float32 feature rows (:data:`FEATURE_NAMES`) of the first ``top_k`` grasps, zero rows after them.

    ``centroid`` (3,) is the object's centroid (m); ``others_nx3`` the other objects' points (m), may be empty.
    """
    out = np.zeros((top_k, len(FEATURE_NAMES)), np.float32)
    tree = cKDTree(others_nx3) if len(others_nx3) else None
    down = np.array([0.0, 0.0, -1.0])
    for i, g in enumerate(grasps[:top_k]):
        T = g.T_world_grasp
        t = T[:3, 3]
        clear = max_clearance if tree is None else min(max_clearance, float(tree.query(t)[0]))
        tilt = float(np.arccos(np.clip(T[:3, 0] @ down, -1.0, 1.0)))
        out[i] = np.concatenate([t - centroid, T[:3, 0], T[:3, 1],
                                 [g.width, g.depth, g.score, t[2] - table_height, clear, tilt, i / top_k]])
    return out


def object_summary(points_nx3: np.ndarray, n_candidates: int, top_k: int) -> np.ndarray:
    """(10,) float32 (:data:`SUMMARY_NAMES`): centroid, bounding-box size, principal std devs, candidates / K."""
    p = np.asarray(points_nx3, float)
    c = p.mean(axis=0)
    size = p.max(axis=0) - p.min(axis=0)
    std = np.sqrt(np.clip(np.linalg.eigvalsh(np.cov((p - c).T))[::-1], 0.0, None))
    return np.concatenate([c, size, std, [n_candidates / top_k]]).astype(np.float32)


class TormGraspSelectEnv(gym.Env):
    """High-level grasp-selection env (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(self, config: GraspSelectEnvConfig | dict | None = None, render_mode: str | None = None,
                 **options: Any) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise UnknownNameError("render_mode", render_mode, self.metadata["render_modes"])
        self.config = cfg = with_options(GraspSelectEnvConfig, config, options)
        self.render_mode = render_mode
        K, M = cfg.top_k, cfg.object_points
        self.action_space = spaces.Discrete(K)
        b = FEATURE_BOUND
        self.observation_space = spaces.Dict({
            "candidates": spaces.Box(-b, b, (K, len(FEATURE_NAMES)), np.float32),
            "valid": spaces.MultiBinary(K),
            "object_summary": spaces.Box(-b, b, (len(SUMMARY_NAMES),), np.float32),
            "object_points": spaces.Box(-b, b, (M, 3), np.float32),
        })
        self._planner_cfg = dataclasses.replace(cfg.planner, top_k=K)
        self._world = self._backend = self._render_cams = None
        self._layout: int | None = None
        self._grasps: list[Grasp] = []
        self._done = True

    # ------------------------------------------------------------------------------------------ properties
    @property
    def backend(self):
        """The :class:`sim.backend.SimBackend` of the current layout (None before the first reset)."""
        return self._backend

    @property
    def candidates(self) -> list[Grasp]:
        """The target object's planner candidates of this episode, best first (action i executes ``candidates[i]``)."""
        return list(self._grasps)

    @property
    def target_object(self) -> int:
        """Instance id of this episode's target object."""
        return self._target

    # ------------------------------------------------------------------------------------------ building
    def _build(self, layout: int) -> None:
        from sim.backend import SimBackend
        from sim.camera_rig import CameraRigConfig
        from sim.world import build_world
        from torm.execution.pick import ToolFrame

        cfg = self.config
        self._close_world()
        realism = None
        if cfg.realism != "ideal":  # drawn per layout from the sourced ranges, as a harness trial draws them
            from sim.realism import sample_realism
            from sim.scenes.objects import get_object
            from sim.scenes.scenario import get_scenario

            hollow = [get_object(n).hollow for n in get_scenario(cfg.scenario).objects]
            realism = sample_realism(cfg.realism, int(layout), hollow, stress=cfg.stress)
        world = build_world(cfg.scenario, int(layout), robot=cfg.robot, realism=realism)
        cam = CameraRigConfig(n_views=cfg.n_views, scale=cfg.capture_scale)
        backend = SimBackend(world, camera_config=cam, realism=realism)
        self._world, self._backend, self._layout = world, backend, int(layout)
        self._pick = cfg.pick
        if realism is not None and realism.grip_force_n is not None:
            lo, hi = backend.gripper.force_range_n
            self._pick = dataclasses.replace(cfg.pick, grip_force=min(max(float(realism.grip_force_n), lo), hi))
        self._tool = ToolFrame.from_robot_config(world.robot_config)
        if cfg.target_object > len(world.objects):
            raise ConfigError(f"target_object {cfg.target_object} but scenario {cfg.scenario!r} has objects "
                              f"1..{len(world.objects)}")
        if self.render_mode == "rgb_array":
            from torm.env.cameras import EnvCameras

            g = world.robot_config.gripper.geometry
            self._render_cams = EnvCameras(world.model, world.data, *cfg.render_size,
                                           tcp_site=world.robot_config.arm.tcp_site,
                                           approach_axis=str(g.approach_axis), closing_axis=str(g.closing_axis))

    def _close_world(self) -> None:
        if self._render_cams is not None:
            self._render_cams.close()
            self._render_cams = None
        if self._backend is not None:
            self._backend.close()
        self._world = self._backend = None
        self._layout = None

    def _true_meshes(self) -> dict[int, TriMesh]:
        w = self._world
        return {o.instance_id: TriMesh(m.vertices, m.faces) for o, m in zip(w.objects, w.object_meshes_world(),
                                                                          strict=True)}

    def _perceive(self, rng: np.random.Generator) -> tuple[list[ObjectPointCloud], list[TriMesh | None], dict]:
        """Per-object clouds labelled with the true instance ids (unmatched reconstructions get 1000 + k)."""
        from torm.perception import (
            depth_point_clouds,
            label_by_ground_truth,
            most_top_down_view,
            oracle_point_clouds,
            perceive_torm,
        )

        cfg = self.config
        truth = self._true_meshes()
        if cfg.perception == "oracle":
            clouds, meshes = oracle_point_clouds(truth, cfg.n_points, rng)
            return clouds, meshes, {}
        capture = self._backend.capture(cfg.n_views)
        if cfg.perception == "depth":
            view = most_top_down_view(capture)
            return depth_point_clouds(capture, view, cfg.n_points, rng), None, {"view": view}
        from torm.reconstruction.api import ReconstructionConfig
        from torm.segmentation import make_segmenter

        seg_opts = {"seed": int(rng.integers(2**31 - 1))} if cfg.segmenter == "noisy" else None
        per = perceive_torm(capture, make_segmenter(cfg.segmenter, seg_opts), ReconstructionConfig())
        clouds, matching = label_by_ground_truth(per.point_clouds, truth)
        return clouds, list(per.meshes), {"matching": matching, **per.info}

    # ------------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        from torm.execution.pick import make_ik_solver
        from torm.grasp.gripper import GripperGeometry
        from torm.grasp.planner import plan_grasps

        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"layout_seed", "target_object"}
        if unknown:
            raise UnknownNameError("reset option", sorted(unknown)[0], ["layout_seed", "target_object"])
        cfg = self.config
        if options.get("layout_seed") is not None:
            layout = int(options["layout_seed"])
        elif seed is not None:
            layout = int(seed)
        elif cfg.layout_seed is not None:
            layout = cfg.layout_seed
        else:
            layout = int(self.np_random.integers(0, 2**31 - 1))
        if layout != self._layout or self._backend is None:
            self._build(layout)
        else:
            self._backend.reset()
        self._ik = make_ik_solver(self._world.robot_config, cfg.pick.ik)  # fresh: no state carried over
        rng = np.random.default_rng(int(self.np_random.integers(0, 2**63 - 1)))
        info: dict[str, Any] = {"layout_seed": layout, "perception": cfg.perception}
        try:
            clouds, meshes, pinfo = self._perceive(rng)
        except ReconstructionError as exc:
            clouds, meshes, pinfo = [], [], {"error": str(exc)}
        info["perception_info"] = {k: v for k, v in pinfo.items() if isinstance(v, (int, float, str, bool))}
        gripper = GripperGeometry.from_robot_config(dataclasses.asdict(self._world.robot_config.gripper.geometry))
        table_z = float(self._world.table_height)
        grasps = plan_grasps(clouds, meshes, table_z, gripper, self._planner_cfg, rng) if clouds else []
        by_id = {c.object_index: (c, g) for c, g in zip(clouds, grasps, strict=True)}
        self._clouds = by_id
        target = int(options.get("target_object") or cfg.target_object)
        if target == 0:
            ids = sorted(k for k, (_, g) in by_id.items() if g and k < 1000) or [o.instance_id
                                                                                 for o in self._world.objects]
            target = int(ids[int(self.np_random.integers(len(ids)))])
        if not 1 <= target <= len(self._world.objects):
            raise ConfigError(f"target_object {target} but the scene has objects 1..{len(self._world.objects)}")
        self._target = target
        cloud, self._grasps = by_id.get(target, (None, []))
        self._grasps = list(self._grasps)[: cfg.top_k]
        if cloud is None:  # the target was not perceived: observe its true centroid only
            from torm.metrics import mesh_centroid

            c = mesh_centroid(self._true_meshes()[target])
            pts = np.tile(c, (cfg.object_points, 1))
        else:
            pts = cloud.points_nx3
        others = [c.points_nx3 for k, (c, _) in by_id.items() if k != target]
        self._others = np.concatenate(others) if others else np.zeros((0, 3))
        self._centroid = pts.mean(axis=0)
        sub = pts[np.linspace(0, len(pts) - 1, cfg.object_points).astype(int)]
        self._obs = {
            "candidates": candidate_features(self._grasps, self._centroid, self._others, cfg.top_k, table_z,
                                             cfg.max_clearance),
            "valid": (np.arange(cfg.top_k) < len(self._grasps)).astype(np.int8),
            "object_summary": object_summary(pts, len(self._grasps), cfg.top_k),
            "object_points": (sub - self._centroid).astype(np.float32),
        }
        info.update(target_object=target, n_candidates=len(self._grasps), perceived=cloud is not None,
                    scenario=cfg.scenario, layout_seed=self._layout, perception=cfg.perception, realism=cfg.realism,
                    grip_force_n=self._pick.grip_force)
        self._done = False
        return self._observation(), info

    def step(self, action):
        from torm.execution.pick import execute_pick, free_directions

        if self._backend is None or self._done:
            raise ConfigError("call reset() before step(); TormGraspSelect episodes are one step long")
        i = self._check_action(action)
        cfg = self.config
        self._done = True
        info: dict[str, Any] = {"target_object": self._target, "candidate": i, "invalid_choice": False}
        if i >= len(self._grasps):
            info.update(invalid_choice=True, outcome="no_grasp_found", is_success=False)
            return self._observation(), 0.0, True, False, info
        xy = self._centroid[:2]
        others_xy = [c.points_nx3[:, :2].mean(axis=0) for k, (c, _) in self._clouds.items() if k != self._target]
        dirs = free_directions(xy, others_xy, self._world.workspace_bounds, cfg.pick.translate_distance)
        from sim.judge import PickJudge

        judge = PickJudge(self._backend, cfg.criteria, self._pick)  # the reward is the judge's verdict
        try:
            loop_res = execute_pick(self._backend, [self._grasps[i]], dirs, self._pick, ik=self._ik, tool=self._tool,
                                    observer=judge)
        finally:
            judge.close()
        res = judge.verdicts.get(id(loop_res), loop_res)
        pick = res.as_dict()  # without wall-clock times, so equal seeds and actions give equal infos
        pick.pop("wall_time_s", None)
        pick["phases"] = [{"name": p["name"], "sim_s": p["sim_s"]} for p in pick["phases"]]
        info.update(outcome=res.outcome.value, is_success=res.success, pick=pick)
        return self._observation(), 1.0 if res.success else 0.0, True, False, info

    def render(self):
        if self.render_mode != "rgb_array" or self._render_cams is None:
            return None
        return self._render_cams.render(["scene"], depth=False)["scene_rgb"]

    def close(self) -> None:
        self._close_world()

    # ------------------------------------------------------------------------------------------ internals
    def _observation(self) -> dict[str, np.ndarray]:
        return {k: (np.clip(v, -FEATURE_BOUND, FEATURE_BOUND) if v.dtype == np.float32 else v.copy())
                for k, v in self._obs.items()}

    def _check_action(self, action) -> int:
        K = self.config.top_k
        a = np.asarray(action)
        if a.shape != () or not np.issubdtype(a.dtype, np.integer) or not 0 <= int(a) < K:
            raise InvalidActionError(f"action {action!r} is not a candidate index; valid actions are the integers "
                                     f"0..{K - 1} (Discrete({K}); 0 = the planner's best)")
        return int(a)
