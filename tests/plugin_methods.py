"""Plug-in perception methods the tests load by ``module:callable`` (tests/ is on sys.path under pytest)."""

from __future__ import annotations

import numpy as np

from torm.methods import MethodContext, Needs, ObjectEstimate
from torm.types import Capture


class Crashing:
    """A plug-in whose perceive() raises: the harness must isolate it to its own trial row."""

    name, version = "crashing", "0.0.1"
    needs = Needs(rgb=False, masks=True, views="top_down")

    def perceive(self, capture: Capture, context: MethodContext) -> list[ObjectEstimate]:
        raise RuntimeError("this plug-in always fails")


class Returns:
    """A plug-in that returns whatever it was built with (``kind``): for the output checks."""

    name, version = "returns", "0.0.1"
    needs = Needs(rgb=False, masks=True, views="top_down")

    def __init__(self, kind: str = "ok") -> None:
        self.kind = kind

    def perceive(self, capture: Capture, context: MethodContext):
        p = np.random.default_rng(0).normal([0.55, 0.0, 0.05], 0.01, (50, 3))
        if self.kind == "nan":
            p[3] = np.nan
        elif self.kind == "camera_frame":
            p = p - [0.55, 0.0, 0.6]
        elif self.kind == "mm":
            p = p * 1000.0
        elif self.kind == "shape":
            p = p[:, :2]
        elif self.kind == "array":
            return p
        return [ObjectEstimate(p)]


class RaisingPlanner:
    """A planner plug-in with a bug: ``plan`` raises."""

    name, version = "raising", "0.0.2"

    def plan(self, point_clouds, meshes, context):
        raise ZeroDivisionError("division by zero in my grasp scorer\nsecond line")


class TopDown:
    """A planner plug-in: one top-down grasp per object, closing along world y, 2 cm below its top."""

    name, version = "top_down", "0.0.1"

    def __init__(self, frame: str = "world") -> None:
        self.frame = frame

    def plan(self, point_clouds, meshes, context):
        from torm.types import Grasp

        out = []
        for c in point_clouds:
            p = c.points_nx3
            T = np.eye(4)
            T[:3, 0], T[:3, 1], T[:3, 2] = [0, 0, -1], [0, 1, 0], [1, 0, 0]
            T[:3, 3] = [*p[:, :2].mean(axis=0), p[:, 2].max() - 0.02]
            if self.frame == "object":
                T[:3, 3] -= p.mean(axis=0)  # a mistake the harness must catch
            width = min(float(np.ptp(p[:, 1])) + 0.01, context.gripper.max_opening)
            out.append([Grasp(T, width, 1.0, c.object_index)])
        return out
