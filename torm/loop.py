"""The decision loop of a trial: capture -> perception -> grasp planning -> execution of every object it believes in.

It runs on a :class:`torm.backend.blind.LoopBackend`, the view of a backend that offers only what the real robot
offers (cameras, depth, camera poses, joint and gripper state, the declared calibration), so it behaves the same in
simulation and on the arm. It attempts every reconstructed object in the planned order, phantoms included; what an
attempt really did is the judge's business (``sim/judge.py``), which watches through the ``observer``. This module
never imports the judge or reads ground truth (``tests/test_loop_blind.py`` checks both).

Units: m, s; frames: world = robot base frame, z up.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from torm.config import to_dict
from torm.errors import CaptureError, ConfigError, ExecutionError, ReconstructionError, TormError
from torm.execution.pick import execute_pick, free_directions
from torm.execution.success import Outcome
from torm.perception import (
    Perception,
    most_top_down_pose,
    most_top_down_view,
)
from torm.trial_config import TABLE_SOURCES, TrialConfig
from torm.types import Capture, ObjectPointCloud, TriMesh

log = logging.getLogger(__name__)

#: Channels each depth baseline captures (it pays for nothing else): sensor depth and the GT masks.
DEPTH_CHANNELS = ("sensor_depth", "mask")
#: Channels of a capture no image is read from (the oracle; TORM with GT or error-model silhouettes): the
#: masks and the exact depth (Table II depth metrics), no RGB, which is the costly pass with ``renderer=pbr``.
MASK_CHANNELS = ("depth", "mask")
#: Segmenters that read the RGB images (every other one works from the simulator's masks).
IMAGE_SEGMENTERS = ("learned", "grounded_sam", "difference")
#: Two reconstructions within this horizontal distance (m) are the same object for re-perception.
SAME_OBJECT_XY = 0.03


def _segmenter(config: TrialConfig) -> Any:
    """The segmenter ``config.segmentation`` names, built (:func:`torm.methods.builtin_methods.segmenter_for`)."""
    from torm.methods.builtin_methods import segmenter_for

    return segmenter_for(config)


def _gripper(backend: Any):
    from torm.grasp.gripper import GripperGeometry

    rcfg = getattr(backend, "robot_config", None)
    if rcfg is None:
        return GripperGeometry()
    return GripperGeometry.from_robot_config(to_dict(rcfg.gripper.geometry))


def _capture_plugin(config: TrialConfig, backend: Any, needs: Any, rgb: bool) -> tuple[Capture, dict[str, Any]]:
    """What a plug-in method declared (:class:`torm.methods.Needs`): its channels, all views or the most top-down
    one, the reference pass if asked; a backend without partial captures captures everything."""
    n = config.capture.n_views
    channels = tuple(dict.fromkeys(needs.channels() + (("rgb",) if rgb else ())))
    if hasattr(backend, "capture_views") and hasattr(backend, "capture_poses"):
        poses = backend.capture_poses(n)
        idx = [most_top_down_pose(poses)] if needs.views == "top_down" else list(range(len(poses)))
        kw = {"reference": True} if needs.reference else {}
        cap = backend.capture_views(n, idx, channels, **kw)
        info = {"views_captured": len(cap), "views_used": len(cap), "channels": list(channels)}
    else:
        full = backend.capture(n)
        cap = full.subset([most_top_down_view(full)]) if needs.views == "top_down" else full
        info = {"views_captured": len(full), "views_used": len(cap), "channels": "all"}
    if needs.reference:
        cap, info = _recorded_reference(config, cap, info)
    if needs.reference and any(v.reference_rgb is None for v in cap.views):
        raise ConfigError(f"method {config.method!r} needs reference views, which this backend did not capture: "
                          "set capture.reference=true (simulation) or capture.reference_dir=DIR (a recorded pass)")
    return cap, {**info, "needs": needs.as_dict()}


def _recorded_reference(config: TrialConfig, capture: Capture, info: dict[str, Any]
                        ) -> tuple[Capture, dict[str, Any]]:
    """``capture`` with ``config.capture.reference_dir``'s recorded reference pass attached view by view
    (:func:`torm.segmentation.reference.attach_reference`) and its static background checked against the scene
    before anything reads it (:func:`~torm.segmentation.reference.check_background` over the whole views); both
    raise :class:`CaptureError` with the fix. Unchanged without a ``reference_dir``."""
    if not config.capture.reference_dir:
        return capture, info
    from torm.segmentation.reference import attach_reference, check_background

    folder = Path(config.capture.reference_dir)
    stamp = (folder / "transforms.json").stat().st_mtime_ns if (folder / "transforms.json").is_file() else 0
    cap = attach_reference(capture, _load_reference(str(folder), stamp))
    grey = check_background(cap)
    return cap, {**info, "reference": {**cap.metadata["reference"], "folder": config.capture.reference_dir,
                                       "background_grey": grey}}


@functools.lru_cache(maxsize=1)
def _load_reference(folder: str, stamp: int) -> Capture:
    """The recorded reference capture, loaded once per folder and file version (``stamp``: the mtime of its
    ``transforms.json``; a re-perceiving trial captures again before every pick)."""
    from torm.capture.io import load_capture

    return load_capture(folder)


#: Built-in methods defined on the simulator's instance masks (declared simulation-only; the loop is granted them).
MASK_METHODS = ("oracle", "depth", "depth_fusion")
#: Segmenters of ``torm`` that read the simulator's masks (ground truth and its error model).
MASK_SEGMENTERS = ("gt", "noisy")


def grants_masks(config: TrialConfig) -> bool:
    """Whether the trial's method is declared to read the simulator's masks and ideal depth (``oracle``, the depth
    baselines that cut with the capture's masks, ``torm`` with the ``gt`` or ``noisy`` segmenter, a plug-in that
    asks for the ``mask`` channel); every other loop gets captures without ground truth
    (:func:`torm.backend.blind.without_ground_truth`)."""
    if config.method in MASK_METHODS:
        return True
    if config.method == "torm":
        return config.segmentation.segmenter in MASK_SEGMENTERS
    from torm.methods import is_builtin, load_method

    if is_builtin(config.method):
        return False
    needs = getattr(load_method(config.method, dict(config.method_options)), "needs", None)
    return needs is not None and "mask" in needs.channels()


def _capture(config: TrialConfig, backend: Any, rgb: bool = False, plugin: Any = None
             ) -> tuple[Capture, dict[str, Any]]:
    """The capture ``config.method`` needs, and what was captured (views, channels, layout indices).

    ``torm`` with an image segmenter (:data:`IMAGE_SEGMENTERS`): the full ``capture.n_views`` capture; ``torm``
    with GT / error-model masks and ``oracle``: the same views without RGB (:data:`MASK_CHANNELS`) unless
    ``rgb`` (a trial being recorded shows its images). ``depth``: one view of the layout (the
    most top-down one, or ``depth_view``), sensor depth + mask only. ``depth_fusion``: every view of the
    layout (the trajectory TORM flies, so both see the same camera poses), sensor depth + mask only. A
    backend without partial captures (``capture_views``) captures everything and the baseline takes a subset.
    """
    n = config.capture.n_views
    if plugin is not None:
        return _capture_plugin(config, backend, plugin.needs, rgb)
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
        # a table fitted to the capture reads the sensor's depth, what a real camera gives
        channels = MASK_CHANNELS + (("sensor_depth",) if config.table == "capture" else ())
        cap = backend.capture_views(n, list(range(n)), channels)
        return cap, {"views_captured": len(cap), "views_used": len(cap), "channels": list(channels)}
    cap = backend.capture(n)
    return _recorded_reference(config, cap, {"views_captured": len(cap), "views_used": len(cap), "channels": "all"})


def _calibration(backend: Any) -> Any:
    """The declared calibration: a :class:`~torm.backend.blind.LoopBackend`'s attribute or a backend's method."""
    cal = getattr(backend, "calibration", None)
    return cal() if callable(cal) else cal


def table_height(config: TrialConfig, backend: Any, capture: Capture) -> tuple[float, dict[str, Any]]:
    """The table-top height (m) the loop plans with, and where it came from.

    ``config.table == "declared"``: the backend's declared calibration (a lab's measured height, with its stated
    error); ``"capture"``: fitted to the capture's depth (:func:`torm.capture.table_plane.estimate_table_plane`),
    sensor depth where the views have it, with the objects left to RANSAC as outliers: a capture's instance masks
    are never read (in simulation they are the simulator's truth; the loop's own masks come later).
    """
    cal = _calibration(backend)
    if config.table == "capture":
        from torm.capture.table_plane import estimate_table_plane

        try:
            plane = estimate_table_plane(capture, use_masks=False)
        except CaptureError as exc:
            raise ConfigError(f"table=capture: {exc}; or use table=declared (the cell's declared table height)") \
                from exc
        return float(plane.height_m), {"source": "capture", **plane.as_dict()}
    if cal is None:
        return 0.0, {"source": "default", "table_height_m": 0.0}
    return float(cal.table_height), {"source": "declared", **cal.as_dict()}


def perceive(config: TrialConfig, backend: Any, rng: np.random.Generator, timings: dict[str, float],
             rgb: bool = False, oracle_meshes: Callable[[], dict[int, TriMesh]] | None = None) -> Perception:
    """Capture and turn the capture into per-object geometry with ``config.method``.

    Args:
        rgb: capture the RGB images even when the method reads none (for a recording).
        oracle_meshes: the true object meshes, for ``method="oracle"`` only (a perception oracle the harness
            grants explicitly in simulation; the real backend has none).
    """
    from torm.methods import MethodContext, is_builtin, load_method
    from torm.methods.builtin_methods import builtin_method

    plugin = None if is_builtin(config.method) else load_method(config.method, dict(config.method_options))
    # a built-in is built before capturing so that a misconfigured one (oracle on the real arm) costs no capture
    builtin = builtin_method(config, oracle_meshes) if plugin is None else None
    t = time.perf_counter()
    capture, cap_info = _capture(config, backend, rgb, plugin)
    cap_info["capture_s"] = time.perf_counter() - t
    timings["capture"] = timings.get("capture", 0.0) + cap_info["capture_s"]
    log.info("capture: %d views in %.1f s", len(capture.views), cap_info["capture_s"])
    table_z, table_info = table_height(config, backend, capture)
    capture = replace(capture, table_height=table_z)
    n_points = config.reconstruction.points_per_object
    t = time.perf_counter()
    if builtin is not None:  # the built-ins implement the plug-in interface; run() keeps their diagnostics
        ctx = MethodContext(n_points=n_points, rng=rng, table_height=table_z,
                            workspace_bounds=_workspace_bounds(capture, table_z))
        per = builtin.run(capture, ctx)
    else:
        per = perceive_plugin(plugin, config, capture, table_z, n_points, rng)
    if "segmentation_s" in per.info:
        timings["segmentation"] = timings.get("segmentation", 0.0) + per.info["segmentation_s"]
    recon_s = per.info.get("reconstruction_s", time.perf_counter() - t - per.info.get("segmentation_s", 0.0))
    timings["reconstruction"] = timings.get("reconstruction", 0.0) + recon_s
    if "depth_view" in cap_info:
        per.info["view"] = cap_info["depth_view"]
    per.info["capture"] = capture
    per.info["capture_info"] = cap_info
    per.info["table"] = table_info
    log.info("perception (%s): %d objects in %.1f s", config.method, len(per.point_clouds), time.perf_counter() - t)
    return per


#: the box (m, world; relative to the table top in z) a plug-in's objects are checked against when the capture
#: declares no workspace bounds
DEFAULT_WORKSPACE = ((0.15, -0.45, -0.03), (0.95, 0.45, 0.40))


def _workspace_bounds(capture: Capture, table_z: float) -> np.ndarray:
    """(2, 3) m, world: the capture's declared workspace box, else :data:`DEFAULT_WORKSPACE` above the table."""
    if capture.workspace_bounds is not None:
        return np.asarray(capture.workspace_bounds, np.float64)
    return np.asarray(DEFAULT_WORKSPACE, np.float64) + np.array([0.0, 0.0, table_z])


