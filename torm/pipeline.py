"""The closed-loop trial: scenario + seed -> capture -> silhouettes -> reconstruction -> split ->
grasp planning -> execution of every object -> the paper's success test.

One reconstruction serves every pick (the paper's no-re-perception claim); ``re_perceive=True``
captures and reconstructs again before each later pick. The 20 cm translation goes towards free table
space. Every outcome is recorded, never raised, except configuration errors; a physics blow-up aborts
the remaining picks with category ``physics_error``.

Result record (ARCHITECTURE.md): one JSON-ready dict per trial with the resolved config, seeds,
versions, per-stage timings (s), reconstruction metrics and per-object outcomes.
"""

from __future__ import annotations

import logging
import platform
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from torm import __version__
from torm.capture.render_settings import PbrSettings
from torm.config import check_finite, to_dict
from torm.errors import ConfigError, ExecutionError, ReconstructionError, TormError, UnknownNameError
from torm.execution.pick import PickConfig, execute_pick, free_directions
from torm.execution.success import Outcome, SuccessCriteria
from torm.fusion import FusionConfig
from torm.grasp.planner import GraspPlannerConfig, plan_grasps
from torm.perception import (
    METHODS,
    Perception,
    depth_point_clouds,
    label_by_ground_truth,
    most_top_down_pose,
    most_top_down_view,
    oracle_point_clouds,
    perceive_depth_fusion,
    perceive_torm,
)
from torm.reconstruction.api import ReconstructionConfig
from torm.runtime import configure_threads, ensure_headless_gl
from torm.types import Capture

log = logging.getLogger(__name__)

#: Surface samples per object used for Chamfer distances in trial records.
CHAMFER_SAMPLES = 20000


#: Image renderers of the simulated capture (``capture.renderer``).
RENDERERS = ("mujoco", "pbr")
#: Sensor-depth models of the simulated depth camera (``capture.depth_model``, :mod:`sim.depth`): ``ideal`` is
#: exact z-depth of every opaque surface with glass invisible (the camera sees straight through it);
#: ``statistical`` a D455 whose glass pixels go missing / see through / read near the surface with
#: incidence-dependent probabilities; ``stereo`` an active-stereo D455 simulation (IR dots + SGBM).
DEPTH_MODELS = ("ideal", "statistical", "stereo")
#: Realism profiles of the simulated world (``world.realism``): ``ideal`` = nominal physics, exact
#: cameras, exact tracking; ``measured`` = contact, grip force, object mass, calibration and execution errors
#: drawn per trial from sourced ranges (``sim/realism.py``, table in ``sim/REALISM.md``).
REALISM_PROFILES = ("ideal", "measured")
#: Factor groups of a realism profile (``world.factors``; empty = all of them).
REALISM_FACTORS = ("contact", "grip_force", "objects", "calibration", "execution")


@dataclass(frozen=True)
class CaptureSettings:
    """Multi-view capture: number of views and image scale of the 1280x720, 91.5 deg HFOV camera.

    Attributes:
        n_views: number of views.
        scale: image scale (0.5 -> 640x360).
        renderer: who renders the RGB images (one of :data:`RENDERERS`): ``mujoco`` rasterises (glass as alpha
            blending), ``pbr`` path-traces with Mitsuba 3 (refracting glass; ``sim.render``). Cameras, depth and
            instance masks are the same for both.
        pbr: settings of the ``pbr`` renderer (samples, bounces, denoiser, variant, cache).
        depth_model: how the sensor depth is simulated (one of :data:`DEPTH_MODELS`).
        depth_options: overrides of the depth model's config fields (e.g. ``{"correlation_px": 0}`` for
            ``statistical``; see ``sim/depth/README.md``); unknown keys are rejected when the backend is built.
    """

    n_views: int = 50
    scale: float = 0.5
    renderer: str = "mujoco"
    depth_model: str = "ideal"
    depth_options: dict[str, Any] = field(default_factory=dict)
    pbr: PbrSettings = field(default_factory=PbrSettings)

    def __post_init__(self) -> None:
        if self.n_views < 1 or not self.scale > 0:
            raise ConfigError("capture.n_views must be >= 1 and capture.scale > 0")
        if self.renderer not in RENDERERS:
            raise UnknownNameError("capture.renderer", self.renderer, RENDERERS)
        if self.depth_model not in DEPTH_MODELS:
            raise UnknownNameError("capture.depth_model", self.depth_model, DEPTH_MODELS)


