"""The learned segmenter's centre head: targets, grouping by centre votes, training and export plumbing."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from torm.errors import ModelFileError
from torm.segmentation.instances import centre_peaks, group_by_centres, instances_from_maps
from torm.segmentation.learned import LearnedConfig, LearnedSegmenter
from torm.segmentation.training.targets import centre_targets


def _two_squares(h: int = 60, w: int = 90) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    m[10:40, 10:40] = 1
    m[10:40, 40:70] = 2  # touching the first: no background between them
    return m


def _maps(mask: np.ndarray, boundary: bool = False) -> np.ndarray:
    """Perfect (5, H, W) maps of a mask: foreground, boundary (none unless asked), centre heat, offsets."""
    from torm.segmentation.training.targets import boundary_band

    heat, off = centre_targets(mask, 4.0)
    fg = (mask > 0).astype(np.float32)
    bd = boundary_band(mask, 2).astype(np.float32) if boundary else np.zeros_like(fg)
    return np.stack([fg, bd, heat, off[0], off[1]])


def test_centre_targets_point_every_pixel_at_its_instance_mean():
    m = _two_squares()
    heat, off = centre_targets(m, 4.0)
    yy, xx = np.mgrid[0:m.shape[0], 0:m.shape[1]]
    for k, centre in ((1, (24.5, 24.5)), (2, (24.5, 54.5))):
        sel = m == k
        np.testing.assert_allclose(yy[sel] + off[0][sel], centre[0], atol=1e-4)
        np.testing.assert_allclose(xx[sel] + off[1][sel], centre[1], atol=1e-4)
    assert np.all(off[:, m == 0] == 0)
    # the heatmap: exp(-d^2 / 2 sigma^2) of the nearest centre, 1 only at a centre (here between pixels)
    assert 0.95 < heat.max() <= 1.0 and heat.min() >= 0.0
    assert heat[24, 24] == pytest.approx(np.exp(-0.5 / 32), rel=1e-5)
    np.testing.assert_array_equal(centre_peaks(heat, 0.3, 3)[:, 1] // 30, [0, 1])  # one peak per square
    empty_heat, empty_off = centre_targets(np.zeros((8, 8), np.uint8))
    assert not empty_heat.any() and not empty_off.any()
    with pytest.raises(ValueError, match="sigma_px"):
        centre_targets(m, 0.0)


def test_touching_objects_without_a_boundary_split_by_centre_votes_only():
    m = _two_squares()
    maps = _maps(m)
    for grouping in ("centre", "hybrid"):
        inst, scores = instances_from_maps(maps, grouping)
        assert len(scores) == 2, grouping
        for k in (1, 2):  # each square is exactly one instance
            assert len(np.unique(inst[m == k])) == 1
        assert inst[m == 1][0] != inst[m == 2][0]
        assert np.array_equal(inst > 0, m > 0)
    inst, _ = instances_from_maps(maps, "boundary")  # no boundary predicted: one merged instance
    assert inst.max() == 1


def test_an_occluded_object_in_two_pieces_stays_one_instance():
    m = np.zeros((50, 100), np.uint8)
    m[10:40, 10:40] = 1
    m[10:40, 60:90] = 1  # the same object, seen on both sides of a gap
    maps = _maps(m)
    inst, scores = instances_from_maps(maps, "centre")
    assert len(scores) == 2  # centre grouping is per foreground component: the pieces are not connected
    # hybrid on one region holding both pieces: one strong centre, so it is not split
    inst, scores = group_by_centres(maps[0], maps[2], maps[3:5], regions_hxw=(m > 0).astype(np.int32))
    assert len(scores) == 1


def test_grouping_without_centres_and_empty_maps():
    m = _two_squares()
    maps = _maps(m)
    maps[2] = 0.0  # no centre peak: each foreground component is one instance
    inst, scores = instances_from_maps(maps, "centre")
    assert len(scores) == 1 and np.array_equal(inst > 0, m > 0)
    inst, scores = instances_from_maps(np.zeros((5, 20, 30), np.float32))
    assert not inst.any() and scores == []
    with pytest.raises(ValueError, match="valid choices"):
        instances_from_maps(maps, "watershed")
    with pytest.raises(ValueError, match="centre head"):
        instances_from_maps(maps[:2], "centre")
    with pytest.raises(ValueError, match=r"\(2, H, W\) or \(5, H, W\)"):
        instances_from_maps(maps[:3])
    with pytest.raises(ValueError, match="offsets"):
        group_by_centres(maps[0], maps[2], maps[3:4])


def test_batches_keep_offsets_pointing_at_the_centre_through_crops_and_flips():
    from torm.segmentation.training.targets import targets
    from torm.segmentation.training.train import Batcher, TrainConfig

    m = _two_squares(64, 96)[None]
    heat, off = centre_targets(m[0], 4.0)
    centre = np.concatenate([heat[None], off])[None].astype(np.float16)
    rgb = np.zeros((1, 64, 96, 3), np.uint8)
    cfg = TrainConfig(channels=(4, 8), batch_size=16, crop=(48, 64))
    b = Batcher(rgb, targets(m), cfg, np.random.default_rng(0), centre)
    _, y = b.sample()
    assert y.shape == (16, 5, 48, 64)
    yy, xx = np.mgrid[0:48, 0:64]
    for t in y.numpy():
        fg = t[0] > 0.5
        vy, vx = yy[fg] + t[3][fg], xx[fg] + t[4][fg]
        # every pixel of a square votes for the same point, after crop and (possibly) mirroring
        for sq in (vx < vx.mean(), vx >= vx.mean()):
            if sq.any():
                assert np.ptp(vy[sq]) < 0.05 and np.ptp(vx[sq]) < 0.05


def test_centre_head_trains_exports_and_segments(tmp_path):
    import torch

    from torm.segmentation.training.model import SegUNet, load_onnx_weights, normalise
    from torm.segmentation.training.train import TrainConfig, export_onnx, load_best, predict, train

    rng = np.random.default_rng(0)
    masks = np.stack([_two_squares(48, 80), _two_squares(48, 80)[:, ::-1]]).astype(np.uint8)
    rgb = (np.where(masks[..., None] > 0, 200, 60) + rng.integers(0, 20, (*masks.shape, 3))).astype(np.uint8)
    cfg = TrainConfig(channels=(4, 8), steps=2, batch_size=2, crop=(32, 48), val_every=1, checkpoint_every=1,
                      centre_head=True, select_on="object_iou")
    summary = train(cfg, rgb, masks, rgb, masks, tmp_path / "a", progress=False)
    assert "best_val_object_iou" in summary and {"centre_mse", "offset_l1", "val_object_iou"} <= set(
        summary["history"][-1])
    net = load_best(tmp_path / "a", cfg)
    path = export_onnx(net, tmp_path / "c.onnx", (32, 48))
    seg = LearnedSegmenter(LearnedConfig(model=str(path), input_width=0, threads=1))
    assert seg.channels == 5 and seg.postprocess["grouping"] == "centre"
    maps = seg.maps(rgb[0], flip_tta=False)
    ref = predict(net, rgb[:1])[0]  # torch and onnxruntime agree, offsets in px
    np.testing.assert_allclose(maps, ref, atol=1e-3)
    mask, dets = seg.segment_image(rgb[0])
    assert mask.shape == masks[0].shape and len(dets) == mask.max()
    # the exported file's (BatchNorm-folded) weights load back into a network computing the same maps
    back = load_onnx_weights(SegUNet((4, 8), centre_head=True), path).eval()
    x = torch.from_numpy(rgb[:1].astype(np.float32)).permute(0, 3, 1, 2)[:, :, :32, :48]
    with torch.no_grad():
        np.testing.assert_allclose(back(normalise(x)).numpy(),
                                   ort.InferenceSession(str(path)).run(None, {"image": x.numpy()})[0], atol=1e-4)
    # fine-tuning from an exported file needs frozen BatchNorms; a file of another network is refused
    from torm.errors import ConfigError

    ft = TrainConfig(channels=(4, 8), steps=1, batch_size=2, crop=(32, 48), centre_head=True, init_from=str(path))
    with pytest.raises(ConfigError, match="freeze_bn"):
        train(ft, rgb, masks, rgb, masks, tmp_path / "b", progress=False)
    ft = TrainConfig(**{**ft.to_dict(), "freeze_bn": True})
    assert train(ft, rgb, masks, rgb, masks, tmp_path / "b", progress=False)["steps"] == 1
    with pytest.raises(ModelFileError, match="do not match"):
        load_onnx_weights(SegUNet((4, 16), centre_head=True), path)
    onnx.checker.check_model(onnx.load(str(path)))


def test_flip_tta_negates_the_mirrored_x_offset(tmp_path):
    import torch

    from torm.segmentation.training.model import SegUNet
    from torm.segmentation.training.train import export_onnx

    torch.manual_seed(0)
    path = export_onnx(SegUNet((4, 8), centre_head=True), tmp_path / "r.onnx", (32, 48))
    seg = LearnedSegmenter(LearnedConfig(model=str(path), input_width=0))
    rgb = np.random.default_rng(2).integers(0, 256, (32, 48, 3), dtype=np.uint8)
    mirror = np.ascontiguousarray(rgb[:, ::-1])
    a, b = seg.maps(rgb, flip_tta=True), seg.maps(mirror, flip_tta=True)
    np.testing.assert_allclose(a[:4], b[:4, :, ::-1], atol=1e-5)
    np.testing.assert_allclose(a[4], -b[4, :, ::-1], atol=1e-5)  # x offsets change sign in the mirror image


def test_inference_and_training_agree_on_the_offset_unit():
    from torm.segmentation import learned
    from torm.segmentation.training import model

    assert learned.OFFSET_SCALE == model.OFFSET_SCALE
