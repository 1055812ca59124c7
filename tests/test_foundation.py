"""Shared types, errors and config loading."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from torm import config
from torm.errors import CaptureError, ConfigError, UnknownNameError
from torm.geometry import cv_to_gl, gl_to_cv, invert_T, look_at_cv
from torm.types import CameraView, Capture, Grasp


@dataclass(frozen=True)
class _Inner:
    res: int = 32
    scale: float = 1.0
    mode: str = "fast"

    def __post_init__(self) -> None:
        if self.res < 4:
            raise ConfigError(f"res must be >= 4, got {self.res}")


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)
    names: tuple[str, ...] = ("a",)
    seed: int | None = None


def test_config_defaults_yaml_and_overrides(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("inner:\n  res: 48\nnames: [x, y]\n")
    cfg = config.load(_Outer, p, overrides=["inner.scale=2", "seed=7"])
    assert cfg.inner.res == 48 and cfg.inner.scale == 2.0 and cfg.names == ("x", "y") and cfg.seed == 7
    assert config.to_dict(cfg)["names"] == ["x", "y"]


def test_config_rejects_unknown_and_bad_values(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['rez'\].*valid keys: \['mode', 'res', 'scale'\]"):
        config.from_dict(_Outer, {"inner": {"rez": 3}})
    with pytest.raises(ConfigError, match="expected an integer"):
        config.from_dict(_Outer, {}, overrides=["inner.res=abc"])
    with pytest.raises(ConfigError, match="res must be >= 4"):
        config.from_dict(_Outer, {}, overrides=["inner.res=2"])
    with pytest.raises(ConfigError, match="section.key=value"):
        config.apply_overrides({}, ["nonsense"])
    with pytest.raises(ConfigError, match="does not exist"):
        config.load(_Outer, tmp_path / "missing.yaml")


def test_unknown_name_lists_choices():
    err = UnknownNameError("scenario", "rw9", ["rw1", "rw2"])
    assert "rw9" in str(err) and "rw1, rw2" in str(err)
    assert isinstance(err, KeyError)


def test_look_at_and_gl_roundtrip():
    T = look_at_cv(np.array([0.5, 0.0, 0.5]), np.zeros(3))
    # The optical axis (+z in OpenCV) points at the target.
    assert np.allclose(T[:3, 2], -np.array([0.5, 0, 0.5]) / np.linalg.norm([0.5, 0, 0.5]))
    # Image "down" (+y) has a negative world-z component.
    assert T[2, 1] < 0
    assert np.allclose(gl_to_cv(cv_to_gl(T)), T)
    assert np.allclose(invert_T(T) @ T, np.eye(4))


def _view(**kw):
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    return CameraView(K=K, T_world_cam=look_at_cv(np.array([0, -0.5, 0.5]), np.zeros(3)), **kw)


def test_camera_view_validation_and_projection():
    v = _view(mask=np.zeros((48, 64), np.int32))
    uv, z = v.project(np.zeros((1, 3)))
    assert np.allclose(uv, [[32, 24]]) and np.isclose(z[0], np.sqrt(0.5))
    with pytest.raises(CaptureError, match="NaN pose"):
        CameraView(K=v.K, T_world_cam=np.full((4, 4), np.nan), mask=v.mask)
    with pytest.raises(CaptureError, match="depth has size"):
        _view(mask=np.zeros((48, 64), np.int32), depth=np.zeros((10, 10), np.float32))
    with pytest.raises(CaptureError, match="rgb must be uint8"):
        _view(rgb=np.zeros((48, 64, 3), np.float32))


def test_capture_checks_sizes_and_masks():
    a = _view(mask=np.zeros((48, 64), np.int32))
    b = _view(rgb=np.zeros((40, 64, 3), np.uint8))
    with pytest.raises(CaptureError, match="view 1"):
        Capture(views=(a, b))
    cap = Capture(views=(a, _view(rgb=np.zeros((48, 64, 3), np.uint8))))
    with pytest.raises(CaptureError, match="view 1 .* has no mask"):
        cap.masks()
    with pytest.raises(CaptureError, match="got 1 masks for 2 views"):
        cap.with_masks([np.zeros((48, 64))])
    assert cap.with_masks(np.ones((2, 48, 64))).masks().dtype == np.int32


def test_grasp_graspnet_roundtrip():
    T = look_at_cv(np.array([0.1, 0.2, 0.3]), np.zeros(3))
    g = Grasp(T, width=0.05, score=0.8, object_id=3, height=0.02, depth=0.015)
    row = g.to_graspnet()
    assert row.shape == (17,) and row[0] == 0.8 and row[16] == 3
    g2 = Grasp.from_graspnet(row)
    assert np.allclose(g2.T_world_grasp, T) and g2.width == 0.05 and g2.object_id == 3


def test_with_options_layers_keywords_over_a_config():
    base = config.from_dict(_Outer, {"inner": {"res": 48}})
    cfg = config.with_options(_Outer, base, {"seed": 3})
    assert cfg.inner.res == 48 and cfg.seed == 3
    assert config.with_options(_Outer, {"names": ["z"]}, {}).names == ("z",)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['sede'\]"):
        config.with_options(_Outer, None, {"sede": 3})
