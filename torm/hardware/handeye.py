"""Eye-in-hand calibration of the wrist camera: T_flange_cam from robot poses and ChArUco board views.

For image i the robot reports ``T_base_flange_i`` and the board pose in the camera is
``T_cam_target_i`` (ChArUco detection + solvePnP). With a static board,
``T_base_target = T_base_flange_i @ T_flange_cam @ T_cam_target_i`` for every i. This is OpenCV's
``calibrateHandEye`` convention ("gripper2base" = T_base_flange, "target2cam" = T_cam_target,
"cam2gripper" = ``T_flange_cam``), solved with ``cv2.calibrateHandEye`` (present again in OpenCV 5.1's
Python bindings); the numpy implementations of the same five methods in :mod:`torm.hardware.handeye_solvers`
are the fallback for OpenCV builds without it and a cross-check in the tests. Residuals are the spread of the per-image
``T_base_target`` around their mean: translation (mm) and rotation (deg). Need >= 3 poses with
rotations about different axes.

File formats:

- hand-eye YAML (written by :func:`save_hand_eye`, read by :func:`load_hand_eye`):
  ``T_flange_cam: 4x4 list`` (metres, OpenCV camera axes) plus ``method``, ``n_images`` and ``residuals``;
- intrinsics YAML/JSON: ``K`` (3x3) or ``fx, fy, cx, cy``; optional ``dist`` ([k1, k2, p1, p2, k3]);
- poses YAML/JSON: ``poses: [{image: name.png, q: [...rad]} | {image: name.png, T_base_flange: 4x4}]``
  (``q`` needs the robot config for the flange FK).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from torm.config import parse_yaml
from torm.errors import CaptureError, ConfigError, UnknownNameError
from torm.hardware.handeye_solvers import METHOD_NAMES, solve_ax_xb

log = logging.getLogger(__name__)

#: Selectable AX = XB methods (the names of OpenCV's CALIB_HAND_EYE_* flags).
METHODS = METHOD_NAMES


def calibrate_hand_eye(T_base_flange_list: Sequence[np.ndarray], T_cam_target_list: Sequence[np.ndarray],
                       method: str = "PARK") -> np.ndarray:
    """T_flange_cam (4, 4) from paired robot poses T_base_flange (4, 4) and board poses T_cam_target (4, 4)."""
    if len(T_base_flange_list) != len(T_cam_target_list):
        raise ConfigError(f"hand-eye: {len(T_base_flange_list)} robot poses but {len(T_cam_target_list)} board poses")
    if len(T_base_flange_list) < 3:
        raise ConfigError("hand-eye calibration needs at least 3 pose pairs (better 10-20 with varied rotations)")
    T = solve_hand_eye_cv2(T_base_flange_list, T_cam_target_list, method)
    if T is None:  # an OpenCV build without calibrateHandEye
        T = solve_ax_xb(T_base_flange_list, T_cam_target_list, method)
    if not np.all(np.isfinite(T)):
        raise ConfigError("hand-eye calibration returned NaN; the poses are degenerate (vary the wrist rotation)")
    return T


def solve_hand_eye_cv2(T_base_flange_list: Sequence[np.ndarray], T_cam_target_list: Sequence[np.ndarray],
                       method: str = "PARK") -> np.ndarray | None:
    """T_flange_cam (4, 4) from ``cv2.calibrateHandEye`` with ``CALIB_HAND_EYE_<method>``; None when this OpenCV
    has no ``calibrateHandEye``. Inputs as :func:`calibrate_hand_eye` (metres)."""
    key = method.upper()
    if key not in METHODS:
        from torm.errors import UnknownNameError

        raise UnknownNameError("hand-eye method", method, METHODS)
    if not hasattr(cv2, "calibrateHandEye"):
        return None
    R_g2b = [np.asarray(T, float)[:3, :3] for T in T_base_flange_list]
    t_g2b = [np.asarray(T, float)[:3, 3].reshape(3, 1) for T in T_base_flange_list]
    R_t2c = [np.asarray(T, float)[:3, :3] for T in T_cam_target_list]
    t_t2c = [np.asarray(T, float)[:3, 3].reshape(3, 1) for T in T_cam_target_list]
    R, t = cv2.calibrateHandEye(R_g2b, t_g2b, R_t2c, t_t2c, method=getattr(cv2, f"CALIB_HAND_EYE_{key}"))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(t).reshape(3)
    return T


def _mean_rotation(Rs: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(Rs.sum(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


@dataclass(frozen=True)
class HandEyeResiduals:
    """Spread of T_base_target over the images: per-image translation (mm) and rotation (deg) from the mean."""

    translation_mm: np.ndarray
    rotation_deg: np.ndarray
    T_base_target: np.ndarray

    def summary(self) -> dict[str, float]:
        return {"translation_mm_mean": float(np.mean(self.translation_mm)),
                "translation_mm_max": float(np.max(self.translation_mm)),
                "rotation_deg_mean": float(np.mean(self.rotation_deg)),
                "rotation_deg_max": float(np.max(self.rotation_deg))}


def hand_eye_residuals(T_flange_cam: np.ndarray, T_base_flange_list: Sequence[np.ndarray],
                       T_cam_target_list: Sequence[np.ndarray]) -> HandEyeResiduals:
    """Consistency of the static board's pose T_base_target across images under ``T_flange_cam``."""
    Ts = np.stack([np.asarray(A) @ T_flange_cam @ np.asarray(B)
                   for A, B in zip(T_base_flange_list, T_cam_target_list, strict=True)])
    t_mean = Ts[:, :3, 3].mean(axis=0)
    R_mean = _mean_rotation(Ts[:, :3, :3])
    dt = np.linalg.norm(Ts[:, :3, 3] - t_mean, axis=1) * 1000.0
    cos = (np.einsum("nij,ij->n", Ts[:, :3, :3], R_mean) - 1.0) / 2.0
    dr = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    T_mean = np.eye(4)
    T_mean[:3, :3], T_mean[:3, 3] = R_mean, t_mean
    return HandEyeResiduals(dt, dr, T_mean)