@dataclass(frozen=True)
class WorldSettings:
    """The simulated world's fidelity.

    Attributes:
        realism: realism profile (one of :data:`REALISM_PROFILES`); ``ideal`` is the default of a single trial,
            ``measured`` the default of benchmark runs (``torm bench``).
        factors: with ``measured``, draw only these factor groups (:data:`REALISM_FACTORS`), the others stay
            ideal; empty = all. The grip force group replaces ``pick.grip_force`` by the drawn pad force.
    """

    realism: str = "ideal"
    factors: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.realism not in REALISM_PROFILES:
            raise UnknownNameError("world.realism", self.realism, REALISM_PROFILES)
        object.__setattr__(self, "factors", tuple(self.factors))
        for f in self.factors:
            if f not in REALISM_FACTORS:
                raise UnknownNameError("world.factors entry", f, REALISM_FACTORS)
        if len(set(self.factors)) != len(self.factors):
            raise ConfigError(f"world.factors {list(self.factors)} lists a factor twice")


@dataclass(frozen=True)
class SegmentationSettings:
    """Silhouette source: ``gt`` (simulator masks), ``noisy`` (error model preset), ``grounded_sam`` or
    ``learned`` (the shipped U-Net; reads the rendered RGB).

    ``options`` is passed to the segmenter's own config (e.g. ONNX paths for ``grounded_sam``, thresholds or
    another model file for ``learned``).
    """

    segmenter: str = "gt"
    preset: str = "paper"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        valid = ("gt", "noisy", "grounded_sam", "learned")
        if self.segmenter not in valid:
            raise UnknownNameError("segmenter", self.segmenter, valid)


@dataclass(frozen=True)
class TrialConfig:
    """Everything that defines a trial. Distances in m, times in s.

    Attributes:
        scenario: scenario name (``torm scenes list``).
        seed: scene layout seed; also seeds segmentation noise and sampling.
        method: ``torm`` | ``depth`` (single-view depth) | ``depth_fusion`` (TSDF fusion of every view's depth) |
            ``oracle`` (see :mod:`torm.perception`).
        backend: ``sim`` or ``real``.
        robot: robot folder name or robot YAML path.
        re_perceive: capture and reconstruct again before every pick after the first.
        depth_view: layout view index for the single-view depth baseline (None: the most top-down view).
        fusion: TSDF settings of the ``depth_fusion`` baseline.
        place_area: ((x_min, y_min), (x_max, y_max)) of the table (m, world) where the 20 cm translation may
            end: the released object must land inside it, away from the other objects.
        hardware_config: hardware YAML for ``backend="real"`` (host, serial port, hand-eye file...;
            default: $TORM_HARDWARE_CONFIG).
        arm_robot: allow the real arm to move (otherwise the real backend refuses every motion).
    """

    scenario: str = "rw3"
    seed: int = 0
    method: Literal["torm", "depth", "depth_fusion", "oracle"] = "torm"
    backend: Literal["sim", "real"] = "sim"
    robot: str = "inovo_2f85"
    re_perceive: bool = False
    depth_view: int | None = None
    place_area: tuple[tuple[float, float], tuple[float, float]] = ((0.25, -0.35), (0.85, 0.35))
    hardware_config: str | None = None
    arm_robot: bool = False
    world: WorldSettings = field(default_factory=WorldSettings)
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    segmentation: SegmentationSettings = field(default_factory=SegmentationSettings)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    grasp: GraspPlannerConfig = field(default_factory=GraspPlannerConfig)
    pick: PickConfig = field(default_factory=PickConfig)
    success: SuccessCriteria = field(default_factory=SuccessCriteria)

    def __post_init__(self) -> None:
        check_finite(self, "TrialConfig")  # NaN / inf in any float field of any section (torm.config)
        if self.method not in METHODS:
            raise UnknownNameError("method", self.method, METHODS)
        if self.backend not in ("sim", "real"):
            raise UnknownNameError("backend", self.backend, ("sim", "real"))
        lo, hi = np.asarray(self.place_area, dtype=float)
        if lo.shape != (2,) or not np.all(hi > lo):
            raise ConfigError(f"place_area must be ((x_min, y_min), (x_max, y_max)) with max > min, got "
                              f"{self.place_area}")


