"""``torm/TormGraspSelect-v0``: choose one of the grasp planner's top-K candidates for a perceived object.

A high-level, one-step env for comparing grasp-selection policies with TORM's own choice, in the harness's world.
At reset a scenario (``scenario``, or one drawn from ``suite``) is built at a layout seed, with the harness's
realism profile, renderer and depth model (:func:`torm.pipeline.make_backend`); it is perceived and planned by the
harness's own loop functions (:func:`torm.loop.perceive`, :func:`torm.loop.plan_with_planner`) on the loop's view
of the backend (:class:`torm.backend.blind.LoopBackend`), which refuses ground truth: ``perception`` = ``oracle``
(samples of the true meshes, granted explicitly), ``torm`` (capture -> silhouettes from ``segmenter`` ->
reconstruction), ``depth`` (single-view sensor depth) or ``depth_fusion``. The table height is the cell's declared
one (or fitted to the capture with ``table="capture"``), fixtures reach the planner through their declaration. One
perceived object with candidates becomes the target (a phantom reconstruction can be one, as on a real robot).

The action ``Discrete(K)`` picks a candidate: **index 0 is the planner's best (TORM's choice)**, then in the
planner's order. The step executes that grasp with :func:`torm.execution.pick.execute_pick` (pre-grasp, approach,
close, lift 25 cm, translate 20 cm towards free table space, lower, release); the simulator's judge
(:class:`sim.judge.PickJudge`) decides from the physics what happened, by the paper's success test: reward 1.0 on
success, else 0.0 (a grasp at a phantom is ``phantom_attempt``). Every episode is one step (``terminated`` is
always True after it). Choosing an index without a candidate (``valid[i] == 0``) gives reward 0 with
``info["invalid_choice"]`` (nothing moves).

Observation (``Dict``), world frame (robot base, z up, m), all from perception:

- ``candidates`` (K, F) float32, one row per candidate (zeros for missing ones), columns
  :data:`FEATURE_NAMES`: grasp centre minus the object centroid (3, m), approach direction (3), closing
  axis (3), opening width (m), fingertip depth beyond the centre (m), planner score (0..1), grasp centre
  height above the table (m), clearance = distance from the grasp centre to the nearest point of another
  perceived object (m, capped at ``max_clearance``), tilt of the approach from straight down (rad), planner rank / K.
- ``valid`` (K,) int8: 1 where a candidate exists.
- ``object_summary`` (10,) float32 (:data:`SUMMARY_NAMES`): centroid (3, m), bounding-box size (3, m),
  principal standard deviations of the points (3, m, descending), number of candidates / K.
- ``object_points`` (M, 3) float32: M points of the target's perceived cloud relative to its centroid (m).

``obs_mode`` adds sensor data the way :class:`torm.env.pick_env.TormPickEnv` names it (ManiSkill's vocabulary),
from the env's fixed overview camera at reset (``image_size``): ``state`` (the keys above only), ``rgb``
(+ ``overview_rgb`` (H, W, 3) uint8), ``rgbd`` (+ ``overview_depth`` (H, W) float32 m), ``pointcloud``
(+ ``pointcloud_xyz`` (N, 3) float32 world m and ``pointcloud_rgb`` (N, 3) uint8, N = ``pointcloud_points``). None of
these is ground truth. ``privileged_state=True`` adds ``true_target`` (4,) float32: the position (m) of the real
object nearest the target's perceived centroid and 1.0, or zeros when none lies within
:data:`PHANTOM_DISTANCE` (a phantom); for privileged baselines and analysis, never for a policy meant for a robot.

``info`` at reset names the scenario, layout seed, perception, segmenter, renderer, depth model, realism profile
(and its draw), the pad force used and the perception's timings; after the step, the outcome, ``is_success``, the
real object the judge saw picked (``picked_object``, None for a phantom) and the pick's record.

Seeding: ``reset(seed=s)`` uses layout seed ``s``; the scenario draw, the perception's and planner's sampling and
the target choice come from the env RNG seeded by ``s``, so the same seed gives the same observation and the same
action the same outcome. Perception and planning of the current layout are cached per seed (both are
deterministic), so resetting the same seed again only resets the physics.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.spatial import cKDTree

from torm.config import with_options
from torm.env.errors import InvalidActionError
from torm.errors import ConfigError, ReconstructionError, UnknownNameError
from torm.execution.pick import PickConfig
from torm.execution.success import SuccessCriteria
from torm.grasp.gripper import GripperGeometry
from torm.grasp.planner import GraspPlannerConfig
from torm.runtime import close_at_exit
from torm.types import Grasp, ObjectPointCloud

if TYPE_CHECKING:
    from torm.pipeline import TrialConfig

log = logging.getLogger(__name__)

PERCEPTIONS = ("oracle", "torm", "depth", "depth_fusion")
FEATURE_NAMES = ("dx", "dy", "dz", "approach_x", "approach_y", "approach_z", "closing_x", "closing_y", "closing_z",
                 "width", "depth", "score", "height", "clearance", "tilt", "rank")
#: Every feature is a distance (m), a unit-vector component, an angle (rad) or a fraction: |value| <= this.
FEATURE_BOUND = 10.0
#: observation modes, as :mod:`torm.env.pick_env` and ManiSkill name them (``obs_mode``)
OBS_MODES = ("state", "rgb", "rgbd", "pointcloud")
#: A perceived target farther than this (m) from every real object is a phantom in ``true_target``.
PHANTOM_DISTANCE = 0.05
SUMMARY_NAMES = ("cx", "cy", "cz", "size_x", "size_y", "size_z", "std_0", "std_1", "std_2", "n_candidates")


@dataclass(frozen=True)
class GraspSelectEnvConfig:
    """Settings of :class:`TormGraspSelectEnv` (m, s).

    The world, perception and planning are the harness's (:class:`torm.pipeline.TrialConfig`): the convenience
    fields below set the usual ones, ``trial_overrides`` any other (``section.key=value``, as ``torm trial --set``).

    Attributes:
        scenario: scenario name, e.g. "rw1" (used when ``suite`` is empty).
        suite: draw the scenario of every reset from this suite (``rw``, ``syn``, ``syn_hard``, ``lab``; ``torm scenes
            list``), uniformly with the env RNG; empty = always ``scenario``.
        robot: robot folder name.
        layout_seed: fixed layout for unseeded resets; None draws one from the env RNG per reset.
        perception: the harness's method: "oracle" (samples of the true meshes, granted by the simulator), "torm"
            (capture -> silhouettes -> reconstruction), "depth" (single-view sensor depth) or "depth_fusion".
        segmenter: silhouette source of "torm" (``gt``, ``noisy``, ``learned``, ``grounded_sam``, ``difference``).
        renderer: ``mujoco`` or ``pbr`` (images for image-based segmenters).
        depth_model: the simulated depth camera (``ideal``, ``statistical``, ``stereo``).
        realism: the world's realism profile (``ideal``, ``measured``, ``stress``: contact, grip force, object mass,
            calibration and execution errors drawn per layout from sourced ranges, :mod:`sim.realism`); the drawn
            pad force replaces ``pick.grip_force``.
        stress: the multiplier of the ``stress`` profile.
        table: where the table height comes from: ``declared`` (the cell's declaration) or ``capture`` (fitted).
        top_k: K, candidates per object (the action space size).
        n_points: points per object cloud (``reconstruction.points_per_object``).
        object_points: M, points of the target's cloud in the observation.
        max_clearance: cap of the clearance feature (m).
        n_views, capture_scale: capture for image/depth perception (views; image scale of 1280x720).
        planner: grasp planner settings (its ``top_k`` is replaced by ``top_k``).
        pick: pick execution settings.
        criteria: the success test's tolerances.
        render_size: (H, W) of ``render()`` images.
        obs_mode: ``state``, ``rgb``, ``rgbd`` or ``pointcloud`` (:data:`OBS_MODES`, the module docstring).
        image_size: (H, W) of the overview camera's observation images (pixels).
        pointcloud_points: N, points of ``pointcloud_xyz`` (drawn from the overview camera's depth pixels).
        privileged_state: add ``true_target`` (ground truth) to the observation.
        trial_overrides: further ``section.key=value`` settings of the trial config (e.g.
            ``("segmentation.options.model=/path/seg.onnx",)``); they win over the fields above.
    """

    scenario: str = "rw1"
    suite: str = ""
    robot: str = "inovo_2f85"
    layout_seed: int | None = None
    perception: str = "oracle"
    segmenter: str = "gt"
    renderer: str = "mujoco"
    depth_model: str = "ideal"
    realism: str = "ideal"
    stress: float = 1.0
    table: str = "declared"
    top_k: int = 8
    n_points: int = 1024
    object_points: int = 64
    max_clearance: float = 0.3
    n_views: int = 50
    capture_scale: float = 0.5
    planner: GraspPlannerConfig = field(default_factory=GraspPlannerConfig)
    pick: PickConfig = field(default_factory=PickConfig)
    criteria: SuccessCriteria = field(default_factory=SuccessCriteria)
    render_size: tuple[int, int] = (240, 320)
    obs_mode: str = "state"
    image_size: tuple[int, int] = (96, 96)
    pointcloud_points: int = 1024
    privileged_state: bool = False
    trial_overrides: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.perception not in PERCEPTIONS:
            raise UnknownNameError("perception", self.perception, PERCEPTIONS)
        if self.obs_mode not in OBS_MODES:
            raise UnknownNameError("obs_mode", self.obs_mode, OBS_MODES)
        for name in ("top_k", "n_points", "object_points", "n_views", "pointcloud_points"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"GraspSelectEnvConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not self.max_clearance > 0 or not self.capture_scale > 0:
            raise ConfigError("GraspSelectEnvConfig.max_clearance and capture_scale must be positive")
        if self.layout_seed is not None and self.layout_seed < 0:
            raise ConfigError(f"GraspSelectEnvConfig.layout_seed must be >= 0 or None, got {self.layout_seed}")
        hw = tuple(int(v) for v in self.render_size)
        if len(hw) != 2 or min(hw) < 8:
            raise ConfigError(f"GraspSelectEnvConfig.render_size must be (H, W) >= 8 pixels, got {hw}")
        object.__setattr__(self, "render_size", hw)
        ihw = tuple(int(v) for v in self.image_size)
        if len(ihw) != 2 or min(ihw) < 8 or max(ihw) > 1024:
            raise ConfigError(f"GraspSelectEnvConfig.image_size must be (H, W) in 8..1024 pixels, got {ihw}")
        object.__setattr__(self, "image_size", ihw)
        object.__setattr__(self, "trial_overrides", tuple(str(o) for o in self.trial_overrides))
        if self.suite:
            from sim.scenes.scenario import list_scenarios, list_suites

            if self.suite not in list_suites():
                raise UnknownNameError("suite", self.suite, list_suites())
            object.__setattr__(self, "_scenarios", tuple(list_scenarios(self.suite)))
        else:
            object.__setattr__(self, "_scenarios", (self.scenario,))
        self.trial_config(self._scenarios[0], 0)  # every harness setting is checked now, not at the first reset

    @property
    def scenarios(self) -> tuple[str, ...]:
        """The scenarios resets draw from (``suite``'s, or ``scenario`` alone)."""
        return self._scenarios

    def trial_config(self, scenario: str, layout: int) -> TrialConfig:
        """The harness's trial config of one layout: the world, capture, perception and planning this env uses."""
        from torm.config import from_dict, to_dict
        from torm.pipeline import TrialConfig

        data = {"scenario": scenario, "seed": int(layout), "method": self.perception, "robot": self.robot,
                "table": self.table, "world": {"realism": self.realism, "stress": self.stress},
                "capture": {"n_views": self.n_views, "scale": self.capture_scale, "renderer": self.renderer,
                            "depth_model": self.depth_model},
                "segmentation": {"segmenter": self.segmenter},
                "reconstruction": {"points_per_object": self.n_points},
                "grasp": {**to_dict(self.planner), "top_k": self.top_k}, "pick": to_dict(self.pick),
                "success": to_dict(self.criteria)}
        return from_dict(TrialConfig, data, self.trial_overrides, where="GraspSelectEnvConfig.trial_overrides")


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
        from torm.env.cameras import MAX_DEPTH

        H, W = cfg.image_size
        extra: dict[str, spaces.Space] = {}
        if cfg.obs_mode in ("rgb", "rgbd"):
            extra["overview_rgb"] = spaces.Box(0, 255, (H, W, 3), np.uint8)
        if cfg.obs_mode == "rgbd":
            extra["overview_depth"] = spaces.Box(0.0, MAX_DEPTH, (H, W), np.float32)
        if cfg.obs_mode == "pointcloud":
            extra["pointcloud_xyz"] = spaces.Box(-b, b, (cfg.pointcloud_points, 3), np.float32)
            extra["pointcloud_rgb"] = spaces.Box(0, 255, (cfg.pointcloud_points, 3), np.uint8)
        if cfg.privileged_state:
            extra["true_target"] = spaces.Box(-b, b, (4,), np.float32)
        self.observation_space = spaces.Dict({**self.observation_space.spaces, **extra})
        self._backend = self._loop = self._render_cams = self._obs_cams = None
        self._key: tuple[str, int] | None = None
        self._perceived: tuple[Any, ...] | None = None
        self._grasps: list[Grasp] = []
        self._obs: dict[str, np.ndarray] | None = None
        self._done = True

    # ------------------------------------------------------------------------------------------ properties
    @property
    def backend(self):
        """The full :class:`sim.backend.SimBackend` of the current layout, ground truth included (for evaluation,
        rendering and tests; the env's perception and execution use only its loop view). None before a reset."""
        return self._backend

    @property
    def trial(self):
        """The :class:`torm.pipeline.TrialConfig` of the current layout (None before the first reset)."""
        return self._trial

    @property
    def candidates(self) -> list[Grasp]:
        """The target's planner candidates of this episode, best first (action i executes ``candidates[i]``)."""
        return list(self._grasps)

    @property
    def target_label(self) -> int:
        """Perception label (1000 + k) of this episode's target reconstruction."""
        return self._target

    # ------------------------------------------------------------------------------------------ building
    def _build(self, scenario: str, layout: int) -> None:
        from torm.backend.blind import LoopBackend
        from torm.execution.pick import ToolFrame
        from torm.pipeline import make_backend

        cfg = self.config
        self._close_world()
        self._trial = trial = cfg.trial_config(scenario, layout)
        backend = make_backend(trial)
        from torm.loop import grants_masks

        loop = LoopBackend(backend, grant_masks=grants_masks(trial))  # captures without ground truth unless declared
        self._backend, self._loop, self._key = backend, loop, (scenario, int(layout))
        self._perceived = None
        self._pick = trial.pick
        realism = getattr(backend, "realism", None)
        if realism is not None and realism.grip_force_n is not None:  # as run_trial: the drawn pad force is used
            lo, hi = backend.gripper.force_range_n
            self._pick = dataclasses.replace(trial.pick, grip_force=min(max(float(realism.grip_force_n), lo), hi))
        self._tool = ToolFrame.from_robot_config(backend.robot_config)
        world = backend.world
        g = world.robot_config.gripper.geometry
        kw = {"tcp_site": world.robot_config.arm.tcp_site, "approach_axis": str(g.approach_axis),
              "closing_axis": str(g.closing_axis)}
        if self.render_mode == "rgb_array" or cfg.obs_mode != "state":
            from torm.env.cameras import EnvCameras

            if self.render_mode == "rgb_array":
                self._render_cams = EnvCameras(world.model, world.data, *cfg.render_size, **kw)
            if cfg.obs_mode != "state":
                self._obs_cams = EnvCameras(world.model, world.data, *cfg.image_size, **kw)

    def _close_world(self) -> None:
        for cams in (self._render_cams, self._obs_cams):
            if cams is not None:
                cams.close()
        self._render_cams = self._obs_cams = None
        if self._backend is not None:
            self._backend.close()
        self._backend = self._loop = None
        self._key = None
        self._trial = None

    def _perceive_and_plan(self, perception_seed: int) -> tuple[Any, ...]:
        """Perceive and plan through the harness's loop functions on the loop's view of the backend (no ground
        truth; the oracle's meshes are granted explicitly). Cached per (layout, seed): both are deterministic."""
        if self._perceived is not None and self._perceived[0] == perception_seed:
            return self._perceived
        from torm.loop import perceive, plan_with_planner
        from torm.perception import Perception

        trial, rng = self._trial, np.random.default_rng(perception_seed)
        oracle = self._backend.ground_truth.object_meshes if trial.method == "oracle" else None
        timings: dict[str, float] = {}
        try:
            per = perceive(trial, self._loop, rng, timings, oracle_meshes=oracle)
            table_z = float(per.info["capture"].table_height)
        except ReconstructionError as exc:
            per, table_z = Perception([], [], {"error": str(exc)}), float(self._loop.calibration.table_height)
        for k, c in enumerate(per.point_clouds):  # perception labels, as the loop gives them: 1000, 1001, ...
            per.point_clouds[k] = ObjectPointCloud(c.points_nx3, c.normals_nx3, 1000 + k)
        gripper = GripperGeometry.from_robot_config(dataclasses.asdict(self._loop.robot_config.gripper.geometry))
        obstacles = self._loop.calibration.obstacle_points()
        grasps = plan_with_planner(trial, per, table_z, gripper, rng, obstacles) if per.point_clouds else []
        info = {k: v for k, v in per.info.items() if isinstance(v, (int, float, str, bool))}
        info["table_height_m"] = table_z
        info.update({f"{k}_s": v for k, v in timings.items()})
        self._perceived = (perception_seed, per.point_clouds, [list(g) for g in grasps], table_z, obstacles, info)
        return self._perceived

    # ------------------------------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        from torm.execution.pick import make_ik_solver

        super().reset(seed=seed)
        options = dict(options or {})
        valid_opts = ["layout_seed", "scenario", "target"]
        unknown = set(options) - set(valid_opts)
        if unknown:
            raise UnknownNameError("reset option", sorted(unknown)[0], valid_opts)
        cfg = self.config
        if options.get("layout_seed") is not None:
            layout = int(options["layout_seed"])
        elif seed is not None:
            layout = int(seed)
        elif cfg.layout_seed is not None:
            layout = cfg.layout_seed
        else:
            layout = int(self.np_random.integers(0, 2**31 - 1))
        scenario = str(options.get("scenario") or cfg.scenarios[int(self.np_random.integers(len(cfg.scenarios)))])
        if (scenario, layout) != self._key or self._backend is None:
            self._build(scenario, layout)
        else:
            self._backend.reset()
        self._ik = make_ik_solver(self._loop.robot_config, self._pick.ik)  # fresh: no state carried over
        _, clouds, grasps, table_z, obstacles, pinfo = self._perceive_and_plan(int(self.np_random.integers(2**63 - 1)))
        self._table_z, self._obstacles = table_z, obstacles
        by_label = {c.object_index: (c, g) for c, g in zip(clouds, grasps, strict=True)}
        self._clouds = by_label
        order = sorted(by_label, key=lambda k: -(by_label[k][1][0].score if by_label[k][1] else -np.inf))
        with_cands = [k for k in order if by_label[k][1]]
        if options.get("target") is not None:
            t = int(options["target"])
            if not 0 <= t < len(order):
                raise ConfigError(f"reset option target={t}: this layout has {len(order)} perceived objects "
                                  f"(indices 0..{len(order) - 1} in the planner's order)")
            target = order[t]
        elif with_cands:
            target = with_cands[int(self.np_random.integers(len(with_cands)))]
        else:
            target = order[0] if order else -1
        self._target = target
        cloud, grasps_t = by_label.get(target, (None, []))
        self._grasps = list(grasps_t)[: cfg.top_k]
        if cloud is None:  # nothing perceived: an empty observation (every candidate invalid)
            pts = np.zeros((cfg.object_points, 3))
            self._centroid = np.zeros(3)
        else:
            pts = cloud.points_nx3
            self._centroid = pts.mean(axis=0)
        others = [c.points_nx3 for k, (c, _) in by_label.items() if k != target]
        self._others = np.concatenate(others) if others else np.zeros((0, 3))
        sub = pts[np.linspace(0, len(pts) - 1, cfg.object_points).astype(int)]
        self._obs = {
            "candidates": candidate_features(self._grasps, self._centroid, self._others, cfg.top_k, table_z,
                                             cfg.max_clearance),
            "valid": (np.arange(cfg.top_k) < len(self._grasps)).astype(np.int8),
            "object_summary": (object_summary(pts, len(self._grasps), cfg.top_k) if cloud is not None
                               else np.zeros(len(SUMMARY_NAMES), np.float32)),
            "object_points": (sub - self._centroid).astype(np.float32),
        }
        self._obs.update(self._sensor_observation(layout))
        if cfg.privileged_state:
            self._obs["true_target"] = self._true_target(cloud)
        realism = getattr(self._backend, "realism", None)
        info: dict[str, Any] = {
            "scenario": scenario, "layout_seed": layout, "perception": cfg.perception, "segmenter": cfg.segmenter,
            "renderer": cfg.renderer, "depth_model": cfg.depth_model, "realism": cfg.realism,
            "grip_force_n": self._pick.grip_force, "target_label": target, "n_perceived": len(order),
            "n_candidates": len(self._grasps), "perception_info": dict(pinfo),
            "realism_drawn": realism.as_dict() if realism is not None else {"profile": cfg.realism},
            "action_mask": self.action_masks(),
        }
        self._done = False
        close_at_exit(self)  # an env left open is closed at exit before EGL terminates (torm.runtime)
        return self._observation(), info

    def action_masks(self) -> np.ndarray:
        """(K,) bool: True for the actions that name a candidate grasp (Gymnasium's ``info["action_mask"]``; the
        method sb3-contrib's ``MaskablePPO`` calls). All False before ``reset`` and when nothing was perceived; an
        action outside the mask is allowed and ends the episode with reward 0 (``info["invalid_choice"]``)."""
        if self._obs is None:
            return np.zeros(self.config.top_k, dtype=bool)
        return self._obs["valid"].astype(bool)

    def step(self, action):
        from sim.judge import PickJudge
        from torm.execution.pick import execute_pick, free_directions
        from torm.loop import fixture_positions

        if self._backend is None or self._done:
            raise ConfigError("call reset() before step(); TormGraspSelect episodes are one step long")
        i = self._check_action(action)
        self._done = True
        info: dict[str, Any] = {"target_label": self._target, "candidate": i, "invalid_choice": False,
                                "action_mask": self.action_masks()}
        if i >= len(self._grasps):
            info.update(invalid_choice=True, outcome="no_grasp_found", is_success=False)
            return self._observation(), 0.0, True, False, info
        xy = self._centroid[:2]
        others_xy = [c.points_nx3[:, :2].mean(axis=0) for k, (c, _) in self._clouds.items() if k != self._target]
        others_xy += fixture_positions(self._obstacles)
        place_area = np.asarray(self._trial.place_area, dtype=float)
        pick = dataclasses.replace(self._pick, table_height=self._table_z)
        dirs = free_directions(xy, others_xy, place_area, pick.translate_distance)
        # the judge (ground truth) watches and decides; the pick itself runs on the loop's view of the backend
        judge = PickJudge(self._backend, self._trial.success, pick)
        try:
            loop_res = execute_pick(self._loop, [self._grasps[i]], dirs, pick, ik=self._ik, tool=self._tool,
                                    observer=judge)
        finally:
            judge.close()
        res = judge.verdicts.get(id(loop_res), loop_res)
        out = res.as_dict()  # without wall-clock times, so equal seeds and actions give equal infos
        out.pop("wall_time_s", None)
        out["phases"] = [{"name": p["name"], "sim_s": p["sim_s"]} for p in out["phases"]]
        info.update(outcome=res.outcome.value, is_success=res.success, picked_object=out.get("target_id"),
                    pick=out)
        return self._observation(), 1.0 if res.success else 0.0, True, False, info

    def render(self):
        if self.render_mode != "rgb_array" or self._render_cams is None:
            return None
        img = self._render_cams.render(["scene"], depth=False)["scene_rgb"]
        close_at_exit(self)
        return img

    def close(self) -> None:
        self._close_world()

    # ------------------------------------------------------------------------------------------ internals
    def _sensor_observation(self, layout: int) -> dict[str, np.ndarray]:
        """The ``obs_mode``'s overview-camera data of the scene as it rests now (the module docstring)."""
        cfg, cams = self.config, self._obs_cams
        if cfg.obs_mode == "state" or cams is None:
            return {}
        if cfg.obs_mode == "pointcloud":
            xyz, rgb = cams.pointcloud(["overview"], cfg.pointcloud_points, np.random.default_rng(layout))
            return {"pointcloud_xyz": xyz, "pointcloud_rgb": rgb}
        imgs = cams.render(["overview"], depth=cfg.obs_mode == "rgbd")
        out = {"overview_rgb": imgs["overview_rgb"]}
        if cfg.obs_mode == "rgbd":
            out["overview_depth"] = imgs["overview_depth"]
        return out

    def _true_target(self, cloud: ObjectPointCloud | None) -> np.ndarray:
        """(4,) float32: the real object nearest the perceived target's centroid (position m, 1.0), zeros for a
        phantom or nothing perceived. Ground truth: only with ``privileged_state``."""
        if cloud is None:
            return np.zeros(4, np.float32)
        gt = self._backend.ground_truth
        c = cloud.points_nx3.mean(axis=0)
        poses = [np.asarray(T)[:3, 3] for T in gt.object_poses().values()]
        if not poses:
            return np.zeros(4, np.float32)
        d = [float(np.linalg.norm(p[:2] - c[:2])) for p in poses]
        k = int(np.argmin(d))
        if d[k] > PHANTOM_DISTANCE:
            return np.zeros(4, np.float32)
        return np.array([*poses[k], 1.0], np.float32)

    def _observation(self) -> dict[str, np.ndarray]:
        return {k: (np.clip(v, -FEATURE_BOUND, FEATURE_BOUND) if v.dtype == np.float32 and k != "overview_depth"
                    else v.copy()) for k, v in self._obs.items()}

    def _check_action(self, action) -> int:
        K = self.config.top_k
        a = np.asarray(action)
        if a.shape != () or not np.issubdtype(a.dtype, np.integer) or not 0 <= int(a) < K:
            raise InvalidActionError(f"action {action!r} is not a candidate index; valid actions are the integers "
                                     f"0..{K - 1} (Discrete({K}); 0 = the planner's best)")
        return int(a)
