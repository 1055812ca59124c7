"""A learned (GraspNet-style) grasp planner behind the :class:`~torm.grasp.planner.GraspPlanner` protocol.

The user supplies an ONNX model (no weights ship with torm) with this signature:

* input ``point_clouds``: float32 ``(B, N, 3)``, one row per object, **object-centred**: each object's
  points (world frame, m) minus that object's centroid (the mean of its points). B and N may be dynamic.
* output ``grasps``: float32 ``(B, K, 17)`` GraspNet rows ``[score, width, height, depth, R (9, row-major),
  t (3), object_id]`` in the same object-centred frame (world axes, translation relative to the centroid);
  grasp frame x = approach, y = closing axis, z = finger height. The object_id column is ignored.

The planner adds the centroids back, re-orthonormalises the rotations, drops rows with non-finite
values, a width beyond the stroke or a score below ``min_score``, and then applies the same table and
point-collision checks and pose-space NMS as the analytic planner (:func:`torm.grasp.planner.select_grasps`),
keeping the best ``top_k`` per object. A missing or mismatched model raises
:class:`~torm.errors.ModelFileError` naming the file and the expected signature.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ModelFileError
from torm.geometry import nearest_rotation
from torm.grasp.antipodal import GraspCandidates
from torm.grasp.gripper import GripperGeometry
from torm.grasp.planner import GraspPlannerConfig, prepare_scene, select_grasps
from torm.types import Grasp, ObjectPointCloud, TriMesh

log = logging.getLogger(__name__)

INPUT_NAME = "point_clouds"
OUTPUT_NAME = "grasps"
EXPECTED_SIGNATURE = (
    f"input '{INPUT_NAME}' float32 (B, N, 3) object-centred points -> output '{OUTPUT_NAME}' float32 (B, K, 17) "
    "GraspNet rows [score, width, height, depth, R(9), t(3), object_id] in the object-centred frame"
)


class OnnxGraspPlanner:
    """Runs a GraspNet-style ONNX model on the object clouds, then the analytic collision filter.

    Args:
        model_path: the ONNX file (see the module docstring for the expected signature).
        gripper: geometry for the collision checks (default: Robotiq 2F-85).
        config: the analytic planner's config; its collision, NMS and ``top_k`` settings apply.
        min_score: network rows scoring below this are dropped.
        providers: onnxruntime execution providers (CPU by default).
    """

    def __init__(self, model_path: str | Path, gripper: GripperGeometry | None = None,
                 config: GraspPlannerConfig | None = None, min_score: float = 0.0,
                 providers: Sequence[str] = ("CPUExecutionProvider",)) -> None:
        self.model_path = Path(model_path)
        self.gripper = gripper or GripperGeometry()
        self.config = config or GraspPlannerConfig()
        self.min_score = float(min_score)
        self.last_stats: dict[str, Any] = {}
        if not self.model_path.is_file():
            raise ModelFileError(f"grasp model {self.model_path} does not exist; give the path of an ONNX model with "
                                 f"{EXPECTED_SIGNATURE}")
        import onnxruntime as ort

        try:
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 2
            self.session = ort.InferenceSession(str(self.model_path), sess_options=opts, providers=list(providers))
        except Exception as exc:  # onnxruntime raises its own exception types
            raise ModelFileError(f"cannot load grasp model {self.model_path} ({exc}); expected an ONNX model with "
                                 f"{EXPECTED_SIGNATURE}") from exc
        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        problems = []
        if len(ins) != 1 or ins[0].name != INPUT_NAME or len(ins[0].shape) != 3 or ins[0].type != "tensor(float)":
            problems.append("inputs " + ", ".join(f"{i.name} {i.type} {i.shape}" for i in ins))
        if not any(o.name == OUTPUT_NAME for o in outs):
            problems.append("outputs " + ", ".join(f"{o.name} {o.type} {o.shape}" for o in outs))
        else:
            o = next(o for o in outs if o.name == OUTPUT_NAME)
            last = o.shape[-1] if o.shape else None
            if len(o.shape) != 3 or (isinstance(last, int) and last != 17):
                problems.append(f"output {o.name} has shape {o.shape}")
        if problems:
            raise ModelFileError(f"grasp model {self.model_path} has {'; '.join(problems)}; "
                                 f"expected {EXPECTED_SIGNATURE}")

    def predict(self, centred_bxnx3: np.ndarray) -> np.ndarray:
        """Raw network output (B, K, 17) for object-centred clouds (B, N, 3)."""
        out = self.session.run([OUTPUT_NAME], {INPUT_NAME: np.ascontiguousarray(centred_bxnx3, dtype=np.float32)})[0]
        out = np.asarray(out, dtype=np.float64)
        B = centred_bxnx3.shape[0]
        if out.ndim != 3 or out.shape[0] != B or out.shape[2] != 17:
            raise ModelFileError(f"grasp model {self.model_path} returned shape {out.shape} for {B} clouds; expected "
                                 f"{EXPECTED_SIGNATURE}")
        return out

    def plan(self, point_clouds: Sequence[ObjectPointCloud], meshes: Sequence[TriMesh | None] | None = None,
             table_height: float = 0.0) -> list[list[Grasp]]:
        """One list per cloud (input order), best first; empty when no network grasp survives the checks."""
        scene = prepare_scene(point_clouds, meshes)
        K = len(scene.object_ids)
        if K == 0:
            return []
        centroid = scene.points.mean(axis=1)  # (K, 3)
        rows = self.predict(scene.points - centroid[:, None, :])  # (K, M, 17)
        M = rows.shape[1]
        flat = rows.reshape(-1, 17)
        obj = np.repeat(np.arange(K), M)
        R = flat[:, 4:13].reshape(-1, 3, 3)
        t = flat[:, 13:16] + centroid[obj]
        score, width, depth = flat[:, 0], flat[:, 1], flat[:, 3]
        g = self.gripper
        ok = np.all(np.isfinite(flat[:, :16]), axis=1) & (score >= self.min_score) & (width <= g.max_opening + 1e-9)
        ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], R, np.eye(3)))) > 1e-6
        obj, R, t, score, width, depth = obj[ok], R[ok], t[ok], score[ok], width[ok], depth[ok]
        if len(R):
            R = nearest_rotation(R)
        width = np.clip(width, g.min_opening, g.max_opening)
        depth = np.clip(depth, 0.0, g.finger_length)
        nan = np.full(len(obj), np.nan)
        cands = GraspCandidates(obj, R, t, width, depth, nan, nan)
        stats: dict[str, Any] = {"network_rows": int(K * M), "valid_rows": int(ok.sum())}
        out = select_grasps(cands, score, scene, g, table_height, self.config, stats)
        self.last_stats = stats
        log.debug("learned grasp planning: %s", stats)
        return out
