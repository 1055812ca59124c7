"""A recorded reference pass in the trial loop (issue 43): the real arm's way to read the empty workspace."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from torm import config
from torm.capture.io import save_capture
from torm.errors import CaptureError, ConfigError
from torm.pipeline import TrialConfig, _capture, make_backend, trial_context
from torm.types import CameraView, Capture

BASE = ["capture.n_views=4", "capture.scale=0.25", "segmentation.segmenter=difference"]


def _cfg(*overrides: str) -> TrialConfig:
    return config.from_dict(TrialConfig, {"scenario": "rw1", "method": "torm"}, overrides=[*BASE, *overrides])


def _captured(cfg: TrialConfig) -> tuple[Capture, dict]:
    backend = make_backend(cfg)
    try:
        return _capture(cfg, backend)
    finally:
        backend.close()


def _recorded(cap: Capture, folder, images=None, shift_m: float = 0.0) -> str:
    """The rendered reference pass of ``cap`` saved as its own capture of the empty workspace."""
    views = []
    for i, v in enumerate(cap.views):
        T = v.T_world_cam.copy()
        T[0, 3] += shift_m
        views.append(CameraView(v.K, T, rgb=v.reference_rgb if images is None else images[i], name=v.name))
    save_capture(Capture(views=tuple(views), metadata={"renderer": cap.metadata["renderer"],
                                                       "date": "2026-12-06T18:00:00+00:00"}), folder)
    return str(folder)


def test_a_recorded_reference_is_paired_checked_and_named_and_a_stale_or_moved_one_refused(tmp_path):
    rendered, _ = _captured(_cfg("capture.reference=true"))
    folder = _recorded(rendered, tmp_path / "empty")
    cfg = _cfg(f"capture.reference_dir={folder}")
    cap, info = _captured(cfg)
    for v, r in zip(cap.views, rendered.views, strict=True):
        np.testing.assert_array_equal(v.reference_rgb, r.reference_rgb)  # the recorded pass, view by view
    ref = info["reference"]
    assert ref["folder"] == folder and ref["recorded"] == "2026-12-06T18:00:00+00:00"
    assert 0.0 <= ref["background_grey"] < 1.0  # MuJoCo: the same renderer, nothing but the objects changed
    assert trial_context(cfg)["reference"] == f"recorded:{folder}"

    # the light moved since the reference was recorded: a brightness ramp across every view
    ramp = [np.clip(v.reference_rgb * np.linspace(0.6, 1.4, v.width)[None, :, None], 0, 255).astype(np.uint8)
            for v in rendered.views]
    stale = _recorded(rendered, tmp_path / "stale", images=ramp)
    with pytest.raises(CaptureError, match="record a new reference pass"):
        _captured(_cfg(f"capture.reference_dir={stale}"))
    moved = _recorded(rendered, tmp_path / "moved", shift_m=0.01)  # flown along another path
    with pytest.raises(CaptureError, match="10.0 mm.*same path"):
        _captured(_cfg(f"capture.reference_dir={moved}"))


def test_reference_settings_are_validated_with_the_fix():
    with pytest.raises(ConfigError, match="set one of them"):
        _cfg("capture.reference=true", "capture.reference_dir=somewhere")
    with pytest.raises(ConfigError, match="capture.reference_dir=DIR"):
        _cfg()  # the difference segmenter with no reference pass at all
    with pytest.raises(ConfigError, match="give it as capture.reference_dir"):
        make_backend(replace(_cfg("capture.reference=true"), backend="real"))


def test_torm_capture_empty_records_the_pass_a_trial_renders_for_itself(tmp_path, capsys):
    from torm.capture.io import load_capture
    from torm.cli import main

    out = tmp_path / "empty"
    assert main(["capture", "--scenario", "rw1", "--views", "4", "--scale", "0.25", "--empty", "--no-progress",
                 "--out", str(out)]) == 0
    capsys.readouterr()
    empty = load_capture(out)
    assert not np.any(empty.masks()) and empty.metadata["source"].startswith("empty workspace")
    rendered, _ = _captured(_cfg("capture.reference=true"))
    cap, info = _captured(_cfg(f"capture.reference_dir={out}"))
    for v, r in zip(cap.views, rendered.views, strict=True):  # MuJoCo: the same pixels as the rendered pass
        np.testing.assert_array_equal(v.reference_rgb, r.reference_rgb)
    assert info["reference"]["background_grey"] == 0.0 and info["reference"]["recorded"] == empty.metadata["date"]
    assert main(["capture", "--scenario", "rw1", "--views", "4", "--empty", "--reference", "--out",
                 str(tmp_path / "x")]) != 0
    assert "give one of them" in capsys.readouterr().err


def test_torm_capture_on_the_real_backend_saves_the_trial_poses_and_disables_the_arm(tmp_path, capsys, monkeypatch):
    """The real code path on the fake rosbridge controller and a fake Modbus gripper; the camera reads a fixed
    image at the pose the arm reports (no RealSense here)."""
    from sim.robots.config import load_robot_config
    from torm.capture.io import load_capture
    from torm.cli import main
    from torm.hardware.backend import RealBackend
    from torm.testing.fake_robotiq import FakeRobotiq, FakeRobotiqServer
    from torm.testing.fake_rosbridge import FakeRosbridge, write_cell_yaml

    class Camera:
        T_flange_cam = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0.05], [0, 0, 1, 0.03], [0, 0, 0, 1]])  # looks along z

        def __init__(self, backend: RealBackend) -> None:
            self.backend = backend

        def read(self) -> CameraView:
            inner = self.backend.arm.inner
            K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
            return CameraView(K, inner.flange_pose(inner.state().q) @ self.T_flange_cam,
                              rgb=np.full((60, 80, 3), 120, np.uint8))

    monkeypatch.setattr(RealBackend, "camera", property(Camera))
    rcfg = load_robot_config("inovo_2f85")
    ros = FakeRosbridge(rcfg.arm.home_q, tuple(rcfg.arm.joints))
    modbus = FakeRobotiqServer(FakeRobotiq())
    hw = write_cell_yaml(tmp_path / "hw.yaml", ros.port, modbus.url, "capture: {settle_s: 0.0}")
    try:
        out = tmp_path / "cell_empty"
        rc = main(["capture", "--backend", "real", "--hardware-config", str(hw), "--arm-robot", "--views", "3",
                   "--empty", "--out", str(out)])
        res = capsys.readouterr()
        assert rc == 0, res.err[-2000:]
        summary = json.loads(res.out)
        assert summary["requested_views"] == 3 and 1 <= summary["views"] <= 3  # the reachable ones (this hand-eye)
        cap = load_capture(out)
        assert cap.metadata["backend"] == "real" and cap.metadata["source"].startswith("empty workspace")
        assert len(cap.metadata["joint_positions"]) == len(cap) == summary["views"]
        assert cap.metadata["date"] == summary["date"]
        assert any(m.get("service") == "/robot/disable" for m in ros.msgs(since=0.0))  # stopped on exit
        assert main(["capture", "--backend", "real", "--scenario", "rw1", "--out", str(tmp_path / "x")]) != 0
        assert "--scenario: simulation flags" in capsys.readouterr().err
    finally:
        ros.close()
        modbus.close()
