"""The adapter on two cylinders with the tiny model: grasps come back in the world frame, at their objects, from
above; the visibility filter keeps the near side; a wrong model file is a named error."""

import numpy as np
import pytest
import trimesh
from torm_scene_graspnet import SceneGraspNet, visible_points
from torm_scene_graspnet.tiny_model import build_tiny_model

from torm.errors import PluginError
from torm.grasp.gripper import GripperGeometry
from torm.grasp.planner import GraspPlannerConfig
from torm.methods.planner_plugins import PlannerContext, validate_grasps
from torm.types import ObjectPointCloud


def _cylinder(x: float, y: float, k: int) -> ObjectPointCloud:
    m = trimesh.creation.cylinder(radius=0.025, height=0.10, sections=64)
    m.apply_translation([x, y, 0.05])
    p, fi = trimesh.sample.sample_surface(m, 2048, seed=k)
    return ObjectPointCloud(np.asarray(p), m.face_normals[fi].copy(), k)


def _ctx(seed=0):
    return PlannerContext(table_height=0.0, gripper=GripperGeometry(), obstacles=None,
                          rng=np.random.default_rng(seed), config=GraspPlannerConfig())


def test_visible_points_keeps_the_near_face_of_a_cube():
    g = np.linspace(-0.05, 0.05, 21)
    a, b = np.meshgrid(g, g)
    near = np.column_stack([a.ravel(), b.ravel(), np.full(a.size, 0.45)])
    far = near + [0, 0, 0.1]
    vis = visible_points(np.vstack([near, far]), cell_m=0.005, tolerance_m=0.005)
    assert vis[: len(near)].all() and not vis[len(near):].any()
    assert not visible_points(np.array([[0.0, 0.0, -1.0]]), 0.005, 0.005).any()  # behind the camera


def test_adapter_plans_top_grasps_for_every_object_in_the_world_frame(tmp_path):
    model = build_tiny_model(tmp_path / "tiny.onnx")
    clouds = [_cylinder(0.50, -0.10, 1), _cylinder(0.55, 0.10, 2)]
    planner = SceneGraspNet(str(model))
    out = validate_grasps("scene_graspnet", planner.plan(clouds, None, _ctx()), clouds, GripperGeometry().max_opening)
    assert len(out) == 2 and all(out), planner.last_stats
    for gl, c in zip(out, clouds, strict=True):
        for g in gl:
            centre = g.T_world_grasp[:3, 3]
            assert np.linalg.norm(centre[:2] - c.points_nx3[:, :2].mean(axis=0)) < 0.04
            assert g.T_world_grasp[2, 0] < -0.5  # approach points down: the camera looks down at the objects
        assert [g.score for g in gl] == sorted((g.score for g in gl), reverse=True)
    assert planner.last_stats["assigned_rows"] < planner.last_stats["valid_rows"]  # table grasps were dropped


def test_a_wrong_model_is_a_named_error(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    g = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "wrong",
                          [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    onnx.save(m, str(tmp_path / "wrong.onnx"))
    with pytest.raises(PluginError, match=r"has x tensor\(float\) \[1, 3\].*expected input 'point_clouds'"):
        SceneGraspNet(str(tmp_path / "wrong.onnx"))
    with pytest.raises(PluginError, match="is not a file"):
        SceneGraspNet(str(tmp_path / "missing.onnx"))