def versions() -> dict[str, str]:
    """Versions of the packages that shape a result."""
    import mujoco
    import torch

    return {"torm": __version__, "mujoco": mujoco.__version__, "torch": torch.__version__,
            "numpy": np.__version__, "python": platform.python_version()}


def trial_context(config: TrialConfig) -> dict[str, Any]:
    """What produced a result: every choice that shapes it, by name (goes first into every trial record).

    Keys: ``method``, ``reconstruction_mode`` (torm only), ``segmenter`` (torm: its segmenter, ``noisy:<preset>``
    for the error model; the depth baselines: ``gt``, they cut with the capture's masks), ``renderer``,
    ``depth_model``, ``realism`` (``measured[contact+...]`` when only some factor groups are drawn), ``backend``;
    with the ``learned`` segmenter also ``segmenter_model`` (:func:`torm.segmentation.learned.model_fingerprint`:
    file name and content hash).
    """
    seg = config.segmentation
    segmenter = f"noisy:{seg.preset}" if seg.segmenter == "noisy" else seg.segmenter
    torm_method = config.method == "torm"
    ctx = {
        "method": config.method,
        "reconstruction_mode": config.reconstruction.mode if torm_method else None,
        "segmenter": segmenter if torm_method else ("gt" if config.method in ("depth", "depth_fusion") else None),
        "renderer": config.capture.renderer,
        "depth_model": config.capture.depth_model,
        "realism": (f"{config.world.realism}[{'+'.join(config.world.factors)}]"
                    if config.world.factors and config.world.realism != "ideal" else config.world.realism),
        "backend": config.backend,
    }
    if torm_method and seg.segmenter == "learned":
        from torm.segmentation.learned import model_fingerprint

        ctx["segmenter_model"] = model_fingerprint(str(seg.options.get("model", "") or ""))
    return ctx


def make_backend(config: TrialConfig) -> Any:
    """The backend named by ``config.backend`` (the simulated one is built from scenario + seed)."""
    if config.backend == "sim":
        ensure_headless_gl()
        from sim.backend import SimBackend
        from sim.camera_rig import CameraRigConfig
        from sim.depth import make_depth_model
        from sim.world import build_world

        realism = sample_trial_realism(config)
        world = build_world(config.scenario, config.seed, robot=config.robot, realism=realism)
        cam = CameraRigConfig(n_views=config.capture.n_views, scale=config.capture.scale)
        depth = make_depth_model(config.capture.depth_model, config.capture.depth_options)
        return SimBackend(world, camera_config=cam, realism=realism, renderer=config.capture.renderer,
                          render_settings=config.capture.pbr, depth_model=depth, depth_seed=config.seed)
    from torm.hardware import make_real_backend  # optional extra; raises a clear error when absent

    return make_real_backend(config)


