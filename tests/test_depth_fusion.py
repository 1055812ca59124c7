"""depth_fusion baseline (torm/fusion.py): an opaque box fused from exact depth views, cut by its masks."""

from __future__ import annotations

import numpy as np
import trimesh

from torm.fusion import FusionConfig, fuse_objects, label_vertices, object_meshes
from torm.geometry import look_at_cv
from torm.mesh.sample import sample_surface
from torm.metrics import chamfer_distance_mm
from torm.reconstruction.raster import render_depth
from torm.types import CameraView, Capture, TriMesh

#: Stated bound for the test below: 2 mm voxels fused from exact depth reconstruct the box's seen surface
#: (top and sides; its bottom rests on the table) within this Chamfer distance.
BOX_CHAMFER_MM = 2.0


def _box_capture(n_views: int = 16, W: int = 160, H: int = 120) -> tuple[Capture, trimesh.Trimesh]:
    box = trimesh.creation.box(extents=(0.05, 0.04, 0.06))
    box.apply_translation([0.55, 0.0, 0.03])
    table = trimesh.creation.box(extents=(0.6, 0.6, 0.01))
    table.apply_translation([0.55, 0.0, -0.005])
    scene = trimesh.util.concatenate([box, table])
    f = 0.6 * W
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    views = []
    for i in range(n_views):
        el, az = np.radians(30 + 40 * (i % 2)), 2 * np.pi * i / n_views
        d_eye = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        eye = np.array([0.55, 0.0, 0.0]) + 0.5 * d_eye
        T = look_at_cv(eye, np.array([0.55, 0.0, 0.02]))
        T_cw = np.linalg.inv(T)
        d = render_depth(scene.vertices, scene.faces, K, T_cw, H, W)
        db = render_depth(box.vertices, box.faces, K, T_cw, H, W)
        mask = ((db > 0) & (np.abs(db - d) < 1e-4)).astype(np.int32)
        views.append(CameraView(K=K, T_world_cam=T, mask=mask, sensor_depth=d, depth=d))
    bounds = np.array([[0.33, -0.22, -0.005], [0.77, 0.22, 0.20]])
    return Capture(views=tuple(views), object_ids=(1,), object_names=("box",), workspace_bounds=bounds), box


def test_fusion_reconstructs_an_opaque_box():
    cap, box = _box_capture()
    meshes, info = fuse_objects(cap, FusionConfig())
    assert list(meshes) == [1]
    m = meshes[1]
    seen = TriMesh(box.vertices, box.faces[box.face_normals[:, 2] > -0.5])  # the bottom is never seen
    r = np.random.default_rng(0)
    cd = chamfer_distance_mm(sample_surface(m, 20000, r).points_nx3, sample_surface(seen, 20000, r).points_nx3)
    assert cd < BOX_CHAMFER_MM, cd
    # faces face the cameras: the top's normals point up
    cloud = sample_surface(m, 5000, r)
    top = cloud.points_nx3[:, 2] > 0.058
    assert top.sum() > 100 and np.median(cloud.normals_nx3[top, 2]) > 0.9
    assert info["n_views_fused"] == len(cap.views)


def test_labelling_needs_a_majority_and_empty_inputs_are_handled():
    cap, _ = _box_capture(n_views=4)
    far = np.array([[5.0, 5.0, 5.0], [0.55, 0.0, 0.06]])
    lab = label_vertices(far, cap, FusionConfig())
    assert lab[0] == 0 and lab[1] == 1
    empty = TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    assert object_meshes(empty, np.zeros(0, np.int64)) == {}
