"""``scene_graspnet``: an example torm grasp-planner plug-in that adapts a GraspNet-baseline-style ONNX model.

torm hands a planner one point cloud per object, full 360-degree surfaces in the world frame. A learned planner of
the GraspNet-baseline kind (Fang et al., CVPR 2020; graspnet-baseline, Contact-GraspNet and their exports) was
trained on something else: **one scene cloud, as a single depth camera sees it, in that camera's frame**, and it
returns GraspNet's 17-float rows in the same frame, without knowing which object a grasp belongs to. This adapter
does the translation both ways:

1. a virtual camera looks at the objects from ``view_from`` (m, world offset from the objects' centroid; default
   up and behind, like a wrist camera before a pick);
2. only the points that camera would see are kept (a z-buffer on ``cell_m`` cells), with a patch of table points
   around the objects, as a real depth image contains the support plane; the cloud is put in the camera's OpenCV
   frame (x right, y down, z forward) and sampled to ``num_points`` (graspnet-baseline: 20000);
3. the model runs (input ``point_clouds`` float32 (1, N, 3); output ``grasps`` float32 (1, K, 17) rows
   ``[score, width, height, depth, R (9, row-major), t (3), object_id]``, grasp frame x = approach, y = closing
   axis: graspnetAPI's ``GraspGroup`` layout);
4. rows are taken back to the world frame, rotations re-orthonormalised, rows with non-finite values, a width
   beyond the gripper's stroke or a score below ``min_score`` dropped, each grasp assigned to the object whose
   points lie nearest its centre (within ``assign_radius_m``; table grasps are dropped), and torm's own table and
   point collision checks and pose NMS applied (:func:`torm.grasp.planner.select_grasps`), best ``top_k`` kept.

Frames and units: world frame (robot base, z up), metres; the model's frame is the virtual camera's.
:func:`torm_scene_graspnet.tiny_model.build_tiny_model` writes a small deterministic model with this signature
for checking the plumbing (it is not a grasp network).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import PluginError
from torm.geometry import nearest_rotation
from torm.types import Grasp, ObjectPointCloud

__version__ = "0.1.0"

INPUT_NAME = "point_clouds"
OUTPUT_NAME = "grasps"
SIGNATURE = (f"input '{INPUT_NAME}' float32 (1, N, 3) scene points in the camera frame (OpenCV) -> output "
             f"'{OUTPUT_NAME}' float32 (1, K, 17) GraspNet rows [score, width, height, depth, R(9), t(3), object_id] "
             "in the same frame")


def visible_points(points_cam_nx3: np.ndarray, cell_m: float, tolerance_m: float) -> np.ndarray:
    """Boolean (N,): the points a camera sees, by a z-buffer.

    ``points_cam_nx3`` (N, 3) in the camera's OpenCV frame (z forward, m). Points are binned by their direction on
    a grid whose cells are ``cell_m`` wide at the median depth; a point is visible when it lies within
    ``tolerance_m`` of the nearest point of its cell and the 8 around it (each point is splatted over 3 x 3 cells,
    so that a sparse near surface still hides what lies behind it). Points behind the camera (z <= 0) are not visible.
    """
    from scipy.ndimage import minimum_filter

    p = np.asarray(points_cam_nx3, np.float64)
    front = p[:, 2] > 1e-6
    vis = np.zeros(len(p), bool)
    if not front.any():
        return vis
    f = float(np.median(p[front, 2])) / cell_m  # focal length in cells
    q = p[front]
    uv = np.floor(f * q[:, :2] / q[:, 2:3]).astype(np.int64)
    uv -= uv.min(axis=0)
    zmin = np.full(tuple(uv.max(axis=0) + 1), np.inf)
    np.minimum.at(zmin, (uv[:, 0], uv[:, 1]), q[:, 2])
    # each point covers its cell's neighbours too (splatting): a sparse near surface still hides what is behind it
    zmin = minimum_filter(zmin, size=3, mode="nearest")
    vis[np.flatnonzero(front)] = q[:, 2] <= zmin[uv[:, 0], uv[:, 1]] + tolerance_m
    return vis


class SceneGraspNet:
    """A GraspNet-baseline-style ONNX model as a torm grasp planner (see the module docstring).

    Args:
        model_path: the ONNX file (signature: :data:`SIGNATURE`).
        view_from: the virtual camera's position (m, world) relative to the objects' centroid.
        num_points: points fed to the model (sampled with the trial's generator; repeats when fewer are visible).
        cell_m: z-buffer cell width (m) at the objects' depth; about the spacing of the object clouds' points.
        table_patch_m: margin (m) of the table patch around the objects (0: no table points).
        min_score: network rows scoring below this are dropped.
        assign_radius_m: a grasp whose centre lies farther than this from every object's points is dropped.
        threads: onnxruntime intra-op threads.
    """

    name = "scene_graspnet"
    version = __version__

    def __init__(self, model_path: str = "", view_from: Sequence[float] = (-0.30, 0.0, 0.45),
                 num_points: int = 20000, cell_m: float = 0.004, table_patch_m: float = 0.05,
                 min_score: float = 0.0, assign_radius_m: float = 0.02, threads: int = 1) -> None:
        if not model_path or not Path(model_path).is_file():
            raise PluginError(f"planner 'scene_graspnet': model_path {model_path!r} is not a file; give "
                              f"planner_options.model_path of an ONNX model with {SIGNATURE}")
        view = np.asarray(view_from, np.float64)
        if view.shape != (3,) or np.linalg.norm(view) < 0.05:
            raise PluginError(f"planner 'scene_graspnet': view_from must be 3 numbers (m) at least 5 cm from the "
                              f"objects, got {view_from}")
        if num_points < 100 or cell_m <= 0 or table_patch_m < 0 or assign_radius_m <= 0 or threads < 1:
            raise PluginError("planner 'scene_graspnet': need num_points >= 100, cell_m > 0, table_patch_m >= 0, "
                              "assign_radius_m > 0, threads >= 1")
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        try:
            self.session = ort.InferenceSession(str(model_path), sess_options=opts,
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types
            raise PluginError(f"planner 'scene_graspnet': cannot load {model_path} ({exc}); expected {SIGNATURE}") \
                from exc
        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        found = (", ".join(f"{i.name} {i.type} {i.shape}" for i in ins) + " -> "
                 + ", ".join(f"{o.name} {o.type} {o.shape}" for o in outs))
        if (len(ins) != 1 or ins[0].name != INPUT_NAME or len(ins[0].shape) != 3
                or not any(o.name == OUTPUT_NAME and len(o.shape) == 3 for o in outs)):
            raise PluginError(f"planner 'scene_graspnet': {model_path} has {found}; expected {SIGNATURE}")
        self.model_path = str(model_path)
        self.view_from = view
        self.num_points, self.cell_m, self.table_patch_m = int(num_points), float(cell_m), float(table_patch_m)
        self.min_score, self.assign_radius_m = float(min_score), float(assign_radius_m)
        self.last_stats: dict[str, Any] = {}

    def camera_pose(self, point_clouds: Sequence[ObjectPointCloud]) -> np.ndarray:
        """(4, 4) OpenCV camera-to-world pose of the virtual camera for these objects."""
        from torm.geometry import look_at_cv

        centre = np.vstack([c.points_nx3 for c in point_clouds]).mean(axis=0)
        return look_at_cv(centre + self.view_from, centre)

    def scene_cloud(self, point_clouds: Sequence[ObjectPointCloud], table_height: float, T_world_cam: np.ndarray,
                    rng: np.random.Generator) -> np.ndarray:
        """(num_points, 3) the scene the virtual camera sees, in its frame (m)."""
        pts = np.vstack([c.points_nx3 for c in point_clouds])
        if self.table_patch_m > 0:
            lo = pts[:, :2].min(axis=0) - self.table_patch_m
            hi = pts[:, :2].max(axis=0) + self.table_patch_m
            gx, gy = np.meshgrid(np.arange(lo[0], hi[0], self.cell_m / 2), np.arange(lo[1], hi[1], self.cell_m / 2))
            table = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, table_height)])
            pts = np.vstack([pts, table])
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        cam = (pts - t) @ R  # world -> camera
        cam = cam[visible_points(cam, self.cell_m, self.cell_m)]
        idx = rng.choice(len(cam), self.num_points, replace=len(cam) < self.num_points)
        return cam[idx]

    def plan(self, point_clouds: Sequence[ObjectPointCloud], meshes: Any, context: Any) -> list[list[Grasp]]:
        """One list per cloud (input order), best first, world frame (see the module docstring)."""
        from scipy.spatial import cKDTree

        from torm.grasp.antipodal import GraspCandidates
        from torm.grasp.planner import prepare_scene, select_grasps

        if not point_clouds:
            return []
        T = self.camera_pose(point_clouds)
        cloud = self.scene_cloud(point_clouds, context.table_height, T, context.rng)
        rows = np.asarray(self.session.run([OUTPUT_NAME], {INPUT_NAME: cloud[None].astype(np.float32)})[0],
                          np.float64)
        if rows.ndim != 3 or rows.shape[0] != 1 or rows.shape[2] != 17:
            raise PluginError(f"planner 'scene_graspnet': the model returned shape {rows.shape}; expected {SIGNATURE}")
        rows = rows[0]
        R_cam, t_cam = rows[:, 4:13].reshape(-1, 3, 3), rows[:, 13:16]
        score, width, depth = rows[:, 0], rows[:, 1], rows[:, 3]
        g = context.gripper
        ok = np.all(np.isfinite(rows[:, :16]), axis=1) & (score >= self.min_score) & (width <= g.max_opening + 1e-9)
        ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], R_cam, np.eye(3)))) > 1e-6
        R_w = T[:3, :3] @ nearest_rotation(R_cam[ok]) if ok.any() else np.zeros((0, 3, 3))
        t_w = t_cam[ok] @ T[:3, :3].T + T[:3, 3]
        # which object each grasp is for: the one with the nearest point to its centre
        owner = np.concatenate([np.full(len(c.points_nx3), k) for k, c in enumerate(point_clouds)])
        dist, nearest = cKDTree(np.vstack([c.points_nx3 for c in point_clouds])).query(t_w) if len(t_w) else \
            (np.zeros(0), np.zeros(0, int))
        mine = dist <= self.assign_radius_m
        obj = owner[nearest[mine]]
        nan = np.full(int(mine.sum()), np.nan)
        cands = GraspCandidates(obj, R_w[mine], t_w[mine], np.clip(width[ok][mine], g.min_opening, g.max_opening),
                                np.clip(depth[ok][mine], 0.0, g.finger_length), nan, nan)
        scene = prepare_scene(point_clouds, meshes)
        stats: dict[str, Any] = {"scene_points": len(cloud), "network_rows": len(rows), "valid_rows": int(ok.sum()),
                                 "assigned_rows": int(mine.sum())}
        out = select_grasps(cands, score[ok][mine], scene, g, context.table_height, context.config, stats,
                            context.obstacles)
        self.last_stats = stats
        return out


__all__ = ["SIGNATURE", "SceneGraspNet", "visible_points"]
