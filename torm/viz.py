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