def perceive_plugin(method: Any, config: TrialConfig, capture: Capture, table_z: float, n_points: int,
                    rng: np.random.Generator) -> Perception:
    """Run a plug-in method (:mod:`torm.methods`): validate its output, estimate missing normals (PCA, oriented to
    the cameras), resample every object to ``n_points`` samples; ``info`` records name, version and confidences."""
    from torm.methods import MethodContext, validate_estimates
    from torm.perception import _estimate_normals, _resample

    bounds = _workspace_bounds(capture, table_z)
    ctx = MethodContext(n_points=n_points, rng=rng, table_height=table_z, workspace_bounds=bounds,
                        options=dict(config.method_options))
    estimates = validate_estimates(config.method, method.perceive(capture, ctx), bounds)
    eye = np.mean([v.T_world_cam[:3, 3] for v in capture.views], axis=0)
    clouds, meshes = [], []
    for k, e in enumerate(estimates):
        p = np.asarray(e.points_nx3, np.float64)
        nrm = np.asarray(e.normals_nx3, np.float64) if e.normals_nx3 is not None else _estimate_normals(p, eye)
        nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        p, nrm = _resample(p, nrm, n_points, rng)
        clouds.append(ObjectPointCloud(p, nrm, 1000 + k))
        meshes.append(e.mesh)
    return Perception(clouds, meshes, {"plugin": {"name": str(method.name), "version": str(method.version),
                                                  "confidences": [float(e.confidence) for e in estimates]}})


