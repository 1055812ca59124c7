"""A tiny deterministic model with the adapter's signature, for checking the plumbing (not a grasp network).

Every ``stride``-th scene point becomes a grasp approaching along the camera's optical axis (grasp x = camera z),
closing along the camera's x axis, its centre ``depth_m`` behind the point, opening ``width_m``; the score is
``1 - z`` (points nearer the camera score higher), ``object_id`` -1 (a scene model does not know objects).
Needs the ``onnx`` package (``pip install onnx``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# columns x (approach) = camera z, y (closing) = camera x, z = x cross y = camera y; row-major
R_ALONG_VIEW = (0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0)


def build_tiny_model(path: str | Path, stride: int = 64, width_m: float = 0.08, depth_m: float = 0.015) -> Path:
    """Write the model to ``path`` (ONNX, opset 17) and return the path."""
    import onnx
    from onnx import TensorProto, helper

    def const(name, values, dtype=TensorProto.FLOAT, shape=None):
        arr = np.asarray(values, np.float32 if dtype == TensorProto.FLOAT else np.int64)
        return helper.make_node("Constant", [], [name], value=helper.make_tensor(
            name + "_v", dtype, list(arr.shape if shape is None else shape), arr.ravel().tolist()))

    nodes = [
        const("s0", [0], TensorProto.INT64), const("s_end", [2**62], TensorProto.INT64),
        const("ax1", [1], TensorProto.INT64), const("step", [stride], TensorProto.INT64),
        helper.make_node("Slice", ["point_clouds", "s0", "s_end", "ax1", "step"], ["seeds"]),  # (1, K, 3)
        const("z0", [2], TensorProto.INT64), const("z1", [3], TensorProto.INT64), const("ax2", [2], TensorProto.INT64),
        helper.make_node("Slice", ["seeds", "z0", "z1", "ax2"], ["z"]),  # (1, K, 1)
        const("one", [1.0], shape=(1, 1, 1)), helper.make_node("Sub", ["one", "z"], ["score"]),
        const("zero", [0.0], shape=(1, 1, 1)), helper.make_node("Mul", ["z", "zero"], ["zb"]),
        const("pre_c", [width_m, 0.02, 0.02, *R_ALONG_VIEW], shape=(1, 1, 12)),
        helper.make_node("Add", ["zb", "pre_c"], ["pre"]),
        const("off", [0.0, 0.0, depth_m], shape=(1, 1, 3)), helper.make_node("Add", ["seeds", "off"], ["t"]),
        const("id_c", [-1.0], shape=(1, 1, 1)), helper.make_node("Add", ["zb", "id_c"], ["oid"]),
        helper.make_node("Concat", ["score", "pre", "t", "oid"], ["grasps"], axis=2),
    ]
    graph = helper.make_graph(nodes, "tiny_scene_graspnet",
                              [helper.make_tensor_value_info("point_clouds", TensorProto.FLOAT, [1, "N", 3])],
                              [helper.make_tensor_value_info("grasps", TensorProto.FLOAT, [1, "K", 17])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path
