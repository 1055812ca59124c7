"""Hardware config loading, the make_real_backend entry point, the operator prompt and the camera helpers."""

from __future__ import annotations

import io
import sys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from torm.errors import ConfigError, HardwareError
from torm.hardware.config import ENV_ARMED, ENV_CONFIG, load_hardware_config, resolve_hardware_config
from torm.hardware.realsense import Undistorter, import_pyrealsense2


def _write(tmp_path, text: str):
    p = tmp_path / "hw.yaml"
    p.write_text(text)
    return p


def test_hardware_yaml_resolves_relative_paths_and_rejects_unknown_keys(tmp_path):
    p = _write(tmp_path, "host: 10.0.0.5\nspeed_scale: 0.2\ncommand_log: logs/cmd.jsonl\n"
                         "gripper: {device: /dev/ttyUSB1, calibration: cal.yaml}\ncamera: {hand_eye: he.yaml}\n")
    cfg = load_hardware_config(p)
    assert cfg.host == "10.0.0.5" and cfg.port == 9090 and not cfg.armed and cfg.speed_scale == 0.2
    assert cfg.command_log == str(tmp_path / "logs" / "cmd.jsonl")
    assert cfg.gripper.calibration == str(tmp_path / "cal.yaml") and cfg.camera.hand_eye == str(tmp_path / "he.yaml")
    with pytest.raises(ConfigError, match="unknown key"):
        load_hardware_config(_write(tmp_path, "host: a\nbogus: 1\n"))
    with pytest.raises(ConfigError, match="host"):
        load_hardware_config(_write(tmp_path, "port: 9090\n"))
    with pytest.raises(ConfigError, match="speed_scale"):
        load_hardware_config(_write(tmp_path, "host: a\nspeed_scale: 1.5\n"))


def test_resolve_from_trial_field_or_environment(tmp_path, monkeypatch):
    p = _write(tmp_path, "host: 10.0.0.5\n")
    monkeypatch.delenv(ENV_CONFIG, raising=False)
    monkeypatch.delenv(ENV_ARMED, raising=False)
    with pytest.raises(ConfigError, match="--hardware-config"):
        resolve_hardware_config(SimpleNamespace())
    assert not resolve_hardware_config(SimpleNamespace(hardware_config=str(p))).armed
    assert resolve_hardware_config(SimpleNamespace(hardware_config=str(p), arm_robot=True)).armed
    monkeypatch.setenv(ENV_CONFIG, str(p))
    monkeypatch.setenv(ENV_ARMED, "1")
    assert resolve_hardware_config(None).armed


def test_make_real_backend_reports_an_unreachable_controller(tmp_path):
    import socket

    from torm.hardware import make_real_backend

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = _write(tmp_path, f"host: 127.0.0.1\nport: {port}\nconnect_timeout_s: 1.0\ncommand_log: cmd.jsonl\n")
    trial = SimpleNamespace(robot="inovo_2f85", hardware_config=str(p), arm_robot=True)
    with pytest.raises(HardwareError, match=f"127.0.0.1:{port}"):
        make_real_backend(trial)
    assert '"kind": "connect"' in (tmp_path / "cmd.jsonl").read_text()


def test_operator_prompt_reads_yes_or_no():
    from torm.hardware import operator_prompt

    out = io.StringIO()
    assert operator_prompt(SimpleNamespace(object_id=2, outcome="success"), io.StringIO("y\n"), out)
    assert "object 2" in out.getvalue()
    assert not operator_prompt(None, io.StringIO("\n"), io.StringIO())
    assert not operator_prompt(None, io.StringIO("no\n"), io.StringIO())


def test_missing_pyrealsense2_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # makes the import fail like an absent package
    with pytest.raises(HardwareError, match=r"pip install 'torm\[hardware\]'"):
        import_pyrealsense2()


def test_undistortion_yields_a_pinhole_image():
    """A dot drawn where the D455's distortion puts a 3D point lands at the pinhole projection after undistortion."""
    K = np.array([[632.4, 0, 639.8], [0, 632.0, 363.3], [0, 0, 1.0]])
    dist = np.array([-0.0565, 0.0688, -0.0007, -0.00003, -0.0224])
    pts = np.array([[0.35, 0.2, 1.0], [-0.5, -0.3, 1.0], [0.0, 0.0, 1.0]])
    uv_dist = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    uv_pin = (pts[:, :2] / pts[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.max(np.linalg.norm(uv_dist - uv_pin, axis=1)) > 2.0  # the distortion is visible
    img = np.zeros((720, 1280, 3), np.uint8)
    for u, v in uv_dist:
        cv2.circle(img, (int(round(u)), int(round(v))), 3, (255, 255, 255), -1)
    und = Undistorter(K, dist, (1280, 720)).image(img)
    for u, v in uv_pin:
        y0, x0 = int(round(v)), int(round(u))
        win = und[y0 - 8:y0 + 9, x0 - 8:x0 + 9, 0].astype(float)
        ys, xs = np.nonzero(win > 60)
        assert len(xs)
        c = np.array([np.average(xs, weights=win[ys, xs]), np.average(ys, weights=win[ys, xs])]) - 8
        assert np.linalg.norm(c + [x0, y0] - [u, v]) < 1.0
