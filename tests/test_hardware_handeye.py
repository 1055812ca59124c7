"""Hand-eye calibration: recovering a known T_flange_cam from synthetic poses and from rendered ChArUco images."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from torm.geometry import invert_T, look_at_cv, make_T
from torm.hardware.handeye import (
    METHODS,
    CharucoSpec,
    board_pose,
    calibrate_hand_eye,
    hand_eye_residuals,
    load_hand_eye,
)

T_FLANGE_CAM = make_T(Rotation.from_euler("xyz", [3.0, -2.0, 91.0], degrees=True).as_matrix(), [0.035, -0.06, 0.045])
# board lying face-up on the table: board x = world x, board y = -world y, board z (into the board) = -world z
T_BASE_TARGET = make_T(np.diag([1.0, -1.0, -1.0]), [0.45, -0.08, 0.0])
BOARD_CENTRE = T_BASE_TARGET[:3, 3] + np.array([0.105, -0.075, 0.0])


def _rot_deg(A: np.ndarray, B: np.ndarray) -> float:
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def _camera_poses(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Camera poses T_base_cam above the board: elevation 45-75 deg, distance 0.33-0.45 m, roll +-30 deg."""
    out = []
    for _ in range(n):
        el, az = np.radians(rng.uniform(45, 75)), rng.uniform(0, 2 * np.pi)
        r = rng.uniform(0.33, 0.45)
        eye = BOARD_CENTRE + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        T = look_at_cv(eye, BOARD_CENTRE + rng.normal(0, 0.01, 3))
        roll = make_T(Rotation.from_euler("z", rng.uniform(-30, 30), degrees=True).as_matrix(), np.zeros(3))
        out.append(T @ roll)
    return out


def _pairs(rng: np.random.Generator, n: int, noise_m: float = 0.0, noise_deg: float = 0.0):
    A, B = [], []
    for T_base_cam in _camera_poses(rng, n):
        T_base_flange = T_base_cam @ invert_T(T_FLANGE_CAM)
        T_cam_target = invert_T(T_base_cam) @ T_BASE_TARGET
        if noise_m or noise_deg:
            dR = Rotation.from_rotvec(np.radians(noise_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
            T_cam_target = make_T(dR @ T_cam_target[:3, :3], T_cam_target[:3, 3] + rng.normal(0, noise_m, 3))
        A.append(T_base_flange)
        B.append(T_cam_target)
    return A, B


@pytest.mark.parametrize("method", ["TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS"])
def test_recovers_known_transform_with_noise(method):
    A, B = _pairs(np.random.default_rng(0), 20, noise_m=0.0003, noise_deg=0.03)
    T = calibrate_hand_eye(A, B, method)
    assert np.linalg.norm(T[:3, 3] - T_FLANGE_CAM[:3, 3]) < 1e-3
    assert _rot_deg(T, T_FLANGE_CAM) < 0.1
    res = hand_eye_residuals(T, A, B)
    assert res.summary()["translation_mm_mean"] < 1.5 and res.summary()["rotation_deg_mean"] < 0.1
    assert np.linalg.norm(res.T_base_target[:3, 3] - T_BASE_TARGET[:3, 3]) < 1.5e-3


def test_noise_free_is_exact_and_a_wrong_transform_shows_in_the_residuals():
    A, B = _pairs(np.random.default_rng(1), 8)
    for method in METHODS:
        T = calibrate_hand_eye(A, B, method)
        assert np.linalg.norm(T[:3, 3] - T_FLANGE_CAM[:3, 3]) < 1e-5, method
    wrong = T_FLANGE_CAM.copy()
    wrong[:3, 3] += [0.01, 0, 0]
    assert hand_eye_residuals(wrong, A, B).summary()["translation_mm_max"] > 3.0


SPEC = CharucoSpec(7, 5, 0.03, 0.022, "DICT_5X5_100")
K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
PPM = 4000.0  # board image pixels per metre
BORDER = 60


def _board_image() -> np.ndarray:
    img = SPEC.board().generateImage((int(round(0.21 * PPM)), int(round(0.15 * PPM))), marginSize=0)
    return cv2.copyMakeBorder(img, BORDER, BORDER, BORDER, BORDER, cv2.BORDER_CONSTANT, value=255)


def _render(board_img: np.ndarray, T_cam_target: np.ndarray) -> np.ndarray:
    """Image of the board plane (z = 0 in the target frame) seen by a pinhole camera K at T_cam_target."""
    A = np.array([[1 / PPM, 0, (0.5 - BORDER) / PPM], [0, 1 / PPM, (0.5 - BORDER) / PPM], [0, 0, 1]])
    H = K @ np.column_stack([T_cam_target[:3, 0], T_cam_target[:3, 1], T_cam_target[:3, 3]]) @ A
    # pixel-centre convention: OpenCV warps map integer pixel centres, so shift by half a pixel both ways
    S = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])
    S_inv = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    out = cv2.warpPerspective(board_img, S @ H @ S_inv, (1280, 720), flags=cv2.INTER_LINEAR, borderValue=128)
    return cv2.cvtColor(out, cv2.COLOR_GRAY2BGR)


