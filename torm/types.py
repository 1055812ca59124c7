"""Shared data types: camera views, captures, meshes, point clouds, reconstructions and grasps.

These are the data contracts of ``docs/architecture.md``. Units are metres, radians, seconds and
kilograms; the world frame is the robot base frame with z up. Camera poses are ``T_world_cam``
in the OpenCV convention (x right, y down, z forward). Arrays are validated on construction and
a :class:`~torm.errors.CaptureError` names the offending field.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from torm.errors import CaptureError, GraspError
from torm.geometry import invert_T, is_rotation


def _check_image(name: str, arr: np.ndarray | None, hw: tuple[int, int] | None, ndim: int) -> None:
    if arr is None:
        return
    if not isinstance(arr, np.ndarray) or arr.ndim != ndim:
        raise CaptureError(f"{name} must be a numpy array with {ndim} dimensions, got {getattr(arr, 'shape', arr)}")
    if hw is not None and arr.shape[:2] != hw:
        raise CaptureError(f"{name} has size {arr.shape[:2]} (H, W) but the view is {hw}; resize or re-export it")


@dataclass(frozen=True, eq=False)
class CameraView:
    """One calibrated camera view.

    Attributes:
        K: (3, 3) float64 pinhole intrinsics in pixels.
        T_world_cam: (4, 4) float64 camera-to-world pose, OpenCV axes, metres.
        rgb: (H, W, 3) uint8 colour image, or None for mask-only views.
        depth: (H, W) float32 ideal metric z-depth in metres (first surface hit; 0 or NaN = none).
        sensor_depth: (H, W) float32 z-depth as a real depth camera reports it (sees through glass).
        mask: (H, W) int32 instance mask; 0 background, k > 0 = object k.
        name: free-form label (e.g. the file stem).
        reference_rgb: (H, W, 3) uint8 the same camera's view of the empty workspace (a reference pass flown before
            the objects were placed; ``reference`` mode of the learned segmenter), or None.
    """

    K: np.ndarray
    T_world_cam: np.ndarray
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    sensor_depth: np.ndarray | None = None
    mask: np.ndarray | None = None
    name: str = ""
    reference_rgb: np.ndarray | None = None

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        T = np.asarray(self.T_world_cam, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CaptureError(f"view {self.name!r}: K must be a finite (3, 3) matrix with positive focal lengths")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise CaptureError(f"view {self.name!r}: T_world_cam must be a finite (4, 4) matrix (NaN pose?)")
        if not is_rotation(T[:3, :3], tol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise CaptureError(f"view {self.name!r}: T_world_cam is not a rigid transform (rotation not orthonormal)")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_world_cam", T)
        if self.rgb is None and self.mask is None:
            raise CaptureError(f"view {self.name!r}: needs an rgb image or a mask to define its size")
        hw = self.rgb.shape[:2] if self.rgb is not None else self.mask.shape[:2]
        _check_image(f"view {self.name!r} rgb", self.rgb, hw, 3)
        if self.rgb is not None and (self.rgb.shape[2] != 3 or self.rgb.dtype != np.uint8):
            raise CaptureError(
                f"view {self.name!r}: rgb must be uint8 (H, W, 3), got {self.rgb.dtype} {self.rgb.shape}"
            )
        _check_image(f"view {self.name!r} reference_rgb", self.reference_rgb, hw, 3)
        ref = self.reference_rgb
        if ref is not None and (ref.shape[2] != 3 or ref.dtype != np.uint8):
            raise CaptureError(f"view {self.name!r}: reference_rgb must be uint8 (H, W, 3), got "
                               f"{self.reference_rgb.dtype} {self.reference_rgb.shape}")
        for nm in ("depth", "sensor_depth", "mask"):
            _check_image(f"view {self.name!r} {nm}", getattr(self, nm), hw, 2)
        if self.mask is not None and self.mask.dtype != np.int32:
            object.__setattr__(self, "mask", self.mask.astype(np.int32))
        for nm in ("depth", "sensor_depth"):
            d = getattr(self, nm)
            if d is not None and d.dtype != np.float32:
                object.__setattr__(self, nm, d.astype(np.float32))

    @property
    def height(self) -> int:
        return int((self.rgb if self.rgb is not None else self.mask).shape[0])

    @property
    def width(self) -> int:
        return int((self.rgb if self.rgb is not None else self.mask).shape[1])

    @property
    def T_cam_world(self) -> np.ndarray:
        """World-to-camera transform (4, 4), OpenCV axes."""
        return invert_T(self.T_world_cam)

    @property
    def silhouette(self) -> np.ndarray:
        """(H, W) bool union of all objects; raises CaptureError when the view has no mask."""
        if self.mask is None:
            raise CaptureError(f"view {self.name!r} has no mask; run a segmenter (torm segment) or provide masks")
        return self.mask > 0

    def project(self, points_world_nx3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) m to pixel coordinates (N, 2) (u right, v down) and depths (N,) m."""
        T = self.T_cam_world
        p = points_world_nx3 @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p[:, :2] / z[:, None]) * np.diag(self.K)[:2] + self.K[:2, 2]
        return uv, z

    def with_(self, **changes: Any) -> CameraView:
        """A copy with some fields replaced (validated again)."""
        return replace(self, **changes)