def plan_with_planner(config: TrialConfig, per: Perception, table_z: float, gripper: Any, rng: np.random.Generator,
                     obstacles: np.ndarray | None) -> list[list[Any]]:
    """Grasps from the trial's planner (:mod:`torm.methods.planner_plugins`: the built-in ``antipodal`` and plug-ins
    through the same interface), checked before execution (:func:`~torm.methods.planner_plugins.validate_grasps`)."""
    from torm.methods.planner_plugins import PlannerContext, load_planner, validate_grasps

    planner = load_planner(config.planner, dict(config.planner_options))
    ctx = PlannerContext(table_height=table_z, gripper=gripper, obstacles=obstacles, rng=rng, config=config.grasp,
                         options=dict(config.planner_options))
    try:
        out = planner.plan(per.point_clouds, per.meshes or None, ctx)
    except TormError:
        raise
    except Exception as exc:  # a plug-in's own bug: one named line, not a traceback from inside the plug-in
        if config.planner == "antipodal":
            raise
        from torm.errors import PluginError

        first = next((ln for ln in str(exc).splitlines() if ln.strip()), "")
        raise PluginError(f"planner plug-in {config.planner!r} (version {getattr(planner, 'version', '?')}) raised "
                          f"{type(exc).__name__}: {first}; fix the plug-in or use --set planner=antipodal") from exc
    return validate_grasps(config.planner, out, per.point_clouds, float(gripper.max_opening))


