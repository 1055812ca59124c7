"""Reference views (issue 43): the empty workspace through the same cameras, as segmentation evidence."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from torm.errors import CaptureError
from torm.types import CameraView, Capture

K = np.array([[80.0, 0, 48], [0, 80.0, 32], [0, 0, 1]])


def _pair(seed: int = 0, shift: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scene, reference, true mask): a textured background, a bright-rimmed disc only in the scene."""
    rng = np.random.default_rng(seed)
    h, w = 64, 96
    bg = np.clip(120 + 30 * np.sin(np.arange(w) / 3.0)[None, :, None] + rng.normal(0, 2, (h, w, 3)), 0, 255)
    ref = np.roll(bg, shift, axis=(0, 1)).astype(np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (yy - 32) ** 2 + (xx - 48) ** 2 < 12**2
    scene = bg.copy()
    scene[disc] = np.clip(scene[disc] * 0.6 + 90, 0, 255)  # glass: the background bent and brightened
    return scene.astype(np.uint8), ref, disc


def test_difference_instances_find_the_object_and_ignore_identical_background():
    from torm.segmentation.reference import difference_instances

    scene, ref, disc = _pair()
    inst = difference_instances(scene, ref)
    assert inst.max() == 1
    iou = np.sum((inst > 0) & disc) / np.sum((inst > 0) | disc)
    assert iou > 0.9
    assert difference_instances(ref, ref).max() == 0


def test_smoothing_averages_out_independent_render_noise_between_the_passes():
    from torm.errors import ConfigError
    from torm.segmentation.reference import DifferenceConfig, difference_instances, difference_map

    scene, ref, disc = _pair()
    rng = np.random.default_rng(3)
    # independent noise in each pass (a path tracer's, a sensor's): sigma 8 grey levels
    noisy = [np.clip(x + rng.normal(0, 8, x.shape), 0, 255).astype(np.uint8) for x in (scene, ref)]
    raw, smooth = difference_map(*noisy), difference_map(*noisy, blur_sigma_px=1.5)
    assert np.mean(raw[~disc] > 10) > 0.5 > 0.05 > np.mean(smooth[~disc] > 10)  # background: noise no longer passes
    assert np.mean(smooth[disc] > 10) > 0.9  # the object still does
    iou = [np.sum((m > 0) & disc) / np.sum((m > 0) | disc) for m in (
        difference_instances(*noisy), difference_instances(*noisy, blur_sigma_px=1.5))]
    assert iou[1] > 0.8 and iou[0] < 0.5  # unsmoothed, the noise fills the frame
    np.testing.assert_array_equal(difference_map(ref, ref, blur_sigma_px=2.0), 0.0)
    with pytest.raises(ConfigError, match="blur_sigma_px"):
        DifferenceConfig(blur_sigma_px=-1.0)


def test_exposure_gain_is_read_off_the_static_background_not_the_objects():
    from torm.segmentation.reference import difference_map

    scene, ref, disc = _pair()
    # the reference was taken 20 % darker (another exposure); the scene holds a bright object over a quarter of it
    big = np.zeros(disc.shape, bool)
    big[:, :24] = True
    scene[big] = 250
    dark = np.round(ref.astype(np.float64) * 0.8).astype(np.uint8)
    d = difference_map(scene, dark)
    bg = ~big & ~disc
    # the gain comes from the background's median ratio: only 8-bit rounding remains there (a gain from the channel
    # means, which count the bright object, leaves 29 grey levels at the median)
    assert np.percentile(d[bg], 99) < 2.0
    assert np.mean(d[disc] > 10) > 0.9 and np.mean(d[big] > 10) > 0.9


def test_pair_noise_measures_the_independent_noise_of_the_two_passes_and_auto_smooths_only_noisy_pairs():
    from torm.errors import ConfigError
    from torm.segmentation.reference import (
        AUTO_BLUR_PX,
        DifferenceConfig,
        DifferenceSegmenter,
        pair_noise,
        resolve_blur,
    )

    scene, ref, disc = _pair()
    assert pair_noise(scene, ref) == 0.0  # a deterministic renderer: identical background, the object a minority
    rng = np.random.default_rng(5)
    base = np.full((120, 160, 3), 128.0)
    a, b = (np.clip(base + rng.normal(0, 4, base.shape), 0, 255).astype(np.uint8) for _ in range(2))
    # sigma 4 in each pass: the difference's sigma is 4 x sqrt(2) = 5.66 (integer rounding adds 1/12 per pass)
    assert abs(pair_noise(a, b) - 4 * np.sqrt(2)) < 0.4
    assert resolve_blur(scene, ref, "auto") == 0.0 and resolve_blur(a, b, "auto") == AUTO_BLUR_PX
    assert resolve_blur(a, b, 0.7) == 0.7
    assert DifferenceConfig().blur_sigma_px == "auto"
    cap = Capture(views=(CameraView(K, np.eye(4), rgb=scene, reference_rgb=ref),))
    assert DifferenceSegmenter().segment(cap).info["blur_sigma_px_used"] == [0.0]
    with pytest.raises(ConfigError, match="'auto' or a number"):
        DifferenceConfig(blur_sigma_px="fast")  # type: ignore[arg-type]


def test_attach_reference_pairs_views_by_pose_and_refuses_a_moved_camera_or_another_renderer():
    from torm.segmentation.reference import attach_reference

    scene, ref, _ = _pair()
    T = np.eye(4)
    cap = Capture(views=(CameraView(K, T, rgb=scene, name="a"),), metadata={"renderer": "pbr mitsuba llvm_ad_rgb"})
    good = Capture(views=(CameraView(K, T, rgb=ref),), metadata={"renderer": "pbr mitsuba llvm_ad_rgb"})
    out = attach_reference(cap, good)
    assert np.array_equal(out.views[0].reference_rgb, ref) and out.metadata["reference"]["renderer"]
    T_far = T.copy()
    T_far[0, 3] = 0.01  # 10 mm
    with pytest.raises(CaptureError, match="10.0 mm.*same path"):
        attach_reference(cap, replace(good, views=(CameraView(K, T_far, rgb=ref),)))
    with pytest.raises(CaptureError, match="same camera or renderer"):
        attach_reference(cap, replace(good, metadata={"renderer": "mujoco 3.17 offscreen"}))
    with pytest.raises(CaptureError, match="same camera settings"):
        attach_reference(cap, replace(good, views=(CameraView(K, T, rgb=ref[:32]),)))


def test_background_check_refuses_a_reference_after_the_table_moved():
    from torm.segmentation.reference import BACKGROUND_MAX_GREY, check_background

    scene, ref, disc = _pair()
    cap = Capture(views=(CameraView(K, np.eye(4), rgb=scene, reference_rgb=ref),))
    masks = disc[None].astype(np.int32)
    assert check_background(cap, masks) < BACKGROUND_MAX_GREY  # passes: only the object changed
    moved = np.roll(ref, 9, axis=1)  # the table moved (and its texture with it)
    stale = Capture(views=(CameraView(K, np.eye(4), rgb=scene, reference_rgb=moved),))
    with pytest.raises(CaptureError, match="record a new reference pass"):
        check_background(stale, masks)
    # a segmenter that reads the stale reference marks the whole table: the check then reads the whole view
    # instead of finding nothing left to check
    everything = np.ones_like(masks)
    with pytest.raises(CaptureError, match="record a new reference pass"):
        check_background(stale, everything)
    assert check_background(cap, everything) < BACKGROUND_MAX_GREY  # a valid reference: the object is a minority


def test_reference_views_survive_a_save_and_load_and_must_match_the_view_size(tmp_path):
    from torm.capture.io import load_capture, save_capture

    scene, ref, _ = _pair()
    cap = Capture(views=(CameraView(K, np.eye(4), rgb=scene, reference_rgb=ref),))
    back = load_capture(save_capture(cap, tmp_path / "c").parent)
    assert np.array_equal(back.views[0].reference_rgb, ref)
    with pytest.raises(CaptureError, match="reference_rgb has size"):
        CameraView(K, np.eye(4), rgb=scene, reference_rgb=ref[:10])


def test_the_simulated_reference_pass_hides_the_objects_and_only_them():
    from sim.cameras.rig import CameraRigConfig, SimCameraRig
    from sim.world import build_world
    from torm.runtime import ensure_headless_gl

    ensure_headless_gl()
    world = build_world("rw3", 0, robot=None)
    with SimCameraRig.from_world(world, CameraRigConfig(n_views=2, scale=0.2)) as rig:
        cap = rig.capture(reference=True)
    groups_after = world.model.geom_group.copy()
    for v in cap.views:
        diff = np.abs(v.rgb.astype(int) - v.reference_rgb.astype(int)).max(axis=2) > 0
        obj = v.mask > 0
        assert diff[obj].mean() > 0.5  # the objects are gone from the reference
        assert diff[~obj].mean() < 0.05  # the rest is the same (shadows and reflections aside)
    assert cap.metadata["reference"].startswith("simulated reference pass")
    with SimCameraRig.from_world(world, CameraRigConfig(n_views=1, scale=0.2)) as rig:
        assert np.array_equal(world.model.geom_group, groups_after)  # restored after the pass
        assert rig.capture().views[0].reference_rgb is None


def test_a_reference_mode_network_starts_as_the_rgb_model_and_needs_reference_views(tmp_path):
    import json
    import shutil

    import torch

    from torm.segmentation.learned import DEFAULT_MODEL, LearnedConfig, LearnedSegmenter
    from torm.segmentation.training.model import SegUNet, load_onnx_weights
    from torm.segmentation.training.train import export_onnx

    net = SegUNet((12, 24, 32, 48, 64), True, in_channels=6)
    load_onnx_weights(net, DEFAULT_MODEL)
    net.eval()
    path = export_onnx(net, tmp_path / "ref.onnx")
    card = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    (tmp_path / "ref.json").write_text(json.dumps(card))
    seg6 = LearnedSegmenter(LearnedConfig(model=str(path), threads=1))
    seg3 = LearnedSegmenter(LearnedConfig(threads=1))
    assert seg6.needs_reference and not seg3.needs_reference
    scene, ref, _ = _pair()
    a = seg6.maps(scene, reference=ref)
    b = seg3.maps(scene)
    assert np.abs(a[:3] - b[:3]).max() < 1e-3  # the reference half of the first convolution starts at zero
    with pytest.raises(CaptureError, match="reference-mode model"):
        seg6.maps(scene)
    shutil.rmtree(tmp_path, ignore_errors=True)
    del torch


def test_reference_batches_carry_six_channels_and_a_misregistered_reference():
    from torm.segmentation.training.targets import targets
    from torm.segmentation.training.train import Batcher, TrainConfig, jitter

    scene, ref, disc = _pair()
    rgb = np.stack([scene, scene])
    refs = np.stack([ref, ref])
    mask = np.stack([disc, disc]).astype(np.uint8)
    cfg = TrainConfig(crop=(48, 64), batch_size=3, reference=True, sensor_effects=1.0, zoom_range=(1.0, 1.5))
    x, y = Batcher(rgb, targets(mask), cfg, np.random.default_rng(0), None, refs).sample()
    assert x.shape == (3, 6, 48, 64) and y.shape == (3, 2, 48, 64)
    moved = jitter(ref.astype(np.float32), 1.0, np.random.default_rng(1))
    assert moved.shape == ref.shape and 0 < np.abs(moved - ref).mean() < 20
    with pytest.raises(Exception, match="reference passes"):
        Batcher(rgb, targets(mask), cfg, np.random.default_rng(0), None, None)