@dataclass(frozen=True, eq=False)
class Capture:
    """An ordered set of views of one scene plus its metadata.

    Attributes:
        views: the camera views; all share one image size.
        scenario: scenario name (e.g. ``"rw3"``) or a free label for recorded data.
        seed: the seed that produced the scene, when simulated.
        object_ids: instance ids used in the masks, one per object.
        object_names: object type names aligned with ``object_ids``.
        table_height: z of the table top in the world frame (m), when known.
        workspace_bounds: (2, 3) float64 [min, max] corners (m) of the box that holds the objects.
        metadata: anything else (renderer, timings, ...); must be JSON-serialisable to be saved.
    """

    views: tuple[CameraView, ...]
    scenario: str = ""
    seed: int | None = None
    object_ids: tuple[int, ...] = ()
    object_names: tuple[str, ...] = ()
    table_height: float | None = None
    workspace_bounds: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        views = tuple(self.views)
        object.__setattr__(self, "views", views)
        if not views:
            raise CaptureError("a capture needs at least one view")
        hw = (views[0].height, views[0].width)
        for i, v in enumerate(views):
            if (v.height, v.width) != hw:
                raise CaptureError(f"view {i} ({v.name!r}) is {v.height}x{v.width} but view 0 is {hw[0]}x{hw[1]}")
        object.__setattr__(self, "object_ids", tuple(int(i) for i in self.object_ids))
        object.__setattr__(self, "object_names", tuple(str(n) for n in self.object_names))
        if self.object_names and len(self.object_names) != len(self.object_ids):
            raise CaptureError(
                f"object_names has {len(self.object_names)} entries but object_ids has {len(self.object_ids)}"
            )
        if self.workspace_bounds is not None:
            b = np.asarray(self.workspace_bounds, dtype=np.float64)
            if b.shape != (2, 3) or not np.all(b[1] > b[0]):
                raise CaptureError("workspace_bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min")
            object.__setattr__(self, "workspace_bounds", b)

    def __len__(self) -> int:
        return len(self.views)

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return self.views[0].height, self.views[0].width

    @property
    def has_masks(self) -> bool:
        return all(v.mask is not None for v in self.views)

    def Ks(self) -> np.ndarray:
        """(V, 3, 3) intrinsics."""
        return np.stack([v.K for v in self.views])

    def poses(self) -> np.ndarray:
        """(V, 4, 4) camera-to-world poses, OpenCV axes."""
        return np.stack([v.T_world_cam for v in self.views])

    def masks(self) -> np.ndarray:
        """(V, H, W) int32 instance masks; raises CaptureError naming the first view without one."""
        for i, v in enumerate(self.views):
            if v.mask is None:
                raise CaptureError(
                    f"view {i} ({v.name!r}) has no mask; segment the capture first (torm segment) or use GT masks"
                )
        return np.stack([v.mask for v in self.views])

    def with_masks(self, masks_vxhxw: Sequence[np.ndarray] | np.ndarray) -> Capture:
        """A copy whose views carry the given (V, H, W) instance masks."""
        if len(masks_vxhxw) != len(self.views):
            raise CaptureError(f"got {len(masks_vxhxw)} masks for {len(self.views)} views; give one mask per view")
        views = tuple(v.with_(mask=np.asarray(m, dtype=np.int32)) for v, m in zip(self.views, masks_vxhxw, strict=True))
        return replace(self, views=views)

    def subset(self, indices: Sequence[int]) -> Capture:
        """A copy with only the views at ``indices`` (in that order)."""
        return replace(self, views=tuple(self.views[i] for i in indices))


