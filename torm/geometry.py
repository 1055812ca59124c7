"""Small rigid-transform helpers shared by every package.

Conventions: transforms are 4x4 float64 homogeneous matrices named ``T_a_b`` (maps b-frame points
into frame a). Camera frames follow OpenCV (x right, y down, z forward) unless named ``gl``.
Quaternions are wxyz (MuJoCo, mink).
"""

from __future__ import annotations

import numpy as np

#: Flips the y and z camera axes: OpenCV camera frame <-> OpenGL/MuJoCo camera frame (involution).
FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a (4, 4) transform from a (3, 3) rotation and a (3,) translation in metres."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform (or a stack (..., 4, 4))."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points_nx3: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points."""
    return points_nx3 @ T[:3, :3].T + T[:3, 3]


def cv_to_gl(T_world_cam_cv: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world pose -> OpenGL camera-to-world pose (NeRF ``transform_matrix``)."""
    return T_world_cam_cv @ FLIP_YZ


def gl_to_cv(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world pose -> OpenCV camera-to-world pose."""
    return T_world_cam_gl @ FLIP_YZ


_Z_UP = np.array([0.0, 0.0, 1.0])


def look_at_cv(eye: np.ndarray, target: np.ndarray, up: np.ndarray = _Z_UP) -> np.ndarray:
    """OpenCV camera-to-world pose at ``eye`` (m) looking at ``target`` (m), image-up close to ``up``.

    Raises ``ValueError`` when eye == target. When the view direction is parallel to ``up`` the
    world x axis is used as the up hint instead.
    """
    eye = np.asarray(eye, dtype=float)
    target = np.asarray(target, dtype=float)
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError("look_at_cv: eye and target coincide; give a camera position away from the target")
    z /= n
    up = np.asarray(up, dtype=float)
    if abs(np.dot(z, up / np.linalg.norm(up))) > 0.999:
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)  # right-handed OpenCV frame: x = z x up, y = z x x (points down)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), eye)


def quat_wxyz_to_R(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> (3, 3) rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> unit quaternion (w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The proper rotations (det +1) nearest in the Frobenius norm to ``M`` (..., 3, 3) (SVD; Higham 1989)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    U = U.copy()
    U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
    return U @ Vt


def is_rotation(R: np.ndarray, tol: float = 1e-5) -> bool:
    """True when R is a proper rotation (orthonormal, det +1) within ``tol``."""
    return bool(
        R.shape == (3, 3)
        and np.all(np.isfinite(R))
        and np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
    )


def backproject_depth(depth_hxw: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points (m, OpenCV axes) of z-depth ``depth_hxw`` (m); pixel centres at integer + 0.5."""
    H, W = depth_hxw.shape
    v, u = np.mgrid[0:H, 0:W]
    z = np.asarray(depth_hxw, dtype=np.float64)
    x = (u + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (v + 0.5 - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1)
