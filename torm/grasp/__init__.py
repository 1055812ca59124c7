"""Per-object, collision-aware grasp planning (TORM Sec. III-C).

Grasp frame (GraspNet): origin at the grasp centre, x = approach, y = closing axis, z = finger height.
"""

from torm.grasp.gripper import BOX_NAMES, GripperGeometry
from torm.grasp.onnx_graspnet import OnnxGraspPlanner
from torm.grasp.planner import (
    AntipodalGraspPlanner,
    GraspPlanner,
    GraspPlannerConfig,
    graspnet_to_grasps,
    grasps_to_graspnet,
    load_graspnet,
    plan_grasps,
    save_graspnet,
)

__all__ = [
    "BOX_NAMES",
    "AntipodalGraspPlanner",
    "GraspPlanner",
    "GraspPlannerConfig",
    "GripperGeometry",
    "OnnxGraspPlanner",
    "grasps_to_graspnet",
    "graspnet_to_grasps",
    "load_graspnet",
    "plan_grasps",
    "save_graspnet",
]