def fixture_positions(obstacles: np.ndarray | None) -> list[np.ndarray]:
    """Horizontal positions (m, world xy, rounded to 1 cm, unique) of the declared fixtures' obstacle points
    ``obstacles`` (N, 3); the places a released object must keep away from. Empty without fixtures."""
    if obstacles is None:
        return []
    return list(np.unique(np.round(np.asarray(obstacles)[:, :2], 2), axis=0))


class _Labels:
    """Trial-unique labels for reconstructed objects (``1000, 1001, ...`` across re-perceptions)."""

    def __init__(self) -> None:
        self.next = 1000

    def relabel(self, per: Perception) -> None:
        out = []
        for c in per.point_clouds:
            out.append(ObjectPointCloud(c.points_nx3, c.normals_nx3, self.next))
            self.next += 1
        per.point_clouds = out


def run_loop(config: TrialConfig, backend: Any, rng: np.random.Generator, timings: dict[str, float],
             record: dict[str, Any], *, observer: Any = None,
             oracle_meshes: Callable[[], dict[int, TriMesh]] | None = None, recorder: Any = None) -> list[dict]:
    """Perceive, plan and attempt every object the loop believes in; returns the attempts in order.

    Args:
        config: the trial definition.
        backend: the loop's view of the robot (:class:`torm.backend.blind.LoopBackend`).
        rng: the trial's generator.
        timings: per-stage wall times (s), updated in place.
        record: the trial record; the loop writes ``perception`` (its own view), ``n_perceptions``, ``table``,
            ``planned_order`` and, when perception fails, ``failure`` / ``message``.
        observer: told of every perception (``perceived(point_clouds)``) and every pick phase (one-way).
        oracle_meshes: see :func:`perceive`.
        recorder: a :class:`torm.viz.TrialRecorder` (images, meshes, grasps).

    Returns:
        One dict per attempt: ``label`` (the reconstruction's trial-unique id), ``n_candidates``, ``result`` (the
        :class:`~torm.execution.pick.PickResult` the robot believes, None when nothing moved), ``outcome`` and
        ``message`` when nothing moved, ``centroid_m`` (where the loop believed the object was).
    """
    rgb = bool(getattr(recorder, "wants_rgb", False))
    labels = _Labels()
    gripper = _gripper(backend)
    cal = _calibration(backend)
    obstacles = cal.obstacle_points() if cal is not None else None
    fixture_xy = fixture_positions(obstacles)

    def sense() -> tuple[Perception, dict[int, tuple[ObjectPointCloud, list]], float]:
        per = perceive(config, backend, rng, timings, rgb=rgb, oracle_meshes=oracle_meshes)
        labels.relabel(per)
        if hasattr(observer, "perceived"):
            observer.perceived(per.point_clouds)
        table_z = float(per.info["capture"].table_height)
        t = time.perf_counter()
        grasps = plan_with_planner(config, per, table_z, gripper, rng, obstacles)
        timings["grasp_planning"] = timings.get("grasp_planning", 0.0) + time.perf_counter() - t
        log.info("grasp planning: %d candidates for %d objects", sum(len(g) for g in grasps), len(grasps))
        if recorder is not None:
            recorder.perception(per.info["capture"], per.meshes or [None] * len(grasps), per.point_clouds, grasps)
        return per, {c.object_index: (c, g) for c, g in zip(per.point_clouds, grasps, strict=True)}, table_z

    try:
        per, by_label, table_z = sense()
    except ReconstructionError as exc:
        record["failure"], record["message"] = "reconstruction_failed", str(exc)
        return []
    record["perception"] = {k: v for k, v in per.info.items() if k not in ("capture", "masks_vxhxw")}
    record["table"] = per.info["table"]
    record["n_perceptions"] = 1
    record["perceptions"] = [per]  # the harness scores them and drops this key

    def best_first(keys: Any) -> list[int]:  # easiest first: by the best grasp score of each object
        return sorted(keys, key=lambda k: -(by_label[k][1][0].score if by_label[k][1] else -np.inf))

    pending = best_first(by_label)
    record["planned_order"] = list(pending)
    max_attempts = 2 * len(pending) + 2  # re-perception may show new objects; never loop forever
    place_area = np.asarray(config.place_area, dtype=float)
    # Where every object is now as the robot believes it (m, world xy): where it was seen, or where it put it down.
    where = {k: c.points_nx3[:, :2].mean(axis=0) for k, (c, _) in by_label.items()}
    attempted_xy: list[np.ndarray] = []
    attempts: list[dict[str, Any]] = []
    timings["execution"] = 0.0
    while pending and len(attempts) < max_attempts:
        if config.re_perceive and attempts and record.get("failure") != Outcome.PHYSICS.value:
            try:
                per, new, table_z = sense()
            except ReconstructionError as exc:  # keep planning on the previous reconstruction
                log.warning("re-perception before attempt %d failed (%s); using the previous one", len(attempts), exc)
            else:
                record["n_perceptions"] += 1
                record["perceptions"].append(per)
                by_label.update(new)
                where.update({k: c.points_nx3[:, :2].mean(axis=0) for k, (c, _) in new.items()})
                pending = best_first(k for k in new if not any(np.linalg.norm(where[k] - p) < SAME_OBJECT_XY
                                                               for p in attempted_xy))
                if not pending:
                    break
        label = pending.pop(0)
        cloud, cands = by_label[label]
        xy = cloud.points_nx3[:, :2].mean(axis=0)
        entry: dict[str, Any] = {"label": int(label), "n_candidates": len(cands), "result": None,
                                 "centroid_m": cloud.points_nx3.mean(axis=0).tolist()}
        attempts.append(entry)
        if record.get("failure") == Outcome.PHYSICS.value:
            entry |= {"outcome": Outcome.PHYSICS.value, "message": "trial aborted after a physics error"}
            continue
        if not cands:
            entry |= {"outcome": Outcome.NO_GRASP.value, "message": "no collision-free grasp within the stroke"}
            attempted_xy.append(xy)
            continue
        others = [p for k, p in where.items() if k != label and k in pending] + attempted_xy + fixture_xy
        t = time.perf_counter()
        try:
            dirs = free_directions(xy, others, place_area, config.pick.translate_distance)
            confirm = backend.operator_confirm() if hasattr(backend, "operator_confirm") else None
            res = execute_pick(backend, cands, dirs, replace(config.pick, table_height=table_z),
                               operator_confirm=confirm, observer=observer)
        except ExecutionError as exc:
            entry |= {"outcome": Outcome.OTHER.value, "message": str(exc)}
            attempted_xy.append(xy)
            continue
        finally:
            timings["execution"] += time.perf_counter() - t
        entry["result"] = res
        moved = res.translate_direction is not None and res.outcome in (Outcome.SUCCESS, Outcome.NOT_RELEASED)
        attempted_xy.append(xy + config.pick.translate_distance * np.asarray(res.translate_direction) if moved else xy)
        log.info("attempt %d (reconstruction %d): the robot believes %s (%.1f s)", len(attempts), label,
                 res.outcome.value, time.perf_counter() - t)
        if res.outcome is Outcome.PHYSICS:
            record["failure"] = Outcome.PHYSICS.value
    if pending:
        log.warning("stopped after %d attempts with %d objects still believed on the table", len(attempts),
                    len(pending))
    return attempts


__all__ = ["DEPTH_CHANNELS", "IMAGE_SEGMENTERS", "MASK_CHANNELS", "TABLE_SOURCES", "fixture_positions", "perceive",
           "run_loop", "table_height"]