def sample_trial_realism(config: TrialConfig) -> Any:
    """The trial's :class:`sim.realism.RealismRecord`, drawn from ``config.world`` and the trial seed."""
    from sim.realism import sample_realism
    from sim.scenes.objects import get_object
    from sim.scenes.scenario import get_scenario

    hollow = [get_object(n).hollow for n in get_scenario(config.scenario).objects]
    return sample_realism(config.world.realism, config.seed, hollow, config.world.factors)


def _segmenter(config: TrialConfig) -> Any:
    from torm.segmentation import make_segmenter

    s = config.segmentation
    opts = dict(s.options)
    if s.segmenter == "noisy":
        opts.setdefault("preset", s.preset)
        opts.setdefault("seed", config.seed)
    return make_segmenter(s.segmenter, opts or None)


def _gripper(backend: Any):
    from torm.grasp.gripper import GripperGeometry

    rcfg = getattr(backend, "robot_config", None)
    if rcfg is None:
        return GripperGeometry()
    return GripperGeometry.from_robot_config(to_dict(rcfg.gripper.geometry))


#: Channels each depth baseline captures (it pays for nothing else): sensor depth and the GT masks.
DEPTH_CHANNELS = ("sensor_depth", "mask")
#: Channels of a capture no image is read from (the oracle; TORM with GT or error-model silhouettes): the
#: masks and the exact depth (Table II depth metrics), no RGB, which is the costly pass with ``renderer=pbr``.
MASK_CHANNELS = ("depth", "mask")
#: Segmenters that read the RGB images (every other one works from the simulator's masks).
IMAGE_SEGMENTERS = ("learned", "grounded_sam")


def _capture(config: TrialConfig, backend: Any, rgb: bool = False) -> tuple[Capture, dict[str, Any]]:
    """The capture ``config.method`` needs, and what was captured (views, channels, layout indices).

    ``torm`` with an image segmenter (:data:`IMAGE_SEGMENTERS`): the full ``capture.n_views`` capture; ``torm``
    with GT / error-model masks and ``oracle``: the same views without RGB (:data:`MASK_CHANNELS`) unless
    ``rgb`` (a trial being recorded shows its images). ``depth``: one view of the layout (the
    most top-down one, or ``depth_view``), sensor depth + mask only. ``depth_fusion``: every view of the
    layout (the trajectory TORM flies, so both see the same camera poses), sensor depth + mask only. A
    backend without partial captures (``capture_views``) captures everything and the baseline takes a subset.
    """
    n = config.capture.n_views
    depth_method = config.method in ("depth", "depth_fusion")
    partial = depth_method and hasattr(backend, "capture_views") and hasattr(backend, "capture_poses")
    if config.method == "depth":
        if partial:
            poses = backend.capture_poses(n)
            view = config.depth_view if config.depth_view is not None else most_top_down_pose(poses)
            if not 0 <= view < len(poses):
                raise ConfigError(f"depth_view {view} is outside the capture layout's views 0..{len(poses) - 1}")
            cap = backend.capture_views(n, [view], DEPTH_CHANNELS)
        else:
            full = backend.capture(n)
            view = config.depth_view if config.depth_view is not None else most_top_down_view(full)
            cap = full.subset([view])
        return cap, {"depth_view": int(view), "views_captured": 1 if partial else len(full), "views_used": 1,
                     "channels": list(DEPTH_CHANNELS) if partial else "all"}
    if config.method == "depth_fusion" and partial:
        cap = backend.capture_views(n, list(range(n)), DEPTH_CHANNELS)
        return cap, {"views_captured": len(cap), "views_used": len(cap), "channels": list(DEPTH_CHANNELS)}
    reads_images = config.method == "torm" and config.segmentation.segmenter in IMAGE_SEGMENTERS
    if not (reads_images or rgb) and hasattr(backend, "capture_views"):
        cap = backend.capture_views(n, list(range(n)), MASK_CHANNELS)
        return cap, {"views_captured": len(cap), "views_used": len(cap), "channels": list(MASK_CHANNELS)}
    cap = backend.capture(n)
    return cap, {"views_captured": len(cap), "views_used": len(cap), "channels": "all"}