def test_charuco_pose_on_a_rendered_board():
    board_img = _board_image()
    T_base_cam = _camera_poses(np.random.default_rng(2), 1)[0]
    T_cam_target = invert_T(T_base_cam) @ T_BASE_TARGET
    T = board_pose(_render(board_img, T_cam_target), K, None, SPEC)
    assert T is not None
    assert np.linalg.norm(T[:3, 3] - T_cam_target[:3, 3]) < 2e-3
    assert _rot_deg(T, T_cam_target) < 0.5
    assert board_pose(np.full((720, 1280, 3), 128, np.uint8), K, None, SPEC) is None


def test_cli_hand_eye_from_rendered_images(tmp_path):
    from torm.cli import main

    board_img = _board_image()
    rng = np.random.default_rng(3)
    poses = []
    (tmp_path / "img").mkdir()
    for i, T_base_cam in enumerate(_camera_poses(rng, 10)):
        name = f"{i:03d}.png"
        cv2.imwrite(str(tmp_path / "img" / name), _render(board_img, invert_T(T_base_cam) @ T_BASE_TARGET))
        poses.append({"image": name, "T_base_flange": (T_base_cam @ invert_T(T_FLANGE_CAM)).tolist()})
    cv2.imwrite(str(tmp_path / "img" / "blank.png"), np.full((720, 1280, 3), 90, np.uint8))
    poses.append({"image": "blank.png", "T_base_flange": np.eye(4).tolist()})
    (tmp_path / "poses.yaml").write_text(yaml.safe_dump({"poses": poses}))
    (tmp_path / "K.json").write_text(json.dumps({"K": K.tolist(), "dist": [0, 0, 0, 0, 0]}))
    out = tmp_path / "hand_eye.yaml"
    rc = main(["calibrate", "hand-eye", "--images", str(tmp_path / "img"), "--poses", str(tmp_path / "poses.yaml"),
               "--intrinsics", str(tmp_path / "K.json"), "--board", "7x5", "--square", "0.03", "--marker", "0.022",
               "--method", "park", "--out", str(out)])
    assert rc == 0
    T = load_hand_eye(out)
    assert np.linalg.norm(T[:3, 3] - T_FLANGE_CAM[:3, 3]) < 3e-3
    assert _rot_deg(T, T_FLANGE_CAM) < 0.5
    data = yaml.safe_load(out.read_text())
    assert data["n_images"] == 10 and data["method"] == "PARK"
    assert data["residuals"]["translation_mm_mean"] < 3.0


@pytest.mark.parametrize("method", ["TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS"])
def test_opencv_and_the_numpy_cross_check_agree(method):
    from torm.hardware.handeye import solve_hand_eye_cv2
    from torm.hardware.handeye_solvers import solve_ax_xb

    A, B = _pairs(np.random.default_rng(3), 12, noise_m=0.0005, noise_deg=0.1)
    T_cv = solve_hand_eye_cv2(A, B, method)
    assert T_cv is not None  # OpenCV 5.1 has calibrateHandEye
    T_np = solve_ax_xb(A, B, method)
    assert np.linalg.norm(T_cv[:3, 3] - T_np[:3, 3]) < 2e-3 and _rot_deg(T_cv, T_np) < 0.2
    assert np.linalg.norm(T_cv[:3, 3] - T_FLANGE_CAM[:3, 3]) < 5e-3 and _rot_deg(T_cv, T_FLANGE_CAM) < 0.5
