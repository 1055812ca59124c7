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
from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from torm.types import Capture, TriMesh


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


class TrialRecorder:
    """Streams one closed-loop trial to an ``.rrd`` file: capture, meshes, grasps and the executed motion.

    The motion is logged on the ``sim_time`` timeline (s) from a backend step callback, at most every
    ``period`` seconds: the TCP position and every object's position (world frame, m).
    """

    def __init__(self, path: str, period: float = 0.05) -> None:
        self.rec = rr.RecordingStream("torm_trial")
        self.rec.save(path)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.period = period
        self._next = -np.inf
        self._tcp: list[np.ndarray] = []

    def perception(self, capture: Capture, meshes: Sequence[Any], clouds: Sequence[Any],
                   grasps: Sequence[Sequence[Any]]) -> None:
        """Log the capture (8 views with images), reconstructed meshes, point clouds and planned grasps."""
        n = len(capture.views)
        log_capture(self.rec, capture, image_views=sorted({int(i) for i in np.linspace(0, n - 1, min(8, n))}))
        colors = instance_colors(max(len(clouds), 1))
        for k, (cloud, mesh) in enumerate(zip(clouds, meshes, strict=False)):
            c = tuple(int(v) for v in colors[k + 1])
            if mesh is not None:
                log_mesh(self.rec, f"world/reconstruction/object_{k}", mesh, color=c)
            log_points(self.rec, f"world/points/object_{k}", cloud.points_nx3, radius=0.0008)
        for k, gs in enumerate(grasps):
            log_grasps(self.rec, f"world/grasps/object_{k}", gs[:1])
            log_grasps(self.rec, f"world/grasps/object_{k}_alternatives", gs[1:], color=(120, 120, 120))

    def due(self, t: float) -> bool:
        """Whether a motion sample at simulated time ``t`` (s) would be logged (rate limit ``period``)."""
        return t >= self._next

    def step(self, t: float, T_world_tcp: np.ndarray, object_positions: dict[int, np.ndarray]) -> None:
        """Log the TCP and object positions at simulated time ``t`` (s), rate-limited to ``period``."""
        if not self.due(t):
            return
        self._next = t + self.period
        self.rec.set_time("sim_time", duration=float(t))
        self._tcp.append(T_world_tcp[:3, 3].copy())
        self.rec.log("world/motion/tcp", rr.Points3D([T_world_tcp[:3, 3]], radii=0.006, colors=[(255, 80, 0)]))
        self.rec.log("world/motion/tcp_path", rr.LineStrips3D([np.asarray(self._tcp)], radii=0.001))
        ids = sorted(object_positions)
        if ids:
            self.rec.log("world/motion/objects", rr.Points3D([object_positions[i] for i in ids], radii=0.01,
                                                            labels=[str(i) for i in ids]))

    def close(self) -> None:
        self.rec.flush()