# -- ChArUco --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board: squares (columns x rows), square and marker side (m), ArUco dictionary name."""

    squares_x: int = 7
    squares_y: int = 5
    square: float = 0.03
    marker: float = 0.022
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.squares_x < 2 or self.squares_y < 2:
            raise ConfigError("the ChArUco board needs at least 2x2 squares")
        if not 0 < self.marker < self.square:
            raise ConfigError(f"marker side {self.marker} m must be positive and smaller than the square "
                              f"{self.square} m")
        if not hasattr(cv2.aruco, self.dictionary):
            raise UnknownNameError("ArUco dictionary", self.dictionary,
                                   [n for n in dir(cv2.aruco) if n.startswith("DICT_")])

    @classmethod
    def parse(cls, board: str, square: float, marker: float, dictionary: str = "DICT_5X5_100") -> CharucoSpec:
        """From ``"7x5"`` (squares x by y)."""
        try:
            sx, sy = (int(v) for v in board.lower().split("x"))
        except ValueError as exc:
            raise ConfigError(f"--board must look like 7x5 (squares across x down), got {board!r}") from exc
        return cls(sx, sy, square, marker, dictionary)

    def board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square, self.marker, d)


def board_pose(image: np.ndarray, K: np.ndarray, dist: np.ndarray | None, spec: CharucoSpec,
               min_corners: int = 6) -> np.ndarray | None:
    """T_cam_target (4, 4) of the ChArUco board in ``image`` (BGR/gray uint8), or None when too few corners."""
    board = spec.board()
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < min_corners:
        return None
    obj, img = board.matchImagePoints(corners, ids)
    if obj is None or len(obj) < min_corners:
        return None
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)
    ok, rvec, tvec = cv2.solvePnP(obj.reshape(-1, 3), img.reshape(-1, 2), np.asarray(K, float), dist,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    return T


# -- files ----------------------------------------------------------------------------------------------
def _read_mapping(path: str | Path) -> dict[str, Any]:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p} does not exist")
    text = p.read_text()
    data = json.loads(text) if p.suffix == ".json" else parse_yaml(text)
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping at the top level")
    return data