def perceive(config: TrialConfig, backend: Any, rng: np.random.Generator, timings: dict[str, float],
             rgb: bool = False) -> Perception:
    """Capture and turn the capture into per-object geometry with ``config.method``.

    ``rgb``: capture the RGB images even when the method reads none (for a recording)."""
    t = time.perf_counter()
    capture, cap_info = _capture(config, backend, rgb)
    cap_info["capture_s"] = time.perf_counter() - t
    timings["capture"] = timings.get("capture", 0.0) + cap_info["capture_s"]
    log.info("capture: %d views in %.1f s", len(capture.views), cap_info["capture_s"])
    gt = backend.ground_truth
    n_points = config.reconstruction.points_per_object
    t = time.perf_counter()
    if config.method == "torm":
        per = perceive_torm(capture, _segmenter(config), config.reconstruction)
        timings["segmentation"] = timings.get("segmentation", 0.0) + per.info["segmentation_s"]
        timings["reconstruction"] = timings.get("reconstruction", 0.0) + per.info["reconstruction_s"]
        if gt is not None:
            per.point_clouds, per.info["matching"] = label_by_ground_truth(per.point_clouds, gt.object_meshes())
    elif config.method == "depth":
        per = Perception(depth_point_clouds(capture, 0, n_points, rng), [], {"view": cap_info["depth_view"]})
        per.meshes = [None] * len(per.point_clouds)
        per.info["baseline"] = "single-view depth, symmetric completion"
        timings["reconstruction"] = timings.get("reconstruction", 0.0) + time.perf_counter() - t
    elif config.method == "depth_fusion":
        per = perceive_depth_fusion(capture, config.fusion, n_points, rng)
        timings["reconstruction"] = timings.get("reconstruction", 0.0) + time.perf_counter() - t
    else:
        if gt is None:
            raise ConfigError("method 'oracle' needs a simulated backend (true object meshes)")
        clouds, meshes = oracle_point_clouds(gt.object_meshes(), n_points, rng)
        per = Perception(clouds, meshes, {})
        timings["reconstruction"] = timings.get("reconstruction", 0.0) + time.perf_counter() - t
    per.info["capture"] = capture
    per.info["capture_info"] = cap_info
    log.info("perception (%s): %d objects in %.1f s", config.method, len(per.point_clouds), time.perf_counter() - t)
    return per


def run_trial(config: TrialConfig, backend: Any | None = None, record: Any = None) -> dict[str, Any]:
    """Run one closed-loop trial and return its result record (see the module docstring).

    Args:
        config: the trial definition.
        backend: an existing backend to run on (default: built from ``config``; closed at the end).
        record: path of a rerun ``.rrd`` file to stream the scene, images, masks, meshes, grasps, motion and the
            outcome into, or a :class:`torm.viz.TrialRecorder` to use.
    """
    configure_threads()
    t_trial = time.perf_counter()
    rng = np.random.default_rng(config.seed)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    own_backend = backend is None
    backend = backend or make_backend(config)
    timings["setup"] = time.perf_counter() - t
    gt = backend.ground_truth
    gt_ids = sorted(gt.object_poses()) if gt is not None else []
    result: dict[str, Any] = {
        "scenario": config.scenario, "seed": config.seed, "method": config.method, "backend": config.backend,
        "context": trial_context(config), "config": to_dict(config), "versions": versions(), "timings": timings,
        "objects": [], "failure": None,
    }
    recorder = None
    if record:
        from torm.viz import TrialRecorder

        recorder = TrialRecorder(record) if isinstance(record, (str, Path)) else record
        _attach_recorder(recorder, backend)
    realism = getattr(backend, "realism", None)
    result["realism"] = realism.as_dict() if realism is not None else {"profile": config.world.realism}
    if realism is not None and realism.grip_force_n is not None:  # the drawn pad force is what the pick requests
        config = replace(config, pick=replace(config.pick, grip_force=realism.grip_force_n))
    try:
        _run(config, backend, rng, timings, result, gt_ids, recorder)
    finally:
        if hasattr(backend, "realism_summary"):
            result["realism"]["applied"] = backend.realism_summary()
        if recorder is not None:
            recorder.finish(result)
            recorder.close()
        if own_backend:
            backend.close()
    outcomes = [o["outcome"] for o in result["objects"]]
    result["n_objects"] = len(outcomes)
    result["n_success"] = sum(o == Outcome.SUCCESS.value for o in outcomes)
    result["success_rate"] = result["n_success"] / len(outcomes) if outcomes else 0.0
    timings["total"] = time.perf_counter() - t_trial
    log.info("trial %s seed %d (%s): %d/%d objects picked in %.1f s", config.scenario, config.seed, config.method,
             result["n_success"], result["n_objects"], timings["total"])
    # The headline first, the resolved config last (ARCHITECTURE.md's trial record, reading order for people).
    resolved = result.pop("config")
    return {"summary": trial_summary(result), **result, "config": resolved}


