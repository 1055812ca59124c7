"""The physically based renderer: silhouettes equal the MuJoCo masks, glass refracts, the rig and trial use it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim.cameras.renderers import make_renderer
from sim.cameras.rig import CameraRigConfig, SimCameraRig
from sim.render import MitsubaRenderer, PbrSettings, RenderCamera
from sim.render.mitsuba_renderer import render_linear, tone_map
from sim.render.scene import describe_world, load_scene
from sim.world import build_world
from tests.render_helpers import camera, tiny_world

FAST = PbrSettings(spp=4, max_depth=6, denoise="none", cache=False)


@pytest.fixture(scope="module")
def rw3():
    return build_world("rw3", 0, robot=None)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def test_pbr_silhouettes_match_mujoco_instance_masks(rw3):
    cfg = CameraRigConfig(n_views=3, width=160, height=90)
    cams = [RenderCamera(cfg.K(), T, cfg.image_width, cfg.image_height) for T in cfg.poses()]
    pbr = MitsubaRenderer(rw3, FAST)
    mj = make_renderer("mujoco", rw3)
    try:
        for p, m in zip(pbr.render(cams, rgb=False), mj.render(cams, rgb=False), strict=True):
            for o in rw3.objects:
                a, b = p.instance == o.instance_id, m.instance == o.instance_id
                assert b.sum() > 50
                assert _iou(a, b) >= 0.98, (o.name, _iou(a, b))
            assert set(np.unique(p.instance)) <= {0, *[o.instance_id for o in rw3.objects]}
    finally:
        mj.close()


def test_robot_and_collision_geoms_are_not_rendered():
    w = tiny_world()
    names = {g.name for g in describe_world(w).geoms}
    assert names == {"table", "obj1_box_visual", "obj2_ball_visual"}


def test_glass_refracts_what_is_behind_it_while_the_masks_stay_exact():
    w = tiny_world()
    cam = camera(width=96, height=72)
    r = MitsubaRenderer(w, dataclasses.replace(FAST, spp=16))
    mi_scene, pbr = r.scene()
    ids = r.render([cam], rgb=False)[0].instance
    mj = make_renderer("mujoco", w)
    try:
        ref = mj.render([cam], rgb=False)[0].instance
    finally:
        mj.close()
    for k in (1, 2):  # the glass silhouette is the MuJoCo mask (to the odd pixel whose centre sits on an edge)
        assert _iou(ids == k, ref == k) >= 0.98 and (ids == k).sum() > 100
    glass_key = next(k for k, v in pbr.shape_instances.items() if v == 1)
    assert pbr.scene_dict[glass_key]["bsdf"]["int_ior"] == 1.5
    with_glass = tone_map(render_linear(mi_scene, cam, r.settings, 7), exposure=1.0).astype(float)
    # the same object with a null BSDF: light passes straight through, nothing bends
    pbr.scene_dict[glass_key]["bsdf"] = {"type": "null"}
    without = tone_map(render_linear(load_scene(pbr), cam, r.settings, 7), exposure=1.0).astype(float)
    inside = ids == 1
    far = ids == 0
    far[20:, :] = False  # stay clear of shadows and caustics next to the objects (top band of the image)
    diff_in = np.abs(with_glass - without)[inside].mean()
    diff_far = np.abs(with_glass - without)[far].mean()
    assert diff_in > 8.0 and diff_in > 4 * diff_far, (diff_in, diff_far)


def test_ior_is_a_per_object_material_property():
    w = tiny_world()
    w.objects[0].ior = 1.47
    r = MitsubaRenderer(w, FAST)
    _, pbr = r.scene()
    key = next(k for k, v in pbr.shape_instances.items() if v == 1)
    assert pbr.scene_dict[key]["bsdf"]["int_ior"] == pytest.approx(1.47)
    opaque = next(k for k, v in pbr.shape_instances.items() if v == 2)
    assert pbr.scene_dict[opaque]["bsdf"]["type"] == "diffuse"


def test_rig_takes_rgb_from_pbr_and_masks_from_mujoco(rw3):
    cfg = CameraRigConfig(n_views=2, width=64, height=36)
    with SimCameraRig.from_world(rw3, cfg) as plain:
        ref = plain.capture()
    pbr = MitsubaRenderer(rw3, FAST)
    with SimCameraRig.from_world(rw3, cfg, rgb_renderer=pbr) as rig:
        cap = rig.capture()
    assert cap.metadata["renderer"].startswith("pbr mitsuba")
    for a, b in zip(cap.views, ref.views, strict=True):
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.depth, b.depth)
        assert np.array_equal(a.K, b.K) and np.array_equal(a.T_world_cam, b.T_world_cam)
        assert a.rgb.shape == b.rgb.shape and not np.array_equal(a.rgb, b.rgb)


def test_trial_config_threads_the_renderer_to_the_backend(tmp_path, monkeypatch):
    from torm import config
    from torm.errors import UnknownNameError
    from torm.pipeline import TrialConfig, make_backend

    monkeypatch.setenv("TORM_CACHE_DIR", str(tmp_path))
    cfg = config.from_dict(TrialConfig, {"scenario": "rw1"}, overrides=[
        "capture.renderer=pbr", "capture.n_views=1", "capture.scale=0.05", "capture.pbr.spp=4",
        "capture.pbr.denoise=none"])
    assert cfg.capture.pbr.spp == 4
    backend = make_backend(cfg)
    try:
        assert backend.renderer == "pbr"
        cap = backend.capture(1)
        assert cap.metadata["renderer"].startswith("pbr") and cap.views[0].rgb.shape == (36, 64, 3)
        assert cap.views[0].mask.max() == 1
    finally:
        backend.close()
    with pytest.raises(UnknownNameError, match="pbr"):
        config.from_dict(TrialConfig, {}, overrides=["capture.renderer=cycles"])


def test_extra_emitters_render_a_projected_dot_pattern_in_a_dark_room():
    """The extension path of the IR stereo renders: a projector emitter added to the scene, room lights off."""
    import mitsuba as mi

    from sim.render import cv_to_mitsuba

    w = tiny_world()
    cam = camera(width=64, height=48)
    r = MitsubaRenderer(w, dataclasses.replace(FAST, spp=4))
    dots = (np.random.default_rng(0).random((64, 64)) > 0.9).astype(np.float32)
    T_proj = cam.T_world_cam.copy()
    T_proj[:3, 3] += cam.T_world_cam[:3, 0] * 0.05  # 5 cm to the camera's right
    projector = {"type": "projector", "fov": 70.0, "scale": 20.0, "to_world": cv_to_mitsuba(T_proj),
                 "irradiance": {"type": "bitmap", "bitmap": mi.Bitmap(np.repeat(dots[..., None], 3, axis=2)),
                                "raw": True, "filter_type": "nearest"}}
    dark = r.render([cam], env_scale=0.0, area_scale=0.0, exposure=1.0, rgb=True, instance=False)[0].rgb
    lit = r.render([cam], extra_emitters={"projector": projector}, env_scale=0.0, area_scale=0.0, exposure=1.0,
                   instance=False)[0].rgb
    assert dark.max() == 0
    grey = lit.astype(float).mean(axis=2)
    assert grey.mean() > 2 and np.abs(np.diff(grey, axis=1)).mean() > 2  # bright, high-frequency dots
    with pytest.raises(Exception, match="clashes"):
        r.render([cam], extra_emitters={"env": projector})


def test_capture_command_renders_pbr_rgb(tmp_path, capsys, monkeypatch):
    import json

    from torm.capture import load_capture
    from torm.cli import main

    monkeypatch.setenv("TORM_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "cap"
    assert main(["capture", "--scenario", "rw1", "--views", "2", "--width", "64", "--height", "36", "--robot",
                 "none", "--renderer", "pbr", "--spp", "4", "--no-occlusion", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["views"] == 2
    cap = load_capture(out)
    assert cap.metadata["renderer"].startswith("pbr mitsuba") and "spp 4" in cap.metadata["renderer"]
    assert cap.views[0].rgb.shape == (36, 64, 3) and cap.masks().max() == 1


def test_auto_render_scale_traces_the_width_the_segmenter_reads(tmp_path, monkeypatch):
    from torm import config
    from torm.errors import ConfigError
    from torm.pipeline import TrialConfig, make_backend, resolve_render_scale

    def cfg(*extra: str) -> TrialConfig:
        return config.from_dict(TrialConfig, {"scenario": "rw1"}, overrides=list(extra))

    assert resolve_render_scale(cfg("capture.pbr.render_scale=0.7")) == 0.7  # explicit values are kept
    auto = "capture.pbr.render_scale=0"
    assert resolve_render_scale(cfg(auto)) == 1.0  # GT masks read no pixels: native
    learned = (auto, "segmentation.segmenter=learned")
    assert resolve_render_scale(cfg(*learned)) == 1.0  # 640 px input on the 640 px capture
    assert resolve_render_scale(cfg(*learned, "segmentation.options.input_width=448")) == pytest.approx(0.7)
    assert resolve_render_scale(cfg(*learned, "segmentation.options.input_width=320")) == pytest.approx(0.5)
    assert resolve_render_scale(cfg(*learned, "segmentation.options.input_width=320", "capture.scale=1")) == \
        pytest.approx(0.25)
    assert resolve_render_scale(cfg(*learned, "segmentation.options.input_width=2000")) == 1.0  # never upsampled
    assert resolve_render_scale(cfg(*learned, "segmentation.options.input_width=0")) == 1.0  # 0 = capture width
    assert resolve_render_scale(cfg(*learned, "method=oracle")) == 1.0
    with pytest.raises(ConfigError, match="auto"):
        cfg("capture.pbr.render_scale=0.01")
    # the backend traces at the resolved scale and says so in the capture's renderer description
    monkeypatch.setenv("TORM_CACHE_DIR", str(tmp_path))
    c = cfg(*learned, "segmentation.options.input_width=32", "capture.renderer=pbr", "capture.n_views=1",
            "capture.scale=0.05", "capture.pbr.spp=4", "capture.pbr.denoise=none")
    backend = make_backend(c)
    try:
        cap = backend.capture(1)
        assert "render_scale 0.5" in cap.metadata["renderer"] and cap.views[0].rgb.shape == (36, 64, 3)
    finally:
        backend.close()
    # outside a trial (no segmenter to match) auto is native
    assert MitsubaRenderer(tiny_world(), PbrSettings(render_scale=0)).settings.render_scale == 1.0


def test_auto_spp_reads_the_sample_count_from_the_segmenters_card(tmp_path):
    import json
    import shutil

    from torm import config
    from torm.capture.render_settings import DEFAULT_SPP
    from torm.errors import ConfigError
    from torm.pipeline import TrialConfig, resolve_spp, trial_context
    from torm.segmentation.learned import MODELS_DIR

    def cfg(*extra: str) -> TrialConfig:
        return config.from_dict(TrialConfig, {"scenario": "rw1"}, overrides=list(extra))

    assert PbrSettings().spp == 0  # auto is the default
    assert resolve_spp(cfg("capture.pbr.spp=64")) == 64  # explicit values are kept
    assert resolve_spp(cfg()) == DEFAULT_SPP == 16  # GT masks: the default count
    learned = "segmentation.segmenter=learned"
    assert resolve_spp(cfg(learned)) == DEFAULT_SPP  # v3's card names no count
    assert resolve_spp(cfg(learned, "segmentation.options.model=v7q")) == 4  # measured on its card
    assert resolve_spp(cfg(learned, "segmentation.options.model=v7q", "method=oracle")) == DEFAULT_SPP
    # a user's model: its card decides; a card without the field (or a nonsense value) falls back to the default
    model = tmp_path / "mine.onnx"
    shutil.copy(MODELS_DIR / "learned_seg_v7q.onnx", model)
    mine = (learned, f"segmentation.options.model={model}")
    for card, want in (({"capture": {"pbr_spp": 64}}, 64), ({}, DEFAULT_SPP), ({"capture": {"pbr_spp": -3}}, 16)):
        model.with_suffix(".json").write_text(json.dumps(card))
        assert resolve_spp(cfg(*mine)) == want
    ctx = trial_context(cfg(learned, "segmentation.options.model=v7q", "capture.renderer=pbr"))
    assert ctx["render_spp"] == 4 and ctx["render_scale"] == 1.0
    with pytest.raises(ConfigError, match="auto"):
        cfg("capture.pbr.spp=-1")
    # outside a trial (no segmenter card) auto renders the default count
    assert MitsubaRenderer(tiny_world(), PbrSettings()).settings.spp == DEFAULT_SPP
