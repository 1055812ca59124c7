"""Collision checks of gripper boxes against the table plane and object points, vectorised over candidates.

All boxes are axis-aligned in the grasp frame (:meth:`GripperGeometry.box_params`), so a box in the world
is ``(R, t, centre_grasp, half_extents)`` with ``R`` the grasp rotation. Object geometry is represented by
its surface points (the reconstruction's point clouds, a few mm apart): a box collides when it contains
an object point. The target object itself is tested too: its points between the pads lie outside every
box (the fingers' inner faces are at ``y = +-width / 2``), so only points that a finger, the palm or the
approach sweep would pass through count, i.e. fingers penetrating the target.
"""

from __future__ import annotations

import numba
import numpy as np

from torm.grasp.gripper import COLLISION_BOXES_NO_SWEEP, COLLISION_BOXES_WITH_SWEEP, GripperGeometry


def box_indices(check_approach_sweep: bool) -> tuple[int, ...]:
    """Box indices whose union is the checked volume (sweep boxes contain the fingers and the palm)."""
    return COLLISION_BOXES_WITH_SWEEP if check_approach_sweep else COLLISION_BOXES_NO_SWEEP


def min_box_z(R_cx3x3: np.ndarray, t_cx3: np.ndarray, centres_cxbx3: np.ndarray, halves_cxbx3: np.ndarray,
              ) -> np.ndarray:
    """Lowest world z (m) of each box: (C, B). Exact for oriented boxes: t_z + r_z . c - sum_k |r_zk| h_k."""
    rz = R_cx3x3[:, 2, :]  # world z row of R: z-components of the grasp axes
    lowest = np.einsum("ck,cbk->cb", rz, centres_cxbx3) - np.einsum("ck,cbk->cb", np.abs(rz), halves_cxbx3)
    return t_cx3[:, 2:3] + lowest


def table_collision_free(R_cx3x3: np.ndarray, t_cx3: np.ndarray, width_c: np.ndarray, depth_c: np.ndarray,
                         gripper: GripperGeometry, table_height: float, clearance: float,
                         check_approach_sweep: bool = True) -> np.ndarray:
    """(C,) True where every checked box lies above ``table_height + clearance`` (m)."""
    centres, halves = gripper.box_params(width_c, depth_c)
    b = list(box_indices(check_approach_sweep))
    return np.all(min_box_z(R_cx3x3, t_cx3, centres[:, b], halves[:, b]) >= table_height + clearance, axis=1)


@numba.njit(cache=True, nogil=True)
def _count_points_in_boxes(P, R, t, lo, hi, lo_u, hi_u, stop_at_first):  # pragma: no cover - compiled
    C = R.shape[0]
    n = P.shape[0]
    B = lo.shape[1]
    counts = np.zeros(C, dtype=np.int64)
    for c in range(C):
        cnt = 0
        for i in range(n):
            dx = P[i, 0] - t[c, 0]
            dy = P[i, 1] - t[c, 1]
            dz = P[i, 2] - t[c, 2]
            gz = R[c, 0, 2] * dx + R[c, 1, 2] * dy + R[c, 2, 2] * dz
            if gz < lo_u[c, 2] or gz > hi_u[c, 2]:
                continue
            gx = R[c, 0, 0] * dx + R[c, 1, 0] * dy + R[c, 2, 0] * dz
            if gx < lo_u[c, 0] or gx > hi_u[c, 0]:
                continue
            gy = R[c, 0, 1] * dx + R[c, 1, 1] * dy + R[c, 2, 1] * dz
            if gy < lo_u[c, 1] or gy > hi_u[c, 1]:
                continue
            for b in range(B):
                if (lo[c, b, 0] <= gx <= hi[c, b, 0] and lo[c, b, 1] <= gy <= hi[c, b, 1]
                        and lo[c, b, 2] <= gz <= hi[c, b, 2]):
                    cnt += 1
                    break
            if stop_at_first and cnt > 0:
                break
        counts[c] = cnt
    return counts


def points_in_boxes(R_cx3x3: np.ndarray, t_cx3: np.ndarray, centres_cxbx3: np.ndarray, halves_cxbx3: np.ndarray,
                    points_px3: np.ndarray, margin: float = 0.0, stop_at_first: bool = False) -> np.ndarray:
    """(C,) number of points inside any of each candidate's boxes (boxes inflated by ``margin`` m).

    Each point is moved into the grasp frame, ``p_g = R^T (p - t)``, rejected early against the union
    bounding box of the candidate's boxes and then tested against every box (a compiled numba loop).
    With ``stop_at_first`` a count stops at 1 (enough for a collision test).
    """
    C = len(R_cx3x3)
    if C == 0 or len(points_px3) == 0:
        return np.zeros(C, dtype=np.int64)
    lo = np.ascontiguousarray(centres_cxbx3 - halves_cxbx3 - margin, dtype=np.float64)
    hi = np.ascontiguousarray(centres_cxbx3 + halves_cxbx3 + margin, dtype=np.float64)
    return _count_points_in_boxes(
        np.ascontiguousarray(points_px3, dtype=np.float64), np.ascontiguousarray(R_cx3x3, dtype=np.float64),
        np.ascontiguousarray(t_cx3, dtype=np.float64), lo, hi, np.ascontiguousarray(lo.min(axis=1)),
        np.ascontiguousarray(hi.max(axis=1)), bool(stop_at_first))


def points_collision_free(R_cx3x3: np.ndarray, t_cx3: np.ndarray, width_c: np.ndarray, depth_c: np.ndarray,
                          gripper: GripperGeometry, points_px3: np.ndarray, margin: float = 0.0,
                          check_approach_sweep: bool = True) -> np.ndarray:
    """(C,) True where no point of ``points_px3`` lies inside the gripper (and its sweep) at the grasp opening."""
    centres, halves = gripper.box_params(width_c, depth_c)
    b = list(box_indices(check_approach_sweep))
    return points_in_boxes(R_cx3x3, t_cx3, centres[:, b], halves[:, b], points_px3, margin, stop_at_first=True) == 0