def load_intrinsics(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), dist (5,)) from a YAML/JSON with ``K`` or ``fx, fy, cx, cy`` (and optional ``dist``)."""
    d = _read_mapping(path)
    if "K" in d:
        K = np.asarray(d["K"], float)
    elif all(k in d for k in ("fx", "fy", "cx", "cy")):
        K = np.array([[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1]], float)
    else:
        raise ConfigError(f"{path}: intrinsics need K (3x3) or fx, fy, cx, cy")
    if K.shape != (3, 3):
        raise ConfigError(f"{path}: K must be 3x3")
    dist = np.asarray(d.get("dist", [0, 0, 0, 0, 0]), float).reshape(-1)
    return K, dist


def load_poses(path: str | Path, flange_fk=None) -> list[tuple[str, np.ndarray]]:
    """[(image name, T_base_flange (4, 4))] from a poses file; entries with ``q`` need ``flange_fk(q) -> (4, 4)``."""
    d = _read_mapping(path)
    entries = d.get("poses")
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}: expected 'poses: [{{image: ..., q: [...]}} or {{image: ..., T_base_flange: ...}}]'")
    out = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or "image" not in e:
            raise ConfigError(f"{path}: poses[{i}] needs an 'image' name")
        if "T_base_flange" in e:
            T = np.asarray(e["T_base_flange"], float)
            if T.shape != (4, 4):
                raise ConfigError(f"{path}: poses[{i}].T_base_flange must be 4x4")
        elif "q" in e:
            if flange_fk is None:
                raise ConfigError(f"{path}: poses[{i}] gives joint values; pass --robot-config for the flange FK")
            T = np.asarray(flange_fk(np.asarray(e["q"], float)), float)
        else:
            raise ConfigError(f"{path}: poses[{i}] needs 'q' (rad) or 'T_base_flange' (4x4, m)")
        out.append((str(e["image"]), T))
    return out


def save_hand_eye(path: str | Path, T_flange_cam: np.ndarray, method: str = "",
                  residuals: dict[str, float] | None = None, n_images: int = 0) -> None:
    """Write the hand-eye YAML (``T_flange_cam`` 4x4, metres, OpenCV camera axes)."""
    data = {"T_flange_cam": np.asarray(T_flange_cam, float).round(9).tolist(), "method": method,
            "n_images": int(n_images), "residuals": residuals or {},
            "convention": "T_flange_cam maps camera (OpenCV x right, y down, z forward) points into the flange frame"}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))


def load_hand_eye(path: str | Path) -> np.ndarray:
    """T_flange_cam (4, 4) from a hand-eye YAML; ConfigError when missing or not rigid."""
    d = _read_mapping(path)
    T = np.asarray(d.get("T_flange_cam"), float)
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise ConfigError(f"{path}: T_flange_cam must be a rigid 4x4 transform; run torm calibrate hand-eye")
    return T


@dataclass(frozen=True)
class HandEyeResult:
    """The calibration, its residuals and the images used / skipped."""

    T_flange_cam: np.ndarray
    residuals: HandEyeResiduals
    used: tuple[str, ...]
    skipped: tuple[str, ...]


def calibrate_from_images(images_dir: str | Path, poses: list[tuple[str, np.ndarray]], K: np.ndarray,
                          dist: np.ndarray, spec: CharucoSpec, method: str = "PARK") -> HandEyeResult:
    """Detect the board in every listed image, then :func:`calibrate_hand_eye`; images without a board are skipped."""
    base = Path(images_dir)
    A, B, used, skipped = [], [], [], []
    for name, T_bf in poses:
        p = base / name
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise CaptureError(f"cannot read image {p}; check --images and the names in the poses file")
        T_ct = board_pose(img, K, dist, spec)
        if T_ct is None:
            log.warning("no ChArUco board found in %s; skipped", p)
            skipped.append(name)
            continue
        A.append(T_bf)
        B.append(T_ct)
        used.append(name)
    if len(A) < 3:
        raise CaptureError(f"the board was found in only {len(A)} image(s); need >= 3 (check --board/--square/"
                           "--marker/--dict match the printed board)")
    T = calibrate_hand_eye(A, B, method)
    return HandEyeResult(T, hand_eye_residuals(T, A, B), tuple(used), tuple(skipped))

