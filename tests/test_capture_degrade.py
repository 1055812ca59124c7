"""Capture degradations (issue 38): a pose error of a chosen reprojection size, a lens that the loader undoes, and
hand-drawn masks whose error grows with the hand's."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from torm.capture.degrade import distort_image, hand_drawn_mask, perturb_poses, reprojection_rms_px
from torm.capture.lens import Lens, undistort
from torm.errors import CaptureError
from torm.geometry import look_at_cv

K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])


def _poses(n: int = 4) -> np.ndarray:
    return np.stack([look_at_cv(np.array([0.4 * np.cos(a), 0.4 * np.sin(a), 0.3]), np.zeros(3))
                     for a in np.linspace(0, 2 * np.pi, n, endpoint=False)])


def test_perturbed_poses_move_the_points_by_the_requested_reprojection_error():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.05, 0.05, (500, 3))
    target = np.array([0.3, 0.6, 1.0, 0.0])
    poses = _poses()
    out, errs = perturb_poses(poses, np.repeat(K[None], 4, 0), pts, target, rng)
    for T0, T1, e, r in zip(poses, out, errs, target, strict=True):
        got = reprojection_rms_px(pts, K, T0, T1)
        assert got == pytest.approx(r, rel=0.02, abs=1e-9) and e.reprojection_rms_px == pytest.approx(got)
        assert np.allclose(T1[:3, :3] @ T1[:3, :3].T, np.eye(3), atol=1e-9)  # still a rotation
    assert 0.2 / 800 < errs[2].rotation_rad < 4 / 800 and 0.2 * 0.4 / 800 < errs[2].translation_m < 4 * 0.4 / 800
    assert np.array_equal(out[3], poses[3])
    with pytest.raises(CaptureError, match="one K per pose"):
        perturb_poses(poses, K[None], pts, target, rng)


def test_a_distorted_mask_comes_back_through_the_loaders_undistortion():
    lens = Lens("SIMPLE_RADIAL", (("k1", 0.0325),))
    m = np.zeros((480, 640), np.uint8)
    cv2.circle(m, (520, 400), 60, 255, -1)  # near a corner, where the lens moves pixels most
    d = distort_image(m, K, lens, nearest=True)
    back = undistort(d, lens.undistort_maps(K, 640, 480), nearest=True)
    iou = ((back > 0) & (m > 0)).sum() / ((back > 0) | (m > 0)).sum()
    moved = ((d > 0) & (m > 0)).sum() / ((d > 0) | (m > 0)).sum()
    assert iou > 0.98 and moved < iou


def test_hand_drawn_masks_are_soft_keep_holes_and_err_more_with_a_shakier_hand():
    m = np.zeros((400, 400), np.uint8)
    cv2.circle(m, (200, 200), 80, 1, -1)
    m[180:220, 180:220] = 0  # a hole
    rng = np.random.default_rng(0)

    def iou(s):
        b = s >= 0.5
        return (b & (m > 0)).sum() / (b | (m > 0)).sum()

    exact = hand_drawn_mask(m, rng, 0.0, 0.0)
    assert exact[(exact > 0) & (exact < 1)].size > 0  # anti-aliased edges
    assert iou(exact) > 0.985 and exact[200, 200] == 0  # the hole stays a hole
    shaky = [iou(hand_drawn_mask(m, rng, s, s / 2)) for s in (1.0, 4.0, 8.0)]
    assert shaky[0] > shaky[1] > shaky[2] > 0.8
    assert hand_drawn_mask(np.zeros((10, 10)), rng).max() == 0
    with pytest.raises(CaptureError, match=">= 0 px"):
        hand_drawn_mask(m, rng, -1.0)
