"""Capture folders: exact save/load round trip, NeRF-style datasets, and refusal of inconsistent folders."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from torm.capture import RecordedProvider, evenly_spaced, load_capture, save_capture
from torm.capture.provider import ImageProvider
from torm.errors import CaptureError
from torm.geometry import cv_to_gl, look_at_cv
from torm.types import CameraView, Capture

H, W = 24, 40


def _capture(n: int = 4) -> Capture:
    rng = np.random.default_rng(7)
    K = np.array([[31.123456789012345, 0.0, 20.0], [0.0, 31.123456789012345, 12.0], [0.0, 0.0, 1.0]])
    views = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.1
        T = look_at_cv(np.array([0.55 + 0.4 * math.cos(a), 0.4 * math.sin(a), 0.3 + 0.01 * i]), np.array([0.55, 0, 0]))
        depth = rng.uniform(0.1, 1.5, (H, W)).astype(np.float32)
        depth[0, :3] = [0.0, np.nan, 1e-30]
        sensor = (depth + rng.normal(0, 1e-3, (H, W))).astype(np.float32)
        mask = rng.integers(0, 4, (H, W)).astype(np.int32)
        mask[0, 0] = 3
        Ki = K.copy()
        if i == 1:  # per-frame intrinsics survive too
            Ki[0, 0], Ki[1, 2] = 29.5, 11.75
        views.append(CameraView(K=Ki, T_world_cam=T, rgb=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                                depth=depth, sensor_depth=sensor if i != 2 else None, mask=mask, name=f"view_{i}"))
    return Capture(views=tuple(views), scenario="rw4", seed=3, object_ids=(1, 2, 3),
                   object_names=("ball", "cube", "toothpick_box"), table_height=0.0,
                   workspace_bounds=np.array([[0.33, -0.22, -0.005], [0.77, 0.22, 0.2]]),
                   metadata={"renderer": "test", "occlusion": {"occlusion_ratio": 0.25}})


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8)


def test_round_trip_is_exact(tmp_path: Path):
    cap = _capture()
    path = save_capture(cap, tmp_path / "cap")
    assert path.name == "transforms.json"
    doc = json.loads(path.read_text())
    assert doc["torm_version"] and doc["w"] == W and doc["h"] == H and doc["camera_model"] == "PINHOLE"
    # nerfstudio convention: the stored matrix is camera-to-world in OpenGL axes
    np.testing.assert_array_equal(np.array(doc["frames"][0]["transform_matrix"]), cv_to_gl(cap.views[0].T_world_cam))
    assert "fl_x" in doc["frames"][1] and "fl_x" not in doc["frames"][0]
    back = load_capture(tmp_path / "cap")
    assert len(back) == len(cap)
    assert (back.scenario, back.seed, back.object_ids, back.object_names) == (
        cap.scenario, cap.seed, cap.object_ids, cap.object_names)
    assert back.table_height == cap.table_height
    np.testing.assert_array_equal(back.workspace_bounds, cap.workspace_bounds)
    assert back.metadata == cap.metadata
    for a, b in zip(cap.views, back.views, strict=True):
        assert b.name == a.name
        np.testing.assert_array_equal(b.rgb, a.rgb)
        assert b.mask.dtype == np.int32
        np.testing.assert_array_equal(b.mask, a.mask)
        assert b.depth.dtype == np.float32
        np.testing.assert_array_equal(_bits(b.depth), _bits(a.depth))  # bitwise, NaN and denormals included
        if a.sensor_depth is None:
            assert b.sensor_depth is None
        else:
            np.testing.assert_array_equal(_bits(b.sensor_depth), _bits(a.sensor_depth))
        assert np.abs(b.T_world_cam - a.T_world_cam).max() <= 1e-12
        assert np.abs(b.K - a.K).max() <= 1e-12


def test_recorded_provider_subsets(tmp_path: Path):
    save_capture(_capture(5), tmp_path)
    prov = RecordedProvider(tmp_path)
    assert isinstance(prov, ImageProvider)
    assert len(prov.capture()) == 5
    sub = prov.capture(3)
    assert [v.name for v in sub.views] == ["view_0", "view_2", "view_4"]
    picked = RecordedProvider(tmp_path, views=[4, 1]).capture()
    assert [v.name for v in picked.views] == ["view_4", "view_1"]
    assert evenly_spaced(10, 1) == [0]
    with pytest.raises(CaptureError):
        prov.capture(6)
    with pytest.raises(CaptureError, match="out of range"):
        load_capture(tmp_path, views=[7])


def _write_nerf_synthetic(root: Path, n: int = 3) -> tuple[float, list[np.ndarray]]:
    """A Blender-NeRF-style folder: transforms_train.json, camera_angle_x, RGBA PNGs, file_path without extension."""
    (root / "train").mkdir(parents=True)
    angle = 0.6911112070083618
    frames, alphas = [], []
    yy, xx = np.mgrid[0:H, 0:W]
    for i in range(n):
        rgba = np.zeros((H, W, 4), np.uint8)
        rgba[..., :3] = (40 * i, 100, 200)
        alpha = ((xx - 20) ** 2 + (yy - 12) ** 2 < (5 + i) ** 2)
        rgba[..., 3] = np.where(alpha, 255, 0)
        rgba[0, 0, 3] = 127  # just below 0.5: background
        rgba[0, 1, 3] = 128  # just above: foreground
        alpha[0, 0], alpha[0, 1] = False, True
        cv2.imwrite(str(root / "train" / f"r_{i}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
        T_gl = cv_to_gl(look_at_cv(np.array([2.0 * math.cos(i), 2.0 * math.sin(i), 1.0]), np.zeros(3)))
        frames.append({"file_path": f"./train/r_{i}", "rotation": 0.012, "transform_matrix": T_gl.tolist()})
        alphas.append(alpha)
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return angle, alphas


def test_nerf_style_rgba_dataset_loads_with_alpha_masks(tmp_path: Path):
    angle, alphas = _write_nerf_synthetic(tmp_path)
    cap = load_capture(tmp_path)
    assert len(cap) == 3 and cap.image_size == (H, W)
    fx = 0.5 * W / math.tan(0.5 * angle)
    for i, v in enumerate(cap.views):
        np.testing.assert_allclose(v.K, [[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]], rtol=1e-15)
        np.testing.assert_array_equal(v.mask, alphas[i].astype(np.int32))
        assert tuple(v.rgb[5, 5]) == (40 * i, 100, 200)
        # OpenGL camera looks along -z: the world origin is in front of the OpenCV camera (positive depth)
        _, z = v.project(np.zeros((1, 3)))
        assert z[0] > 0
    assert cap.object_ids == (1,)


def test_folder_without_masks_and_with_mm_depth(tmp_path: Path):
    img = np.full((H, W, 3), 90, np.uint8)
    cv2.imwrite(str(tmp_path / "a.jpg"), img)
    depth_mm = np.full((H, W), 1234, np.uint16)
    cv2.imwrite(str(tmp_path / "a_depth.png"), depth_mm)
    doc = {"fl_x": 30.0, "fl_y": 31.0, "w": W, "h": H,
           "frames": [{"file_path": "a.jpg", "depth_file_path": "a_depth.png", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    cap = load_capture(tmp_path)
    v = cap.views[0]
    assert v.mask is None and not cap.has_masks
    # a nerfstudio-style binary 0/255 mask becomes instance 1
    fg = np.zeros((H, W), np.uint8)
    fg[5:9, 6:20] = 255
    cv2.imwrite(str(tmp_path / "a_mask.png"), fg)
    doc["frames"][0]["mask_path"] = "a_mask.png"
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    masked = load_capture(tmp_path)
    np.testing.assert_array_equal(masked.views[0].mask, (fg > 0).astype(np.int32))
    assert masked.object_ids == (1,)
    assert v.K[0, 0] == 30.0 and v.K[1, 1] == 31.0 and v.K[0, 2] == W / 2
    np.testing.assert_allclose(v.depth, 1.234, rtol=1e-6)


@pytest.mark.parametrize(
    "breakage, expected",
    [
        ("missing_image", "images/00001.png"),
        ("image_size", "images/00002.png"),
        ("mask_size", "masks/00000.png"),
        ("nan_pose", "frame 1"),
        ("names_count", "object_names has 2 entries but object_ids has 3"),
        ("mask_ids", "masks/00003.png"),
        ("depth_size", "depth/00001.npy"),
        ("no_transforms", "transforms.json"),
    ],
)
def test_inconsistent_folders_are_refused_naming_the_file(tmp_path: Path, breakage: str, expected: str):
    root = tmp_path / "cap"
    save_capture(_capture(), root)
    tpath = root / "transforms.json"
    doc = json.loads(tpath.read_text())
    if breakage == "missing_image":
        (root / "images/00001.png").unlink()
    elif breakage == "image_size":
        cv2.imwrite(str(root / "images/00002.png"), np.zeros((H + 2, W, 3), np.uint8))
    elif breakage == "mask_size":
        cv2.imwrite(str(root / "masks/00000.png"), np.zeros((H, W - 1), np.uint16))
    elif breakage == "nan_pose":
        doc["frames"][1]["transform_matrix"][0][3] = float("nan")
    elif breakage == "names_count":
        doc["object_names"] = ["a", "b"]
    elif breakage == "mask_ids":
        m = np.zeros((H, W), np.uint16)
        m[3, 3] = 9
        cv2.imwrite(str(root / "masks/00003.png"), m)
    elif breakage == "depth_size":
        np.save(root / "depth/00001.npy", np.zeros((H, W + 1), np.float32))
    elif breakage == "no_transforms":
        tpath.unlink()
    if tpath.exists():
        tpath.write_text(json.dumps(doc))
    with pytest.raises(CaptureError) as exc:
        load_capture(root)
    assert expected in str(exc.value)
