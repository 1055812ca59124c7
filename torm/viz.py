"""Rerun logging helpers (rerun-sdk 0.41): captures, meshes and point clouds, written to ``.rrd`` files.

Typical use, no viewer needed::

    rec = rr.RecordingStream("torm")
    rec.save("capture.rrd")          # stream everything logged from here on to the file
    log_capture(rec, capture)

World entities use z up (``world`` has RIGHT_HAND_Z_UP view coordinates). Each view is an entity
``<root>/view_<i>`` with a Transform3D (camera-to-world) and a Pinhole in OpenCV axes
(``camera_xyz=RDF``); its ``rgb``, ``mask`` (SegmentationImage with object names as annotation
labels), ``depth`` and ``sensor_depth`` (DepthImage, metres) are children, so the viewer projects
them into 3D.
"""

from __future__ import annotations

import colorsys
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from torm.types import Capture, TriMesh

log = logging.getLogger(__name__)


def instance_colors(n: int) -> np.ndarray:
    """(n + 1, 3) uint8 colours: black for background (id 0), evenly spaced saturated hues for ids 1..n."""
    out = np.zeros((n + 1, 3), np.uint8)
    for k in range(1, n + 1):
        r, g, b = colorsys.hsv_to_rgb((k - 1) / max(n, 1) * 0.9, 0.75, 0.95)
        out[k] = (int(r * 255), int(g * 255), int(b * 255))
    return out


def log_annotations(rec: rr.RecordingStream, path: str, object_ids: Sequence[int], object_names: Sequence[str]) -> None:
    """Label instance ids for SegmentationImages below ``path`` (0 = background)."""
    ids = [int(i) for i in object_ids]
    names = list(object_names) or [f"object_{i}" for i in ids]
    colors = instance_colors(max(ids, default=0))
    infos: list[Any] = [rr.AnnotationInfo(id=0, label="background", color=(0, 0, 0))]
    for k, n in zip(ids, names, strict=True):
        infos.append(rr.AnnotationInfo(id=k, label=n, color=tuple(int(c) for c in colors[k])))
    rec.log(path, rr.AnnotationContext(infos), static=True)


def log_capture(
    rec: rr.RecordingStream,
    capture: Capture,
    root: str = "world/capture",
    image_views: Sequence[int] | None = None,
    jpeg_quality: int | None = 90,
) -> None:
    """Log every view of ``capture`` (poses, intrinsics, images) as static data under ``root``.

    Args:
        rec: the recording stream (e.g. ``rr.RecordingStream("torm")`` followed by ``.save(path)``).
        capture: the capture to log.
        root: entity path prefix.
        image_views: indices of the views whose images are logged (default: all); every view's
            camera frustum is logged regardless, which keeps recordings of big captures small.
        jpeg_quality: compress RGB to JPEG at this quality (None: raw pixels).
    """
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    log_annotations(rec, root, capture.object_ids, capture.object_names)
    keep = set(range(len(capture)) if image_views is None else (int(i) for i in image_views))
    H, W = capture.image_size
    for i, v in enumerate(capture.views):
        path = f"{root}/view_{i:03d}"
        T = v.T_world_cam
        rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
        rec.log(path, rr.Pinhole(image_from_camera=v.K, resolution=[W, H], camera_xyz=rr.ViewCoordinates.RDF,
                                 image_plane_distance=0.05), static=True)
        if i not in keep:
            continue
        if v.rgb is not None:
            img = rr.Image(v.rgb)
            rec.log(f"{path}/rgb", img.compress(jpeg_quality=jpeg_quality) if jpeg_quality else img, static=True)
        if v.mask is not None:
            rec.log(f"{path}/mask", rr.SegmentationImage(v.mask.astype(np.uint16), opacity=0.5), static=True)
        if v.depth is not None:
            rec.log(f"{path}/depth", rr.DepthImage(v.depth, meter=1.0), static=True)
        if v.sensor_depth is not None:
            rec.log(f"{path}/sensor_depth", rr.DepthImage(v.sensor_depth, meter=1.0), static=True)


