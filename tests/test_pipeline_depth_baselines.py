"""Depth baselines in the trial pipeline: what each captures, trial records naming the depth model."""

from __future__ import annotations

import numpy as np
import pytest

from torm import config
from torm.errors import UnknownNameError
from torm.pipeline import TrialConfig, _capture, make_backend, perceive, trial_context


def _cfg(method: str, depth_model: str = "statistical") -> TrialConfig:
    return config.from_dict(TrialConfig, {"scenario": "rw2", "method": method},
                            overrides=["capture.n_views=6", "capture.scale=0.25",
                                       f"capture.depth_model={depth_model}"])


def test_single_view_depth_captures_one_view_without_rgb():
    cfg = _cfg("depth")
    backend = make_backend(cfg)
    try:
        cap, info = _capture(cfg, backend)
        poses = backend.capture_poses(6)
        assert len(cap) == 1 and info["views_captured"] == 1
        assert info["depth_view"] == int(np.argmax(-poses[:, 2, 2]))
        v = cap.views[0]
        assert v.rgb is None and v.sensor_depth is not None and v.mask is not None
        assert np.allclose(v.T_world_cam, poses[info["depth_view"]])
        assert cap.metadata["depth_model"]["name"] == "statistical"
    finally:
        backend.close()


@pytest.mark.parametrize(("method", "segmenter", "rgb", "wants_rgb"), [
    ("oracle", "gt", False, False), ("torm", "gt", False, False), ("torm", "noisy", False, False),
    ("torm", "learned", False, True), ("oracle", "gt", True, True)])
def test_methods_that_read_no_image_capture_no_rgb(method, segmenter, rgb, wants_rgb):
    """The RGB pass (path tracing with renderer=pbr) runs only for a segmenter that reads pixels, or a recording."""
    cfg = config.from_dict(TrialConfig, {"scenario": "rw2", "method": method},
                           overrides=["capture.n_views=4", "capture.scale=0.25",
                                      f"segmentation.segmenter={segmenter}"])
    backend = make_backend(cfg)
    try:
        cap, info = _capture(cfg, backend, rgb=rgb)
        assert len(cap) == info["views_captured"] == 4
        assert all((v.rgb is not None) == wants_rgb for v in cap.views)
        assert all(v.mask is not None and v.depth is not None for v in cap.views)
        assert info["channels"] == ("all" if wants_rgb else ["depth", "mask"])
    finally:
        backend.close()


def test_depth_fusion_perceives_the_opaque_cup_from_every_view():
    cfg = _cfg("depth_fusion", "ideal")
    backend = make_backend(cfg)
    try:
        timings: dict[str, float] = {}
        per = perceive(cfg, backend, np.random.default_rng(0), timings)
        info = per.info["capture_info"]
        assert info["views_captured"] == 6 and info["channels"] == ["sensor_depth", "mask"]
        assert [c.object_index for c in per.point_clouds] == [1]
        assert per.meshes[0] is not None and per.info["n_views_fused"] == 6
        true_c = backend.ground_truth.object_meshes()[1].verts_vx3.mean(axis=0)
        assert np.linalg.norm(per.point_clouds[0].points_nx3.mean(axis=0)[:2] - true_c[:2]) < 0.02
    finally:
        backend.close()


def test_context_names_the_depth_model_and_methods_are_validated():
    ctx = trial_context(_cfg("depth_fusion"))
    assert ctx["depth_model"] == "statistical" and ctx["segmenter"] == "gt" and ctx["method"] == "depth_fusion"
    with pytest.raises(UnknownNameError):
        config.from_dict(TrialConfig, {"capture": {"depth_model": "lidar"}})
    with pytest.raises(UnknownNameError, match="depth_fusion.*package.module:callable"):
        config.from_dict(TrialConfig, {"method": "graspnet"})
