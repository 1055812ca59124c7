"""Closed-form AX = XB hand-eye solvers (numpy), the methods of OpenCV's ``calibrateHandEye``.

:func:`torm.hardware.handeye.calibrate_hand_eye` uses ``cv2.calibrateHandEye``; these numpy versions of its five
classical methods are the fallback for OpenCV builds whose Python bindings lack it (some 5.0 builds exported only
the ``CALIB_HAND_EYE_*`` constants) and a cross-check in the tests:

- ``TSAI``: Tsai & Lenz 1989 (modified Rodrigues vectors, linear least squares);
- ``PARK``: Park & Martin 1994 (rotation logs, ``R = (M^T M)^-1/2 M^T``);
- ``HORAUD``: Horaud & Dornaika 1995 (unit quaternion, smallest eigenvector);
- ``ANDREFF``: Andreff et al. 1999 (Kronecker-product null space, then orthonormalised);
- ``DANIILIDIS``: Daniilidis 1999 (dual quaternions, SVD; rotation and translation together).

All but Daniilidis then solve the translation by linear least squares ``(R_A - I) t = R t_B - t_A``.
Motions: for poses i < j, ``A = inv(T_base_flange_j) @ T_base_flange_i`` and
``B = T_cam_target_j @ inv(T_cam_target_i)`` satisfy ``A X = X B`` with ``X = T_flange_cam``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from torm.errors import ConfigError, UnknownNameError
from torm.geometry import nearest_rotation


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def relative_motions(T_base_flange: Sequence[np.ndarray], T_cam_target: Sequence[np.ndarray],
                     min_angle_deg: float = 1.0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Motion pairs (A, B) over all i < j whose flange rotation exceeds ``min_angle_deg`` (deg)."""
    As, Bs = [], []
    n = len(T_base_flange)
    for i in range(n):
        for j in range(i + 1, n):
            A = _inv(np.asarray(T_base_flange[j])) @ np.asarray(T_base_flange[i])
            B = np.asarray(T_cam_target[j]) @ _inv(np.asarray(T_cam_target[i]))
            if np.degrees(np.linalg.norm(Rotation.from_matrix(A[:3, :3]).as_rotvec())) >= min_angle_deg:
                As.append(A)
                Bs.append(B)
    if len(As) < 2:
        raise ConfigError("hand-eye: fewer than 2 robot motions with a rotation >= 1 deg; vary the wrist orientation "
                          "between the images (rotations about at least two different axes)")
    return As, Bs


def _translation(As: list[np.ndarray], Bs: list[np.ndarray], R: np.ndarray) -> np.ndarray:
    C = np.concatenate([A[:3, :3] - np.eye(3) for A in As])
    d = np.concatenate([R @ B[:3, 3] - A[:3, 3] for A, B in zip(As, Bs, strict=True)])
    return np.linalg.lstsq(C, d, rcond=None)[0]


def _rot_tsai(As, Bs) -> np.ndarray:
    def mrp(R):  # modified Rodrigues: 2 sin(theta / 2) * axis
        rv = Rotation.from_matrix(R).as_rotvec()
        th = np.linalg.norm(rv)
        return np.zeros(3) if th < 1e-12 else 2 * np.sin(th / 2) * rv / th

    C, d = [], []
    for A, B in zip(As, Bs, strict=True):
        pg, pc = mrp(A[:3, :3]), mrp(B[:3, :3])
        C.append(_skew(pg + pc))
        d.append(pc - pg)
    p = np.linalg.lstsq(np.concatenate(C), np.concatenate(d), rcond=None)[0]
    px = 2 * p / np.sqrt(1 + p @ p)
    n2 = px @ px
    return (1 - n2 / 2) * np.eye(3) + 0.5 * (np.outer(px, px) + np.sqrt(4 - n2) * _skew(px))


def _rot_park(As, Bs) -> np.ndarray:
    M = np.zeros((3, 3))
    for A, B in zip(As, Bs, strict=True):
        alpha = Rotation.from_matrix(A[:3, :3]).as_rotvec()
        beta = Rotation.from_matrix(B[:3, :3]).as_rotvec()
        M += np.outer(beta, alpha)
    w, V = np.linalg.eigh(M.T @ M)
    return nearest_rotation(V @ np.diag(1 / np.sqrt(np.maximum(w, 1e-18))) @ V.T @ M.T)


