"""Depth-fusion baseline: fuse every view's sensor depth into a TSDF (Open3D), cut per-object meshes by the masks.

What a user with a depth camera on the arm would try first (the ``depth_fusion`` method): integrate the
sensor depth of each capture view into one truncated signed distance volume (Open3D's
``VoxelBlockGrid``: Curless & Levoy weighted integration in hashed voxel blocks, marching cubes extraction;
5x faster here than the legacy ``ScalableTSDFVolume``), then give each vertex of the
fused mesh the instance id that the masks assign it in the majority of the views where it is visible
(projects inside the image with a sensor reading within ``visibility_tol_m`` of its depth), and keep, per
object, the faces whose three vertices carry that id. The masks are the capture's (ground truth in
simulation), as for the single-view baseline, so the baseline is not penalised for segmentation.

On glass, the fused surface sits where the sensor put it: on the table behind a see-through pixel, near
the glass where it read near-surface, nowhere where it read nothing.

Frames: world (robot base, z up), m. Open3D takes world-to-camera extrinsics and pixel centres at integer
coordinates, so ``cx, cy`` are shifted by -0.5 from torm's convention (pixel centres at integer + 0.5).
Needs ``open3d`` (PyPI ``open3d-cpu`` or ``open3d``; on Debian it loads ``libusb-1.0-0``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from torm.errors import ConfigError, ReconstructionError, TormError
from torm.geometry import backproject_depth as backproject
from torm.types import Capture, TriMesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FusionConfig:
    """TSDF fusion settings (m).

    Attributes:
        voxel_m: voxel edge (m); 2 mm resolves 3 cm objects with ~15 voxels across.
        trunc_m: truncation distance of the signed distance (m), 4 voxels (Open3D's examples use 3-5).
        depth_max_m: readings farther than this are ignored (m); the capture radius is 0.5 m.
        visibility_tol_m: a vertex counts as seen in a view when the view's reading at its pixel is within
            this of its depth (m).
        min_vote: share of a vertex's visible views whose mask must name the object.
        min_faces: objects whose cut has fewer faces count as not reconstructed.
        crop_margin_m: readings whose point falls outside the capture's workspace box grown by this margin (m)
            are dropped before fusion (the floor and the far table would otherwise cost 10x the time);
            negative = no crop.
    """

    voxel_m: float = 0.002
    trunc_m: float = 0.008
    depth_max_m: float = 1.0
    visibility_tol_m: float = 0.01
    min_vote: float = 0.5
    min_faces: int = 20
    crop_margin_m: float = 0.03

    def __post_init__(self) -> None:
        for name in ("voxel_m", "trunc_m", "depth_max_m", "visibility_tol_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"fusion.{name} must be > 0 m, got {getattr(self, name)}")
        if not 0.0 < self.min_vote <= 1.0:
            raise ConfigError(f"fusion.min_vote must be in (0, 1], got {self.min_vote}")
        if self.min_faces < 1:
            raise ConfigError(f"fusion.min_faces must be >= 1, got {self.min_faces}")


def _open3d() -> Any:
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise TormError(f"the depth_fusion baseline needs Open3D ({exc}); pip install open3d-cpu (and on Debian "
                        "apt-get install libusb-1.0-0)") from exc
    return o3d


def fuse_tsdf(capture: Capture, config: FusionConfig | None = None) -> TriMesh:
    """Integrate the sensor depth of every view (``sensor_depth``, else ``depth``) into a TSDF; the fused mesh.

    Open3D's ``VoxelBlockGrid`` (hashed 8^3 voxel blocks, weighted TSDF averaging, marching cubes). Returns
    the world-frame mesh (m) with faces oriented towards the observed free space. Raises
    :class:`ReconstructionError` when no view has depth.
    """
    o3d = _open3d()
    o3c = o3d.core
    cfg = config or FusionConfig()
    dev = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32), attr_channels=((1), (1)),
        voxel_size=cfg.voxel_m, block_resolution=8, block_count=20000, device=dev)
    mult = cfg.trunc_m / cfg.voxel_m
    n = 0
    box = None
    if capture.workspace_bounds is not None and cfg.crop_margin_m >= 0:
        box = np.asarray(capture.workspace_bounds, dtype=np.float64) + np.array([[-1.0], [1.0]]) * cfg.crop_margin_m
    for v in capture.views:
        depth = v.sensor_depth if v.sensor_depth is not None else v.depth
        if depth is None:
            continue
        z = np.nan_to_num(depth, nan=0.0).astype(np.float32)
        H, W = z.shape
        K = v.K
        if box is not None:
            p = backproject(z, K).reshape(-1, 3) @ v.T_world_cam[:3, :3].T + v.T_world_cam[:3, 3]
            inside = np.all((p >= box[0]) & (p <= box[1]), axis=1).reshape(H, W)
            z = np.where(inside, z, np.float32(0.0))
        if not np.any(z > 0):
            continue
        # Open3D puts pixel centres at integer coordinates: shift the principal point by -0.5 px
        K_o3d = K.astype(np.float64).copy()
        K_o3d[0, 2] -= 0.5
        K_o3d[1, 2] -= 0.5
        intr = o3c.Tensor(K_o3d, o3c.float64)
        extr = o3c.Tensor(np.linalg.inv(v.T_world_cam), o3c.float64)
        img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(z)))
        blocks = vbg.compute_unique_block_coordinates(img, intr, extr, 1.0, cfg.depth_max_m,
                                                      trunc_voxel_multiplier=mult)
        vbg.integrate(blocks, img, intr, extr, 1.0, cfg.depth_max_m, trunc_voxel_multiplier=mult)
        n += 1
    if n == 0:
        raise ReconstructionError("depth fusion: no view has a depth reading in the workspace; capture sensor_depth")
    try:
        mesh = vbg.extract_triangle_mesh(weight_threshold=1.0)
    except RuntimeError:  # Open3D raises on an empty extraction
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    verts = mesh.vertex.positions.numpy().astype(np.float64)
    faces = mesh.triangle.indices.numpy().astype(np.int64)
    return TriMesh(verts, faces)


def label_vertices(verts_vx3: np.ndarray, capture: Capture, config: FusionConfig | None = None) -> np.ndarray:
    """(V,) int instance id per vertex by majority over the views that see it (0 = none / background)."""
    cfg = config or FusionConfig()
    ids = sorted({int(i) for v in capture.views if v.mask is not None for i in np.unique(v.mask) if i > 0})
    col = {k: j + 1 for j, k in enumerate(ids)}
    votes = np.zeros((len(verts_vx3), len(ids) + 1))
    seen = np.zeros(len(verts_vx3))
    for v in capture.views:
        depth = v.sensor_depth if v.sensor_depth is not None else v.depth
        if depth is None or v.mask is None:
            continue
        uv, z = v.project(verts_vx3)
        H, W = depth.shape
        c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (c >= 0) & (c < W) & (r >= 0) & (r < H)
        idx = np.nonzero(inside)[0]
        d = np.nan_to_num(depth[r[idx], c[idx]], nan=0.0)
        vis = (d > 0) & (np.abs(d - z[idx]) < cfg.visibility_tol_m)
        idx = idx[vis]
        m = v.mask[r[idx], c[idx]]
        seen[idx] += 1
        lut = np.zeros(int(max(ids, default=0)) + 2, np.int64)
        for k, j in col.items():
            lut[k] = j
        votes[idx, lut[np.clip(m, 0, len(lut) - 1)]] += 1
    best = votes.argmax(axis=1)
    share = votes[np.arange(len(best)), best] / np.maximum(seen, 1)
    inv = np.array([0, *ids])
    return np.where((seen > 0) & (best > 0) & (share >= cfg.min_vote), inv[best], 0)


def object_meshes(mesh: TriMesh, labels_v: np.ndarray, min_faces: int = 1) -> dict[int, TriMesh]:
    """Per instance id, the faces whose three vertices carry it (vertices re-indexed); small cuts dropped."""
    out: dict[int, TriMesh] = {}
    f = mesh.faces_fx3
    lab = labels_v[f]
    for k in sorted(int(i) for i in np.unique(labels_v) if i > 0):
        faces = f[np.all(lab == k, axis=1)]
        if len(faces) < min_faces:
            continue
        used, inv = np.unique(faces, return_inverse=True)
        out[k] = TriMesh(mesh.verts_vx3[used], inv.reshape(-1, 3))
    return out


def fuse_objects(capture: Capture, config: FusionConfig | None = None) -> tuple[dict[int, TriMesh], dict[str, Any]]:
    """TSDF fusion + mask cut: instance id -> object mesh (world, m), and diagnostics (timings s, sizes)."""
    cfg = config or FusionConfig()
    t0 = time.perf_counter()
    fused = fuse_tsdf(capture, cfg)
    t1 = time.perf_counter()
    labels = label_vertices(fused.verts_vx3, capture, cfg)
    meshes = object_meshes(fused, labels, cfg.min_faces)
    t2 = time.perf_counter()
    info = {"fusion_s": t1 - t0, "labelling_s": t2 - t1, "n_views_fused": len(capture.views),
            "fused_vertices": len(fused.verts_vx3), "fused_faces": len(fused.faces_fx3),
            "object_faces": {str(k): len(m.faces_fx3) for k, m in meshes.items()}}
    log.info("depth fusion: %d views, %d faces, %d objects in %.2f s", len(capture.views), len(fused.faces_fx3),
             len(meshes), t2 - t0)
    return meshes, info