def trial_summary(result: dict[str, Any]) -> dict[str, Any]:
    """The headline of a trial record: scenario, method, k/n objects picked, the outcome per object, total time (s)."""
    objs = result.get("objects") or []
    return {
        "scenario": result.get("scenario"), "seed": result.get("seed"), "method": result.get("method"),
        "success": f"{result.get('n_success', 0)}/{result.get('n_objects', len(objs))}",
        "outcomes": {f"{o['object_id']}:{o['name']}": o["outcome"] for o in objs},
        "failure": result.get("failure"),
        "total_s": (result.get("timings") or {}).get("total"),
    }


def _attach_recorder(recorder: Any, backend: Any) -> None:
    """Log the scene once and the motion from the backend's step callback (simulation only)."""
    world = getattr(backend, "world", None)
    if not hasattr(backend, "add_step_callback") or world is None:
        return
    recorder.scene(world)

    def on_step(t: float) -> None:
        if recorder.due(t):
            recorder.step(t, backend.arm.state().T_world_tcp)

    backend.add_step_callback(on_step)


def _run(config: TrialConfig, backend: Any, rng: np.random.Generator, timings: dict[str, float],
         record: dict[str, Any], gt_ids: list[int], recorder: Any = None) -> None:
    gt = backend.ground_truth
    names = _object_names(backend)
    try:
        per = perceive(config, backend, rng, timings, rgb=bool(getattr(recorder, "wants_rgb", False)))
    except ReconstructionError as exc:
        record["failure"] = "reconstruction_failed"
        record["message"] = str(exc)
        record["objects"] = [_obj(i, names, Outcome.NOT_RECONSTRUCTED, str(exc)) for i in gt_ids]
        return
    record["perception"] = _perception_summary(per, backend, config)
    record["n_perceptions"] = 1
    if hasattr(backend, "occlusion_ratio") and per.info["capture"].has_masks:
        t = time.perf_counter()
        record["occ"] = backend.occlusion_ratio(per.info["capture"])
        timings["occlusion_metric"] = time.perf_counter() - t
    gripper = _gripper(backend)
    table_z = gt.table_height() if gt is not None else 0.0
    # Known static fixtures (a rack, a tray): the planner keeps the gripper off them, the drop-offs avoid them.
    obstacles = backend.known_obstacles() if hasattr(backend, "known_obstacles") else None
    t = time.perf_counter()
    grasps = plan_grasps(per.point_clouds, per.meshes or None, table_z, gripper, config.grasp, rng, obstacles)
    timings["grasp_planning"] = time.perf_counter() - t
    log.info("grasp planning: %d candidates for %d objects in %.2f s", sum(len(g) for g in grasps), len(grasps),
             timings["grasp_planning"])
    if recorder is not None:
        recorder.perception(per.info["capture"], per.meshes or [None] * len(grasps), per.point_clouds, grasps)
    by_label = {c.object_index: (c, g) for c, g in zip(per.point_clouds, grasps, strict=True)}
    done: dict[int, dict[str, Any]] = {}
    # Pick easiest first: by the best grasp score of each object.
    order = sorted(by_label, key=lambda k: -(by_label[k][1][0].score if by_label[k][1] else -np.inf))
    place_area = np.asarray(config.place_area, dtype=float)
    # Where every object is now (m, world xy): where it was seen, or where this trial put it down.
    where = {k: c.points_nx3[:, :2].mean(axis=0) for k, (c, _) in by_label.items()}
    fixture_xy = [] if obstacles is None else list(np.unique(np.round(np.asarray(obstacles)[:, :2], 2), axis=0))
    timings["execution"] = 0.0
    aborted = None
    for n_pick, label in enumerate(order):
        if aborted:
            done[label] = _obj(label, names, Outcome.PHYSICS, "trial aborted after a physics error")
            continue
        if config.re_perceive and n_pick > 0:
            try:
                per = perceive(config, backend, rng, timings, rgb=bool(getattr(recorder, "wants_rgb", False)))
            except ReconstructionError as exc:  # keep planning on the previous reconstruction
                log.warning("re-perception before pick %d failed (%s); using the previous one", n_pick, exc)
            else:
                record["n_perceptions"] += 1
                grasps = plan_grasps(per.point_clouds, per.meshes or None, table_z, gripper, config.grasp, rng,
                                     obstacles)
                by_label.update({c.object_index: (c, g) for c, g in zip(per.point_clouds, grasps, strict=True)})
        cloud, cands = by_label[label]
        if not cands:
            done[label] = _obj(label, names, Outcome.NO_GRASP, "no collision-free grasp within the stroke")
            continue
        if gt is not None and label not in gt.object_poses():
            done[label] = _obj(label, names, Outcome.OTHER, "reconstructed object matches no real object")
            continue
        xy = cloud.points_nx3[:, :2].mean(axis=0)
        others = [p for k, p in where.items() if k != label] + fixture_xy
        t = time.perf_counter()
        try:
            dirs = free_directions(xy, others, place_area, config.pick.translate_distance)
            confirm = backend.operator_confirm() if hasattr(backend, "operator_confirm") else None
            res = execute_pick(backend, cands, dirs, config.success, config.pick, operator_confirm=confirm,
                               ignore_ids=[j for j in done if j != label])
        except ExecutionError as exc:
            done[label] = _obj(label, names, Outcome.OTHER, str(exc))
            continue
        finally:
            timings["execution"] += time.perf_counter() - t
        if res.translate_direction is not None and res.outcome in (Outcome.SUCCESS, Outcome.NOT_RELEASED):
            where[label] = xy + config.pick.translate_distance * np.asarray(res.translate_direction)
        entry = _obj(label, names, res.outcome, res.message)
        entry["pick"] = res.as_dict()
        done[label] = entry
        log.info("pick %d/%d (%s): %s in %.1f s", n_pick + 1, len(order), entry["name"], res.outcome.value,
                 time.perf_counter() - t)
        if res.outcome is Outcome.PHYSICS:
            aborted = res.message
            record["failure"] = Outcome.PHYSICS.value
    # Every real object gets an entry; objects never matched by a reconstruction are "not reconstructed", each
    # on its own (the other objects were planned and picked), with the reconstruction's reason when it has one.
    for i in gt_ids:
        if i not in done:
            done[i] = _obj(i, names, Outcome.NOT_RECONSTRUCTED, _not_reconstructed_reason(per, gt, i))
    record["objects"] = [done[k] for k in sorted(done) if (not gt_ids or k in gt_ids)]
    record["spurious_objects"] = [done[k] for k in sorted(done) if gt_ids and k not in gt_ids]