def log_mesh(rec: rr.RecordingStream, path: str, mesh: Any, color: Sequence[int] | None = None) -> None:
    """Log a triangle mesh (:class:`~torm.types.TriMesh` or ``trimesh.Trimesh``, world frame, m) at ``path``."""
    if isinstance(mesh, TriMesh):
        verts, faces = mesh.verts_vx3, mesh.faces_fx3
    else:
        verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    kw: dict[str, Any] = {}
    if color is not None:
        kw["albedo_factor"] = list(color)
    rec.log(path, rr.Mesh3D(vertex_positions=verts, triangle_indices=faces, **kw), static=True)


def log_points(
    rec: rr.RecordingStream, path: str, points_nx3: np.ndarray, colors: np.ndarray | None = None, radius: float = 0.001
) -> None:
    """Log a point cloud (N, 3) m, optional (N, 3) uint8 colours, at ``path``."""
    rec.log(path, rr.Points3D(points_nx3, colors=colors, radii=radius), static=True)


def grasp_strips(grasp: Any, finger_depth: float = 0.04) -> list[np.ndarray]:
    """Line strips (world frame, m) drawing a parallel-jaw grasp: a U through the two finger tips plus the approach.

    Grasp frame (GraspNet): x = approach, y = closing axis; origin between the pads.
    """
    T = grasp.T_world_grasp
    x, y, o = T[:3, 0], T[:3, 1], T[:3, 3]
    half = grasp.width / 2
    tip_l, tip_r = o + y * half + x * 0.01, o - y * half + x * 0.01
    base_l, base_r = tip_l - x * finger_depth, tip_r - x * finger_depth
    mid = (base_l + base_r) / 2
    return [np.stack([tip_l, base_l, base_r, tip_r]), np.stack([mid, mid - x * 0.05])]


def log_grasps(rec: rr.RecordingStream, path: str, grasps: Sequence[Any], color: Sequence[int] = (0, 220, 220)) -> None:
    """Log grasps (:class:`~torm.types.Grasp`) as gripper outlines at ``path`` (static)."""
    strips = [s for g in grasps for s in grasp_strips(g)]
    if strips:
        rec.log(path, rr.LineStrips3D(strips, colors=[tuple(color)] * len(strips), radii=0.0015), static=True)


#: Entity roots of a trial recording.
SCENE_ROOT = "world/scene"  # robot links, table and true objects (body entities with time-varying transforms)
RECON_ROOT = "world/reconstruction"


#: Entity root of the per-step time series (gripper opening, pad force, TCP error, object heights).
SIGNALS_ROOT = "signals"
#: Entity of the pick's stage events (attempt start and end, each phase's start and end).
EVENTS_ROOT = "events"


def trial_blueprint(image_views: Sequence[int] = (0,), n_image_views: int | None = None) -> Any:
    """The saved layout of a trial recording: a 3-D view of the scene, the outcome text, the camera images of
    ``image_views`` (indices of views whose images are logged) and the time series of every pick.

    The 3-D view shows the robot, the table, the true objects (moving with physics), the reconstructed meshes,
    the grasps and the TCP path, plus the camera frustums; depth images are left out of it (their point clouds
    would swamp the scene) and shown only in the 2-D views. The time-series view plots ``signals/**``: the
    gripper opening (m), the pad force (N), the TCP tracking error (mm) and each true object's height (m), on
    the simulated clock; the text log beside it lists each pick's phases as they start and end.
    ``n_image_views`` (old spelling): the first N views.
    """
    import rerun.blueprint as rrb

    if n_image_views is not None:
        image_views = range(n_image_views)
    images = [rrb.Spatial2DView(origin=f"world/capture/view_{i:03d}", name=f"view {i}",
                                contents=["+ $origin/rgb", "+ $origin/mask"]) for i in image_views]
    view3d = rrb.Spatial3DView(origin="world", name="scene", contents=[
        "+ world/**", "- world/capture/**/depth", "- world/capture/**/sensor_depth", "- world/capture/**/rgb",
        "- world/capture/**/mask", "- world/points/**"])
    series = rrb.TimeSeriesView(origin=SIGNALS_ROOT, name="pick signals")
    events = rrb.TextLogView(origin=EVENTS_ROOT, name="pick phases")
    side = rrb.Vertical(rrb.TextDocumentView(origin="outcome", name="outcome"), *images)
    return rrb.Blueprint(rrb.Vertical(rrb.Horizontal(view3d, side, column_shares=[3, 1]),
                                      rrb.Horizontal(series, events, column_shares=[3, 1]), row_shares=[3, 1]),
                         collapse_panels=True)


