"""The backend protocol shared by the simulated and the real robot, and the safety layer around it."""

from torm.backend.protocol import Arm, ArmState, Backend, Camera, Clock, Gripper, GripperState, GroundTruth
from torm.backend.safety import SafeArm, SafetyError, SafetyLimits

__all__ = [
    "Arm", "ArmState", "Backend", "Camera", "Clock", "Gripper", "GripperState", "GroundTruth",
    "SafeArm", "SafetyError", "SafetyLimits",
]