def _not_reconstructed_reason(per: Perception, gt: Any, object_id: int, max_dist: float = 0.04) -> str:
    """Why object ``object_id`` has no reconstruction: a rejected component near it (its check's reason), else
    the views whose silhouettes hold regions no reconstructed object explains."""
    rejected = per.info.get("rejected_objects") or []
    if gt is not None and rejected:
        from torm.metrics import mesh_centroid

        c = mesh_centroid(gt.object_meshes()[object_id])
        near = [r for r in rejected if np.linalg.norm(np.asarray(r["centroid"]) - c) < max_dist]
        if near:
            return f"rejected by the reconstruction: {near[0]['reason']}"
    msg = "no reconstructed object matched it"
    views = per.info.get("unexplained_views") or []
    if views:
        msg += (f" (silhouette regions no reconstructed object covers in {len(views)} of the checked views, e.g. "
                f"{views[:5]}: other views' masks carved it away, e.g. a segmenter that missed it there)")
    return msg


def _object_names(backend: Any) -> dict[int, str]:
    world = getattr(backend, "world", None)
    if world is None:
        return {}
    return {o.instance_id: o.name for o in world.objects}


def _obj(label: int, names: dict[int, str], outcome: Outcome, message: str = "") -> dict[str, Any]:
    return {"object_id": int(label), "name": names.get(label, f"object{label}"), "outcome": outcome.value,
            "message": message}


