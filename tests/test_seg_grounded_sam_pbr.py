"""Grounding DINO + SAM plumbing on a PBR-like frame (640x360, textured table, a refracting glass disc with a
Fresnel rim, render noise) with the tiny ONNX models of test_seg_grounded_sam: boxes and masks land on the
right pixels at the capture's size, whatever the image content."""

from __future__ import annotations

import numpy as np
from test_seg_grounded_sam import _models, build_gdino

from torm.segmentation import make_segmenter
from torm.segmentation.grounded_sam import gdino_resize_hw
from torm.types import CameraView, Capture

H, W = 360, 640


def pbr_like_frame(seed: int = 0) -> np.ndarray:
    """(H, W, 3) uint8: a wood-toned checker table, a disc that magnifies and shifts what lies behind it
    (refraction), a bright Fresnel rim, a specular highlight and Monte Carlo-like noise, tone-mapped."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W].astype(np.float64)

    def table(y, x):
        chk = ((np.floor(y / 23) + np.floor(x / 23)) % 2)[..., None]
        return np.where(chk > 0, [0.62, 0.52, 0.40], [0.50, 0.41, 0.31]) * (0.7 + 0.3 * np.sin(x / 7.0)[..., None])

    img = table(yy, xx)
    cy, cx, r = 180.0, 160.0, 45.0
    d = np.hypot(yy - cy, xx - cx)
    inside = d < r
    k = 0.6  # refraction: sample the background closer to the centre (a magnified, flipped-in view)
    ry, rx = cy + (yy - cy) * k + 6.0, cx + (xx - cx) * k
    img[inside] = table(ry, rx)[inside] * 0.92
    rim = inside & (d > r - 4)
    img[rim] = 0.95
    img += 0.8 * np.exp(-((yy - 160) ** 2 + (xx - 150) ** 2) / 20.0)[..., None]
    img = np.maximum(img + rng.normal(0, 0.03, img.shape), 0.0)
    img = img / (1 + img)  # Reinhard tone map of the linear radiance
    return np.clip(255 * img ** (1 / 2.2), 0, 255).astype(np.uint8)


def test_grounded_sam_on_a_pbr_like_frame(tmp_path):
    cfg = _models(tmp_path)
    # the image-dependent check term is for the grey test image; this frame uses the model without it
    cfg["gdino_model"] = str(build_gdino(tmp_path / "gdino_pbr.onnx", None, 36.0, gdino_resize_hw(H, W), 0.0,
                                         check=False))
    K = np.array([[311.7, 0, W / 2], [0, 311.7, H / 2], [0, 0, 1]])
    rgb = pbr_like_frame()
    assert rgb.std() > 10  # a textured frame, not the flat grey of the other tests
    cap = Capture(views=(CameraView(K=K, T_world_cam=np.eye(4), rgb=rgb, name="pbr0"),))
    res = make_segmenter("grounded_sam", cfg).segment(cap)
    dets = res.detections[0]
    assert [d.label for d in dets] == ["clear glass", "transparent object"]
    np.testing.assert_allclose(dets[0].box_xyxy, [120, 135, 200, 225], atol=1e-3)  # normalised boxes x (W, H)
    np.testing.assert_allclose(dets[1].box_xyxy, [400, 90, 520, 180], atol=1e-3)
    m = res.masks_vxhxw[0]
    assert m.shape == (H, W)
    expect1 = np.zeros((H, W), bool)
    expect1[135:225, 120:200] = True
    expect2 = np.zeros((H, W), bool)
    expect2[90:180, 400:520] = True
    np.testing.assert_array_equal(m == 1, expect1)
    np.testing.assert_array_equal(m == 2, expect2)