@dataclass(frozen=True, eq=False)
class TriMesh:
    """A triangle mesh: vertices (V, 3) float64 in metres (world frame), faces (F, 3) int64, outward CCW."""

    verts_vx3: np.ndarray
    faces_fx3: np.ndarray

    def __post_init__(self) -> None:
        v = np.asarray(self.verts_vx3, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(self.faces_fx3, dtype=np.int64).reshape(-1, 3)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError("TriMesh: face indices out of range of the vertex array")
        object.__setattr__(self, "verts_vx3", v)
        object.__setattr__(self, "faces_fx3", f)

    @property
    def is_empty(self) -> bool:
        return len(self.faces_fx3) == 0

    def to_trimesh(self):  # -> trimesh.Trimesh (import kept lazy)
        import trimesh

        return trimesh.Trimesh(self.verts_vx3, self.faces_fx3, process=False)


@dataclass(frozen=True, eq=False)
class ObjectPointCloud:
    """Surface samples of one reconstructed object: points (N, 3) m and unit outward normals (N, 3), world frame."""

    points_nx3: np.ndarray
    normals_nx3: np.ndarray
    object_index: int

    def __post_init__(self) -> None:
        p, n = self.points_nx3, self.normals_nx3
        if p.shape != n.shape or p.ndim != 2 or p.shape[1] != 3:
            raise ValueError("ObjectPointCloud: points and normals must both be (N, 3)")


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """A scene reconstruction: the whole watertight mesh, its split into objects, and per-object samples.

    ``object_meshes[k]`` and ``point_clouds[k]`` describe the same object; every point cloud has the
    same number of points. ``history`` holds per-iteration curves (e.g. ``loss``, ``iou``) and
    ``timings`` the wall time in seconds of each stage.
    """

    scene_mesh: TriMesh
    object_meshes: tuple[TriMesh, ...]
    point_clouds: tuple[ObjectPointCloud, ...]
    timings: dict[str, float] = field(default_factory=dict)
    history: dict[str, list[float]] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_objects(self) -> int:
        return len(self.object_meshes)


@dataclass(frozen=True, eq=False)
class Grasp:
    """A parallel-jaw grasp.

    ``T_world_grasp`` (4, 4): origin at the grasp centre (midway between the pads), x = approach
    direction (pointing into the object), y = closing axis, z = finger height axis (GraspNet frame).
    ``width`` is the opening in metres, ``height``/``depth`` follow GraspNet (m).
    """

    T_world_grasp: np.ndarray
    width: float
    score: float
    object_id: int
    height: float = 0.02
    depth: float = 0.02

    def __post_init__(self) -> None:
        T = np.asarray(self.T_world_grasp, dtype=np.float64)
        if T.shape != (4, 4) or not is_rotation(T[:3, :3], tol=1e-4):
            raise GraspError("Grasp.T_world_grasp must be a rigid (4, 4) transform")
        if not np.isfinite(self.width) or self.width < 0:
            raise GraspError(f"Grasp.width must be a finite non-negative number of metres, got {self.width}")
        object.__setattr__(self, "T_world_grasp", T)

    def to_graspnet(self) -> np.ndarray:
        """GraspNet's 17-float row ``[score, width, height, depth, R (9, row-major), t (3), object_id]``."""
        T = self.T_world_grasp
        return np.concatenate(
            [[self.score, self.width, self.height, self.depth], T[:3, :3].reshape(-1), T[:3, 3], [self.object_id]]
        ).astype(np.float64)

    @classmethod
    def from_graspnet(cls, row: np.ndarray) -> Grasp:
        """Inverse of :meth:`to_graspnet`."""
        row = np.asarray(row, dtype=np.float64)
        if row.shape != (17,):
            raise GraspError(f"a GraspNet row has 17 floats, got shape {row.shape}")
        T = np.eye(4)
        T[:3, :3] = row[4:13].reshape(3, 3)
        T[:3, 3] = row[13:16]
        return cls(T, width=float(row[1]), score=float(row[0]), object_id=int(row[16]),
                   height=float(row[2]), depth=float(row[3]))
