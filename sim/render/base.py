"""The renderer interface shared by the MuJoCo rasteriser and the physically based renderer.

A :class:`Renderer` is bound to one world (it reads the world's *current* state at each call) and renders a
list of :class:`RenderCamera` into :class:`RenderedView` (RGB + instance ids). Units: metres; poses
``T_world_cam`` (4, 4) in OpenCV camera axes (x right, y down, z forward); ``K`` (3, 3) pinhole intrinsics in
pixels, pixel ``(i, j)`` covering ``[i, i+1) x [j, j+1)`` (pixel centres at ``i + 0.5``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from torm.errors import CaptureError
from torm.geometry import is_rotation


class RenderError(CaptureError):
    """A renderer cannot run (missing library, unsupported camera) or its inputs are invalid."""


@dataclass(frozen=True, eq=False)
class RenderCamera:
    """One pinhole camera: ``K`` (3, 3) px, ``T_world_cam`` (4, 4) OpenCV axes (m), image ``width`` x ``height`` px."""

    K: np.ndarray
    T_world_cam: np.ndarray
    width: int
    height: int
    name: str = ""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        T = np.asarray(self.T_world_cam, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise RenderError(f"camera {self.name!r}: K must be a finite (3, 3) matrix with positive focal lengths")
        if K[0, 1] != 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise RenderError(f"camera {self.name!r}: K must be a pinhole matrix without skew, got {K.tolist()}")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not is_rotation(T[:3, :3], tol=1e-4):
            raise RenderError(f"camera {self.name!r}: T_world_cam must be a finite rigid (4, 4) transform")
        if int(self.width) < 1 or int(self.height) < 1:
            raise RenderError(f"camera {self.name!r}: image size {self.width}x{self.height} must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_world_cam", T)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def project(self, points_world_nx3: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates (u right, v down; continuous, centres at i + 0.5) of world points (N, 3) m."""
        p = np.asarray(points_world_nx3, dtype=np.float64).reshape(-1, 3)
        R, t = self.T_world_cam[:3, :3], self.T_world_cam[:3, 3]
        pc = (p - t) @ R
        return pc[:, :2] / pc[:, 2:3] * np.diag(self.K)[:2] + self.K[:2, 2]


@dataclass(frozen=True, eq=False)
class RenderedView:
    """One rendered camera: ``rgb`` (H, W, 3) uint8 and ``instance`` (H, W) int32 (0 background, k = object k)
    or None when not requested; ``info`` says who rendered it (renderer, settings, timing, cache hit)."""

    rgb: np.ndarray | None
    instance: np.ndarray | None
    info: dict


@runtime_checkable
class Renderer(Protocol):
    """RGB + instance ids of a world for a list of cameras (the world's state at call time)."""

    #: ``mujoco`` or ``pbr``
    name: str

    def render(self, cameras: Sequence[RenderCamera], *, rgb: bool = True, instance: bool = True
               ) -> list[RenderedView]:
        """One :class:`RenderedView` per camera, in order."""
        ...

    def close(self) -> None:
        """Free resources (GL context, scene); the renderer cannot render afterwards."""
        ...