def _quat(R: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _qmat_left(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _qmat_right(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def _rot_horaud(As, Bs) -> np.ndarray:
    S = np.zeros((4, 4))
    for A, B in zip(As, Bs, strict=True):
        D = _qmat_left(_quat(A[:3, :3])) - _qmat_right(_quat(B[:3, :3]))  # q_A * q_X - q_X * q_B
        S += D.T @ D
    q = np.linalg.eigh(S)[1][:, 0]
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def _rot_andreff(As, Bs) -> np.ndarray:
    # R_A R_X - R_X R_B = 0  ->  (I kron R_A - R_B^T kron I) vec(R_X) = 0 (column-major vec)
    M = np.concatenate([np.kron(np.eye(3), A[:3, :3]) - np.kron(B[:3, :3].T, np.eye(3)) for A, B in zip(As, Bs,
                                                                                                       strict=True)])
    v = np.linalg.svd(M)[2][-1]
    R = v.reshape(3, 3, order="F")
    R = R * np.sign(np.linalg.det(R)) / abs(np.linalg.det(R)) ** (1 / 3)
    return nearest_rotation(R)


def _dual_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = _quat(T[:3, :3])
    if q[0] < 0:
        q = -q
    t = np.concatenate([[0.0], T[:3, 3]])
    qd = 0.5 * _qmat_left(t) @ q
    return q, qd


def _daniilidis(As, Bs) -> np.ndarray:
    rows = []
    for A, B in zip(As, Bs, strict=True):
        a, ad = _dual_quat(A)
        b, bd = _dual_quat(B)
        S = np.zeros((6, 8))
        S[:3, 0] = a[1:] - b[1:]
        S[:3, 1:4] = _skew(a[1:] + b[1:])
        S[3:, 0] = ad[1:] - bd[1:]
        S[3:, 1:4] = _skew(ad[1:] + bd[1:])
        S[3:, 4] = a[1:] - b[1:]
        S[3:, 5:8] = _skew(a[1:] + b[1:])
        rows.append(S)
    V = np.linalg.svd(np.concatenate(rows))[2]
    v7, v8 = V[-2], V[-1]
    u1, w1, u2, w2 = v7[:4], v7[4:], v8[:4], v8[4:]
    # s^2 (u1.w1) + s (u1.w2 + u2.w1) + (u2.w2) = 0 with s = l1 / l2
    a, b, c = u1 @ w1, u1 @ w2 + u2 @ w1, u2 @ w2
    disc = max(b * b - 4 * a * c, 0.0)
    if abs(a) < 1e-15:
        roots = [-c / b] if abs(b) > 1e-15 else [0.0]
    else:
        roots = [(-b + np.sqrt(disc)) / (2 * a), (-b - np.sqrt(disc)) / (2 * a)]
    best = max(roots, key=lambda s: s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2)
    val = best * best * (u1 @ u1) + 2 * best * (u1 @ u2) + u2 @ u2
    l2 = 1 / np.sqrt(val)
    l1 = best * l2
    q = l1 * u1 + l2 * u2
    qd = l1 * w1 + l2 * w2
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    q_conj = q * np.array([1, -1, -1, -1])
    t = 2 * (_qmat_left(qd) @ q_conj)[1:]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


_ROTATION = {"TSAI": _rot_tsai, "PARK": _rot_park, "HORAUD": _rot_horaud, "ANDREFF": _rot_andreff}
METHOD_NAMES = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")


def solve_ax_xb(T_base_flange: Sequence[np.ndarray], T_cam_target: Sequence[np.ndarray],
                method: str = "PARK") -> np.ndarray:
    """X = T_flange_cam (4, 4) from poses T_base_flange (4, 4) and T_cam_target (4, 4) with ``method``."""
    key = method.upper()
    if key not in METHOD_NAMES:
        raise UnknownNameError("hand-eye method", method, METHOD_NAMES)
    As, Bs = relative_motions(T_base_flange, T_cam_target)
    if key == "DANIILIDIS":
        return _daniilidis(As, Bs)
    R = _ROTATION[key](As, Bs)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = _translation(As, Bs, R)
    return T