def _geom_mesh(model: Any, g: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(verts (V, 3), faces (F, 3)) of MuJoCo geom ``g`` in its own frame (m); None for planes and unknown types."""
    import mujoco
    import trimesh

    t, size = int(model.geom_type[g]), model.geom_size[g]
    if t == mujoco.mjtGeom.mjGEOM_MESH:
        m = int(model.geom_dataid[g])
        v0, nv = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
        f0, nf = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
        return model.mesh_vert[v0:v0 + nv].copy(), model.mesh_face[f0:f0 + nf].copy()
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        tm = trimesh.creation.box(extents=2 * size)
    elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
        tm = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    elif t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        tm = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=24)
    elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        tm = trimesh.creation.capsule(radius=size[0], height=2 * size[1], count=[12, 12])
    elif t == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        tm = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        tm.apply_scale(size)
    else:
        return None
    return np.asarray(tm.vertices), np.asarray(tm.faces)


def _quat_mat(q_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = q_wxyz
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def outcome_markdown(record: dict[str, Any]) -> str:
    """A trial record's headline and per-object outcomes as a Markdown document (the recording's text panel)."""
    objs = record.get("objects") or []
    ctx = record.get("context") or {}
    lines = [f"## {record.get('scenario')} seed {record.get('seed')}: {record.get('method')}",
             f"**{sum(o.get('outcome') == 'success' for o in objs)}/{len(objs)} objects picked**"
             + (f" (trial failure: `{record['failure']}`)" if record.get("failure") else ""), "",
             ", ".join(f"{k}: `{v}`" for k, v in ctx.items() if v is not None), "",
             "| object | outcome | message |", "|---|---|---|"]
    lines += [f"| {o.get('object_id')}: {o.get('name')} | {o.get('outcome')} | "
              f"{str(o.get('message') or '').replace('|', '/')[:120]} |" for o in objs]
    return "\n".join(lines) + "\n"


class TrialRecorder:
    """Streams one closed-loop trial to an ``.rrd`` file with a saved layout (:func:`trial_blueprint`).

    What it logs (world frame, z up, m):

    - :meth:`scene`: once, static: the robot's visual geometry and the true object meshes as children of one
      entity per MuJoCo body (``world/scene/<body>``), the table;
    - :meth:`step`: per motion sample on the ``sim_time`` timeline (s), at most every ``period`` s: only the
      body transforms and the TCP position (nothing re-logged that does not change);
    - :meth:`perception`: the capture (frustums of every view, images of 8), reconstructed meshes, the
      point clouds (hidden in the 3-D view by default) and the planned grasps (best in cyan, others grey);
    - :meth:`finish`: the TCP path once, as one static line strip, and the outcome per object as a text document.

    ``best_effort=True`` (the benchmark runner) logs and swallows every recording error so that a recording
    problem never fails a trial, and leaves the capture as the method needs it (``wants_rgb`` False: a recorded
    benchmark trial captures what an unrecorded one does); otherwise the trial also captures the RGB images for
    the recording when its method reads none (``wants_rgb`` True).
    """

    def __init__(self, path: str, period: float = 0.05, best_effort: bool = False,
                 recording_id: str | None = None) -> None:
        self.best_effort = best_effort
        self.wants_rgb = not best_effort
        self.period = period
        self._next = -np.inf
        self._tcp: list[np.ndarray] = []
        self._bodies: list[tuple[int, str]] = []
        self._moving: list[tuple[int, str]] = []
        self._world: Any = None
        self.rec: Any = None
        #: Views whose images the layout shows (updated once the capture is logged, so no panel is blank).
        self.image_views: tuple[int, ...] = (0,)
        try:
            self.rec = rr.RecordingStream("torm_trial", recording_id=recording_id)
            self.rec.save(path, default_blueprint=trial_blueprint(self.image_views))
            self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        except Exception as exc:
            if not best_effort:
                raise
            log.warning("rerun recording %s disabled: %s", path, exc)
            self.rec = None

    def _guard(self, fn: Any, *args: Any) -> None:
        """Run a logging step; with ``best_effort`` an error is logged instead of raised."""
        if self.rec is None:
            return
        try:
            fn(*args)
        except Exception as exc:
            if not self.best_effort:
                raise
            log.warning("rerun recording: %s failed: %s", getattr(fn, "__name__", fn), exc)

    # ------------------------------------------------------------------------------------------ scene
    def scene(self, world: Any) -> None:
        """Log the robot and the true objects of a :class:`sim.world.World` (static geometry, body frames)."""
        self._guard(self._scene, world)

    def _scene(self, world: Any) -> None:
        model = world.model
        object_bodies = {o.body_id: o for o in world.objects}
        robot_group = 1  # sim.world.GROUP_ROBOT: the robot's visual geoms
        bodies: dict[int, str] = {}
        for g in range(model.ngeom):
            b = int(model.geom_bodyid[g])
            if b in object_bodies or b == 0 or int(model.geom_group[g]) != robot_group:
                continue
            mesh = _geom_mesh(model, g)
            if mesh is None:
                continue
            name = model.body(b).name or f"body{b}"
            bodies[b] = name
            path = f"{SCENE_ROOT}/{name}/geom_{g}"
            self.rec.log(path, rr.Transform3D(translation=model.geom_pos[g], mat3x3=_quat_mat(model.geom_quat[g])),
                         static=True)
            rgba = (np.clip(model.geom_rgba[g], 0, 1) * 255).astype(np.uint8)
            self.rec.log(path, rr.Mesh3D(vertex_positions=mesh[0], triangle_indices=mesh[1],
                                         albedo_factor=[int(c) for c in rgba]), static=True)
        colors = instance_colors(max(object_bodies and max(o.instance_id for o in world.objects), 1))
        for b, o in object_bodies.items():
            name = f"object_{o.instance_id}_{o.name}"
            bodies[b] = name
            c = colors[o.instance_id]
            log_mesh(self.rec, f"{SCENE_ROOT}/{name}/mesh", o.mesh, color=(int(c[0]), int(c[1]), int(c[2]), 110))
        self._bodies = sorted(bodies.items())
        self._world = world
        self._log_bodies(static=True, bodies=self._bodies)
        # bodies welded to the world (the robot's base) never move: only the others are logged per step
        self._moving = [(b, n) for b, n in self._bodies if int(model.body_weldid[b]) != 0]

    def _log_bodies(self, static: bool = False, bodies: list[tuple[int, str]] | None = None) -> None:
        d = self._world.data
        for b, name in self._moving if bodies is None else bodies:
            self.rec.log(f"{SCENE_ROOT}/{name}", rr.Transform3D(translation=d.xpos[b], mat3x3=d.xmat[b].reshape(3, 3)),
                         static=static)

    # ------------------------------------------------------------------------------------------ perception
    def perception(self, capture: Capture, meshes: Sequence[Any], clouds: Sequence[Any],
                   grasps: Sequence[Sequence[Any]]) -> None:
        """Log the capture (8 views with images), reconstructed meshes, point clouds and planned grasps."""
        self._guard(self._perception, capture, meshes, clouds, grasps)

    def _perception(self, capture: Capture, meshes: Sequence[Any], clouds: Sequence[Any],
                    grasps: Sequence[Sequence[Any]]) -> None:
        n = len(capture.views)
        logged = sorted({int(i) for i in np.linspace(0, n - 1, min(8, n))})
        log_capture(self.rec, capture, image_views=logged)
        if capture.views and capture.views[0].rgb is not None:  # show two views that have images
            self.image_views = tuple(logged[:: max(1, len(logged) // 2)][:2])
            self.rec.send_blueprint(trial_blueprint(self.image_views), make_active=True, make_default=True)
        colors = instance_colors(max(len(clouds), 1))
        for k, (cloud, mesh) in enumerate(zip(clouds, meshes, strict=False)):
            c = tuple(int(v) for v in colors[k + 1])
            if mesh is not None:
                log_mesh(self.rec, f"{RECON_ROOT}/object_{k}", mesh, color=c)
            log_points(self.rec, f"world/points/object_{k}", cloud.points_nx3, radius=0.0008)
        for k, gs in enumerate(grasps):
            log_grasps(self.rec, f"world/grasps/object_{k}", gs[:1])
            log_grasps(self.rec, f"world/grasps/object_{k}_alternatives", gs[1:], color=(120, 120, 120))

    # ------------------------------------------------------------------------------------------ motion
    def due(self, t: float) -> bool:
        """Whether a motion sample at simulated time ``t`` (s) would be logged (rate limit ``period``)."""
        return self.rec is not None and t >= self._next

    def step(self, t: float, T_world_tcp: np.ndarray, signals: dict[str, float] | None = None) -> None:
        """Log the body transforms, the TCP and the ``signals`` (name -> value, e.g. ``gripper_opening_m``) at
        simulated time ``t`` (s), rate-limited to ``period``; each true object's height is added as a signal."""
        if self.due(t):
            self._guard(self._step, t, T_world_tcp, signals or {})

    def _step(self, t: float, T_world_tcp: np.ndarray, signals: dict[str, float]) -> None:
        self._next = t + self.period
        self.rec.set_time("sim_time", duration=float(t))
        self._tcp.append(T_world_tcp[:3, 3].copy())
        self.rec.log("world/motion/tcp", rr.Points3D([T_world_tcp[:3, 3]], radii=0.006, colors=[(255, 80, 0)]))
        for name, value in signals.items():
            if value is not None and np.isfinite(value):
                self.rec.log(f"{SIGNALS_ROOT}/{name}", rr.Scalars(float(value)))
        if self._world is not None:
            self._log_bodies()
            d = self._world.data
            for o in self._world.objects:
                self.rec.log(f"{SIGNALS_ROOT}/object_height_m/{o.instance_id}_{o.name}",
                             rr.Scalars(float(d.xpos[o.body_id][2])))

    # ------------------------------------------------------------------------------------------ pick events
    def _event(self, text: str, level: str = "INFO") -> None:
        self.rec.log(EVENTS_ROOT, rr.TextLog(text, level=level))

    def attempt_started(self, grasp: Any) -> None:
        """A pick attempt starts (the grasp's centre, m, world)."""
        p = np.round(np.asarray(grasp.T_world_grasp)[:3, 3], 3).tolist()
        self._guard(self._event, f"attempt at {p} m (object {getattr(grasp, 'object_id', '?')})")

    def phase_started(self, name: str) -> None:
        self._guard(self._event, f"{name} started", "DEBUG")

    def phase_ended(self, name: str) -> None:
        self._guard(self._event, f"{name} ended", "DEBUG")

    def attempt_ended(self, result: Any) -> None:
        outcome = getattr(getattr(result, "outcome", None), "value", getattr(result, "outcome", "?"))
        self._guard(self._event, f"attempt ended: {outcome} (the robot's belief; the judge scores afterwards)",
                    "INFO")

    # ------------------------------------------------------------------------------------------ end
    def finish(self, record: dict[str, Any]) -> None:
        """Log the TCP path (once) and the trial's outcome per object as the recording's text document."""
        self._guard(self._finish, record)

    def _finish(self, record: dict[str, Any]) -> None:
        if self._tcp:
            self.rec.log("world/motion/tcp_path", rr.LineStrips3D([np.asarray(self._tcp)], radii=0.001,
                                                                 colors=[(255, 160, 0)]), static=True)
        self.rec.log("outcome", rr.TextDocument(outcome_markdown(record), media_type=rr.MediaType.MARKDOWN),
                     static=True)

    def close(self) -> None:
        """Flush and close the file (writes the .rrd footer); idempotent."""
        if self.rec is not None:
            self._guard(self.rec.flush)
            self._guard(self.rec.disconnect)
            self.rec = None
