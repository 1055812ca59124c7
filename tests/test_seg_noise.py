"""Mask error model, ground-truth segmenter and mask-quality helpers on synthetic captures."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from torm.errors import CaptureError, ConfigError, UnknownNameError
from torm.metrics import silhouette_iou
from torm.segmentation import make_segmenter, mask_quality
from torm.segmentation.noise import PRESET_EXPECTED_IOU, PRESETS, MaskCorruptor, NoiseConfig, noise_preset
from torm.segmentation.sphere_capture import sphere_capture
from torm.types import CameraView, Capture


@pytest.fixture(scope="module")
def cap():
    return sphere_capture(n_views=50, size_px=256, seed=0)


def _disc(hw, center, r, value=1, out=None):
    m = np.zeros(hw, np.int32) if out is None else out
    cv2.circle(m, center, r, int(value), thickness=-1)
    return m


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_each_preset_gives_its_stated_iou(cap, preset):
    lo, hi = PRESET_EXPECTED_IOU[preset]
    for seed in (0, 5):
        q = make_segmenter("noisy", {"preset": preset, "seed": seed}).segment(cap).info["quality"]
        assert lo - 1e-9 <= q["silhouette_iou_mean"] <= hi + 1e-9, (preset, seed, q["silhouette_iou_mean"])
        assert q["silhouette_iou_min"] <= q["silhouette_iou_mean"]


def test_presets_are_ordered_by_severity(cap):
    iou = {p: make_segmenter("noisy", {"preset": p, "seed": 1}).segment(cap).info["quality"]["silhouette_iou_mean"]
           for p in ("none", "mild", "moderate", "paper", "severe")}
    assert iou["none"] == 1.0 > iou["mild"] > iou["moderate"] > iou["paper"] > iou["severe"]


def test_same_seed_same_corruption_and_the_paper_fractions(cap):
    a = make_segmenter("noisy", {"preset": "moderate", "seed": 3}).segment(cap)
    b = make_segmenter("noisy", {"preset": "moderate", "seed": 3}).segment(cap)
    c = make_segmenter("noisy", {"preset": "moderate", "seed": 4}).segment(cap)
    np.testing.assert_array_equal(a.masks_vxhxw, b.masks_vxhxw)
    assert not np.array_equal(a.masks_vxhxw, c.masks_vxhxw)
    ev = make_segmenter("noisy", {"preset": "paper", "seed": 0}).segment(cap).info["events"]
    assert sum("missing" in e for e in ev) == 5  # 10 % of 50 views
    assert sum("spurious" in e for e in ev) == 3  # 6 % of 50 views
    assert all(abs(o) >= 1.0 and abs(o) <= 3.0 for e in ev for o in e["offset_px"].values())


def test_erosion_and_dilation_move_the_boundary_by_the_radius():
    gt = _disc((120, 120), (60, 60), 30)[None]
    area = np.count_nonzero(gt)
    for p_dilate, r_exp in ((0.0, 27.0), (1.0, 33.0)):
        out, _ = MaskCorruptor(NoiseConfig(boundary_radius_px=(3.0, 3.0), p_dilate=p_dilate), 0).corrupt(gt)
        r_eq = np.sqrt(np.count_nonzero(out) / np.pi)
        assert abs(r_eq - r_exp) < 0.6, (p_dilate, r_eq)
    out, _ = MaskCorruptor(NoiseConfig(), 0).corrupt(gt)
    assert np.count_nonzero(out) == area  # no-op config is the identity


def test_jagged_boundaries_only_touch_pixels_near_edges():
    gt = _disc((160, 160), (80, 80), 40)[None]
    cfg = NoiseConfig(jagged_amplitude_px=1.5, jagged_scale_px=3.0, p_jagged_view=1.0)
    out, _ = MaskCorruptor(cfg, 7).corrupt(gt)
    changed = out[0] != gt[0]
    assert changed.any()
    yy, xx = np.mgrid[:160, :160]
    dist_to_edge = np.abs(np.hypot(xx + 0.5 - 80.5, yy + 0.5 - 80.5) - 40)
    assert dist_to_edge[changed].max() < 1.5 * 6  # < 6 sigma of the boundary displacement
    assert 0.85 < silhouette_iou(out[0], gt[0])["mean"] < 1.0


def test_missing_spurious_and_merged_objects():
    hw = (100, 160)
    m = _disc(hw, (50, 50), 15, 1)
    _disc(hw, (84, 50), 15, 2, out=m)  # 4 px gap between the two discs
    _disc(hw, (135, 50), 10, 3, out=m)  # 26 px gap to disc 2: too far to merge
    gt = np.stack([m] * 4)
    out, ev = MaskCorruptor(NoiseConfig(p_missing_view=1.0), 0).corrupt(gt)
    for v in range(4):
        assert len(np.unique(out[v])) == 3 and ev[v]["missing"] not in np.unique(out[v])
    out, ev = MaskCorruptor(NoiseConfig(p_spurious_view=1.0, spurious_size_range=(1.0, 1.0)), 0).corrupt(gt)
    for v in range(4):
        blob = out[v] == 4
        r_med = np.sqrt(np.median([np.count_nonzero(m == k) for k in (1, 2, 3)]) / np.pi)
        assert 0.4 * np.pi * r_med**2 <= np.count_nonzero(blob) <= 1.1 * np.pi * r_med**2  # b in [0.5, 1] a
    out, ev = MaskCorruptor(NoiseConfig(p_merge_view=1.0, merge_max_gap_px=6.0), 0).corrupt(gt)
    assert ev[0]["merged"] == [1, 2]
    assert set(np.unique(out[0])) == {0, 1, 3}
    assert out[0][50, 67] == 1  # the gap between the discs is bridged
    assert np.count_nonzero(out[0] == 3) == np.count_nonzero(m == 3)


def test_gt_segmenter_and_errors():
    cap = sphere_capture(n_views=3, size_px=64, seed=1)
    res = make_segmenter("gt").segment(cap)
    np.testing.assert_array_equal(res.masks_vxhxw, cap.masks())
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    no_mask = Capture(views=(CameraView(K=K, T_world_cam=np.eye(4), rgb=np.zeros((64, 64, 3), np.uint8), name="x"),))
    with pytest.raises(CaptureError, match="'x'"):
        make_segmenter("gt").segment(no_mask)
    with pytest.raises(CaptureError, match="'x'"):
        make_segmenter("noisy").segment(no_mask)
    with pytest.raises(UnknownNameError, match="grounded_sam, gt, learned, noisy"):
        make_segmenter("magic")
    with pytest.raises(UnknownNameError, match="paper"):
        noise_preset("awful")
    with pytest.raises(ConfigError, match="valid presets"):
        make_segmenter("noisy", {"preset": "awful"})
    with pytest.raises(ConfigError, match="p_missing"):
        make_segmenter("noisy", {"overrides": {"p_missing": 0.3}})
    with pytest.raises(ConfigError, match="p_missing_view"):
        make_segmenter("noisy", {"overrides": {"p_missing_view": 1.5}})
    seg = make_segmenter("noisy", {"preset": "none", "overrides": {"p_missing_view": 1.0}})
    assert seg.segment(cap).info["quality"]["missed_fraction"] > 0.2


def test_mask_quality_numbers():
    gt = np.zeros((1, 10, 10), np.int32)
    gt[0, :, :5] = 1
    pred = np.zeros_like(gt)
    pred[0, :, :4] = 7  # ids need not match
    pred[0, 0, 9] = 8  # one spurious pixel
    q = mask_quality(pred, gt)
    assert q["silhouette_iou_mean"] == pytest.approx(40 / 51)
    assert q["object_iou_mean"] == pytest.approx(40 / 50)
    assert q["spurious_fraction"] == pytest.approx(0.5)
    assert q["missed_fraction"] == 0.0