def _perception_summary(per: Perception, backend: Any, config: TrialConfig) -> dict[str, Any]:
    """Reconstruction metrics against the simulator's truth (when there is one)."""
    out: dict[str, Any] = {k: v for k, v in per.info.items() if k not in ("capture",)}
    out["depth_model"] = per.info["capture"].metadata.get("depth_model") if "capture" in per.info else None
    gt = backend.ground_truth
    out["n_objects_found"] = sum(1 for c in per.point_clouds if c.object_index < 1000)
    out["n_objects_reconstructed"] = len(per.point_clouds)
    if gt is None:
        return out
    from torm.metrics import chamfer_distance_mm

    true_meshes = gt.object_meshes()
    out["n_objects_present"] = len(true_meshes)
    cd = {}
    r = np.random.default_rng(0)
    from torm.mesh.sample import sample_surface

    # Dense samples on both sides: sparse samples would add ~1 mm of sampling noise to the Chamfer distance.
    for k, c in enumerate(per.point_clouds):
        if c.object_index not in true_meshes:
            continue
        mesh = per.meshes[k] if per.meshes and per.meshes[k] is not None else None
        pred = sample_surface(mesh, CHAMFER_SAMPLES, r).points_nx3 if mesh is not None else c.points_nx3
        ref = sample_surface(true_meshes[c.object_index], CHAMFER_SAMPLES, r).points_nx3
        cd[str(c.object_index)] = chamfer_distance_mm(pred, ref)
    out["chamfer_samples"] = CHAMFER_SAMPLES
    out["chamfer_mm"] = cd
    out["chamfer_mm_mean"] = float(np.mean(list(cd.values()))) if cd else None
    if per.reconstruction is not None:
        out["silhouette_iou_mean"] = per.reconstruction.info.get("silhouette_iou_mean")
        out["silhouette_iou_min"] = per.reconstruction.info.get("silhouette_iou_min")
    return out


def trial_succeeded(record: dict[str, Any]) -> bool:
    """True when every object of the trial was picked successfully."""
    return bool(record["objects"]) and all(o["outcome"] == Outcome.SUCCESS.value for o in record["objects"])


__all__ = ["DEPTH_MODELS", "REALISM_FACTORS", "REALISM_PROFILES", "RENDERERS", "CaptureSettings",
           "SegmentationSettings", "TormError", "TrialConfig", "WorldSettings", "make_backend", "perceive",
           "run_trial", "sample_trial_realism", "trial_context", "trial_succeeded", "trial_summary", "versions"]
