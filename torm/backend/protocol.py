"""Backend protocol: what the harness (trial, benchmark, env) may ask of a robot, simulated or real.

The harness talks only to these interfaces; ``sim/backend.py`` implements them on MuJoCo and
``torm/hardware/`` on the real Inovo arm, Robotiq 2F-85 and RealSense D455. Frames: world = robot
base frame (z up, metres); joint values in radians; times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from torm.types import CameraView, Capture, TriMesh


@dataclass(frozen=True)
class ArmState:
    """Arm state: joint positions ``q`` (n,) rad, velocities ``qd`` (n,) rad/s, TCP pose (4, 4) in the world, time s."""

    q: np.ndarray
    qd: np.ndarray
    T_world_tcp: np.ndarray
    time: float


@dataclass(frozen=True)
class GripperState:
    """Gripper state: opening ``width`` (m), raw command (0..255), whether an object is detected between the pads."""

    width: float
    command: int
    object_detected: bool


@runtime_checkable
class Arm(Protocol):
    """A position-controlled arm."""

    joint_names: tuple[str, ...]

    def state(self) -> ArmState: ...

    def forward_kinematics(self, q: np.ndarray) -> np.ndarray:
        """TCP pose (4, 4) in the world for joint positions ``q`` (n,) rad, without moving."""
        ...

    def follow_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray) -> ArmState:
        """Track joint waypoints ``q_txn`` (T, n) rad at ``times_s`` (T,) s from now; blocks until done."""
        ...

    def stop(self) -> None:
        """Stop all motion now."""
        ...


@runtime_checkable
class Gripper(Protocol):
    """A parallel-jaw gripper commanded by opening width."""

    max_width: float

    def activate(self) -> None: ...

    def move(self, width_m: float, speed_mps: float = 0.1, force_n: float = 100.0) -> GripperState:
        """Move the jaws to ``width_m`` (m) at ``speed_mps`` (m/s), at most ``force_n`` (N); blocks until settled."""
        ...

    def state(self) -> GripperState: ...


@runtime_checkable
class Camera(Protocol):
    """A calibrated colour camera."""

    def read(self) -> CameraView:
        """One frame with intrinsics and its world pose (OpenCV axes)."""
        ...


@runtime_checkable
class Clock(Protocol):
    """Time source; simulated time in the simulator, wall time on the real robot."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


@runtime_checkable
class GroundTruth(Protocol):
    """Privileged information only a simulator has (used to judge success, never by the pipeline)."""

    def object_poses(self) -> dict[int, np.ndarray]:
        """Instance id -> (4, 4) object pose in the world."""
        ...

    def table_height(self) -> float: ...

    def object_meshes(self) -> dict[int, TriMesh]:
        """Instance id -> the object's true outer surface in the world frame at its current pose (m)."""
        ...


@runtime_checkable
class Backend(Protocol):
    """Everything a trial needs from a robot."""

    name: str
    arm: Arm
    gripper: Gripper
    clock: Clock
    ground_truth: GroundTruth | None

    def capture(self, n_views: int | None = None) -> Capture:
        """Multi-view capture of the workspace (simulated rig, or the wrist camera moved over the hemisphere)."""
        ...

    def close(self) -> None: ...
