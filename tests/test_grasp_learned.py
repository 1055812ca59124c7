"""ONNX (GraspNet-style) planner plumbing with a tiny deterministic model built by onnx.helper."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import trimesh
from onnx import TensorProto, helper

from torm.errors import ModelFileError
from torm.grasp import GraspPlanner
from torm.grasp.onnx_graspnet import OnnxGraspPlanner
from torm.types import ObjectPointCloud

# top-down: x = -z, y = +y, z = x cross y = +x ; from below: x = +z, y = +y, z = -x
R_TOP = [0, 0, 1, 0, 1, 0, -1, 0, 0]
R_BELOW = [0, 0, -1, 0, 1, 0, 1, 0, 0]


def _const(name: str, values, shape) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=helper.make_tensor(name + "_v", TensorProto.FLOAT, shape,
                                                                              np.asarray(values, np.float32).ravel()))


def build_model(path, last_dim: int = 17, input_name: str = "point_clouds") -> None:
    """Per cloud two grasps in the object-centred frame:
    0: top-down at (mean_x, mean_y, max_z - 0.015), width 0.07, score 0.9;
    1: from below at the centroid, width 0.07, score 0.95 (hits the table: must be filtered out)."""
    extra = last_dim - 17
    nodes = [
        helper.make_node("ReduceMean", [input_name], ["mean"], axes=[1], keepdims=1),  # (B, 1, 3)
        helper.make_node("ReduceMax", [input_name], ["max"], axes=[1], keepdims=1),
        _const("mxy", [1, 1, 0], (1, 1, 3)), _const("mz", [0, 0, 1], (1, 1, 3)),
        _const("off", [0, 0, -0.015], (1, 1, 3)),
        helper.make_node("Mul", ["mean", "mxy"], ["a"]), helper.make_node("Mul", ["max", "mz"], ["b"]),
        helper.make_node("Add", ["a", "b"], ["ab"]), helper.make_node("Add", ["ab", "off"], ["t0"]),
        _const("zero", [0.0], (1, 1, 1)),
        helper.make_node("ReduceMean", ["mean"], ["m1"], axes=[2], keepdims=1),  # (B, 1, 1)
        helper.make_node("Mul", ["m1", "zero"], ["zb"]),  # zeros (B, 1, 1) to broadcast constants over B
        _const("pre0", [0.9, 0.07, 0.022, 0.02, *R_TOP], (1, 1, 13)),
        _const("pre1", [0.95, 0.07, 0.022, 0.02, *R_BELOW], (1, 1, 13)),
        _const("suf", [0.0] * (1 + extra), (1, 1, 1 + extra)),
        helper.make_node("Add", ["zb", "pre0"], ["p0"]), helper.make_node("Add", ["zb", "pre1"], ["p1"]),
        helper.make_node("Add", ["zb", "suf"], ["s"]),
        helper.make_node("Concat", ["p0", "t0", "s"], ["g0"], axis=2),
        helper.make_node("Concat", ["p1", "mean", "s"], ["g1"], axis=2),
        helper.make_node("Concat", ["g0", "g1"], ["grasps"], axis=1),
    ]
    graph = helper.make_graph(
        nodes, "tiny_grasp",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["B", "N", 3])],
        [helper.make_tensor_value_info("grasps", TensorProto.FLOAT, ["B", 2, last_dim])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _cylinder_cloud(x: float, y: float, k: int) -> ObjectPointCloud:
    m = trimesh.creation.cylinder(radius=0.03, height=0.10, sections=64)
    m.apply_translation([x, y, 0.05])
    p, fi = trimesh.sample.sample_surface(m, 1024, seed=k)
    return ObjectPointCloud(np.asarray(p), m.face_normals[fi].copy(), k)


def test_onnx_planner_runs_model_and_filters_collisions(tmp_path):
    path = tmp_path / "tiny.onnx"
    build_model(path)
    planner = OnnxGraspPlanner(path)
    assert isinstance(planner, GraspPlanner)
    pcs = [_cylinder_cloud(0.45, -0.1, 0), _cylinder_cloud(0.65, 0.1, 1)]
    grasps = planner.plan(pcs, table_height=0.0)
    assert planner.last_stats["network_rows"] == 4
    assert [len(g) for g in grasps] == [1, 1]  # the from-below grasp hits the table
    for k, (pc, gs) in enumerate(zip(pcs, grasps, strict=True)):
        g = gs[0]
        assert g.object_id == k and g.score == pytest.approx(0.9) and g.width == pytest.approx(0.07)
        c = pc.points_nx3.mean(axis=0)
        top = pc.points_nx3[:, 2].max()
        assert np.allclose(g.T_world_grasp[:3, 3], [c[0], c[1], top - 0.015], atol=1e-5)
        assert np.allclose(g.T_world_grasp[:3, :3].reshape(-1), R_TOP, atol=1e-6)
    # a neighbour right above the first cylinder blocks its approach
    blocker = _cylinder_cloud(0.45, -0.1, 2)
    lifted = ObjectPointCloud(blocker.points_nx3 + [0.0, 0.0, 0.13], blocker.normals_nx3, 2)
    grasps = planner.plan([pcs[0], pcs[1], lifted])
    assert grasps[0] == [] and len(grasps[1]) == 1


def test_missing_or_mismatched_model_raises_model_file_error(tmp_path):
    with pytest.raises(ModelFileError, match="point_clouds"):
        OnnxGraspPlanner(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    build_model(bad, last_dim=18)
    with pytest.raises(ModelFileError, match=r"bad\.onnx.*\(B, K, 17\)"):
        OnnxGraspPlanner(bad)
    renamed = tmp_path / "renamed.onnx"
    build_model(renamed, input_name="xyz")
    with pytest.raises(ModelFileError, match="xyz"):
        OnnxGraspPlanner(renamed)
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(ModelFileError, match="garbage.onnx"):
        OnnxGraspPlanner(garbage)
