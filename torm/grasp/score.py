"""Grasp quality terms, their weighted sum, and non-maximum suppression in pose space.

Every term is in [0, 1] (1 = best):

* antipodal: how well the contact normals align with the closing axis (from the sampler);
* approach: ``(1 + x . (-z_world)) / 2``: 1 for a straight top-down approach, 0.5 for horizontal;
* centre: ``1 - min(1, |t - c| / r)``: grasp centre ``t`` near the object's centre of mass ``c``, ``r`` the
  object's radius (largest point distance from ``c``);
* clearance: ``min(1, d / clearance_scale)`` with ``d`` the distance (m) from the two fingers (level with the
  grasp centre) to the nearest point of any *other* object (1 when the object is alone);
* depth: ``min(1, depth / default_depth)``: pads centred on the contacts (or deeper) beat fingertip grasps.

The score is the weight-normalised sum, so it is in [0, 1] too.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from torm.grasp.gripper import GripperGeometry


def approach_quality(R_cx3x3: np.ndarray) -> np.ndarray:
    """(C,) ``(1 + x . (-z)) / 2`` for approach axes x = R[:, :, 0]."""
    return 0.5 * (1.0 - R_cx3x3[:, 2, 0])


def centre_quality(t_cx3: np.ndarray, com_3: np.ndarray, radius: float) -> np.ndarray:
    """(C,) ``1 - min(1, |t - com| / radius)`` (m / m)."""
    d = np.linalg.norm(t_cx3 - com_3[None], axis=1)
    return 1.0 - np.clip(d / max(radius, 1e-9), 0.0, 1.0)


def depth_quality(depth_c: np.ndarray, gripper: GripperGeometry) -> np.ndarray:
    """(C,) ``min(1, depth / gripper.default_depth)`` (m / m)."""
    return np.clip(depth_c / max(gripper.default_depth, 1e-9), 0.0, 1.0)


def finger_centres(R_cx3x3: np.ndarray, t_cx3: np.ndarray, width_c: np.ndarray, gripper: GripperGeometry,
                   ) -> np.ndarray:
    """(C, 2, 3) world points (m) at the two fingers' centre lines level with the grasp centre:
    ``t -+ (width / 2 + finger_thickness / 2) y``."""
    off = (width_c / 2 + gripper.finger_thickness / 2)[:, None] * R_cx3x3[:, :, 1]
    return np.stack([t_cx3 - off, t_cx3 + off], axis=1)


def clearance_quality(R_cx3x3: np.ndarray, t_cx3: np.ndarray, width_c: np.ndarray, gripper: GripperGeometry,
                      obstacle_tree: cKDTree | None, clearance_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(C,) quality ``min(1, d / clearance_scale)`` and (C,) distance d (m) from the two finger points
    (:func:`finger_centres`) to the nearest obstacle point (inf when farther than ``clearance_scale``).

    It depends on the centre, closing axis and width only, so it can be evaluated once per contact pair.
    """
    C = len(R_cx3x3)
    if obstacle_tree is None or obstacle_tree.n == 0 or C == 0:
        return np.ones(C), np.full(C, np.inf)
    fc = finger_centres(R_cx3x3, t_cx3, width_c, gripper).reshape(-1, 3)
    d, _ = obstacle_tree.query(fc, k=1, distance_upper_bound=clearance_scale)  # inf beyond the scale
    d = d.reshape(C, 2).min(axis=1)
    return np.clip(d / clearance_scale, 0.0, 1.0), d


def rotation_distance(R_a_3x3: np.ndarray, R_bx3x3: np.ndarray, symmetric: bool = True) -> np.ndarray:
    """(B,) rotation angle (rad) between ``R_a`` and each ``R_b``.

    With ``symmetric`` the parallel-jaw symmetry (a half turn about the approach axis x, which swaps the
    fingers) counts as the same grasp: the smaller of the two angles is returned.
    """
    dots = np.einsum("ik,bik->bk", R_a_3x3, R_bx3x3)  # column-wise dot products x.x', y.y', z.z'
    tr = dots.sum(axis=1)
    if symmetric:
        tr = np.maximum(tr, dots[:, 0] - dots[:, 1] - dots[:, 2])
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


class GreedyNMS:
    """Greedy non-maximum suppression in pose space, fed candidates best first.

    A candidate is suppressed when an accepted grasp is closer than ``translation`` (m) *and*
    ``angle`` (rad) (finger-swap symmetric).
    """

    def __init__(self, translation: float, angle: float, limit: int) -> None:
        self.translation = translation
        self.angle = angle
        self.limit = limit
        self.R: list[np.ndarray] = []
        self.t: list[np.ndarray] = []
        self.accepted: list[int] = []

    @property
    def full(self) -> bool:
        return len(self.accepted) >= self.limit

    def offer(self, index: int, R_3x3: np.ndarray, t_3: np.ndarray) -> bool:
        """Accept ``index`` unless it duplicates an accepted grasp; returns True when accepted."""
        if self.full:
            return False
        if self.R:
            close_t = np.linalg.norm(np.asarray(self.t) - t_3[None], axis=1) < self.translation
            if np.any(close_t):
                ang = rotation_distance(R_3x3, np.asarray(self.R)[close_t])
                if np.any(ang < self.angle):
                    return False
        self.R.append(R_3x3)
        self.t.append(t_3)
        self.accepted.append(index)
        return True
