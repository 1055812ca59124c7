"""Net2WiderNet for the segmentation U-Net: a widened network computes what the narrow one computes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torm.errors import ConfigError
from torm.segmentation.training.model import SegUNet
from torm.segmentation.training.widen import copy_map, onnx_channels, widen


def _random_bn_net(channels: tuple[int, ...], centre_head: bool, in_channels: int) -> SegUNet:
    """A network in eval mode whose BatchNorms carry non-trivial statistics (so widening must copy them)."""
    torch.manual_seed(0)
    net = SegUNet(channels, centre_head, in_channels)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.normal_(0.0, 0.1)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.normal_(0.0, 0.1)
    return net.eval()


def test_copy_map_keeps_the_old_channels_first_and_draws_the_rest_from_them():
    g = copy_map(3, 8, np.random.default_rng(0))
    assert g.shape == (8,) and list(g[:3]) == [0, 1, 2] and set(g[3:]) <= {0, 1, 2}
    assert list(copy_map(4, 4, np.random.default_rng(0))) == [0, 1, 2, 3]
    with pytest.raises(ConfigError, match="new width must be >= the old"):
        copy_map(5, 4, np.random.default_rng(0))


@pytest.mark.parametrize("centre_head", [False, True])
@pytest.mark.parametrize("in_channels", [3, 6])
def test_widened_network_computes_the_same_maps(centre_head, in_channels):
    net = _random_bn_net((4, 6, 8), centre_head, in_channels)
    wide = widen(net, (7, 6, 13), np.random.default_rng(1)).eval()
    assert wide.channels == (7, 6, 13) and wide.down[0][0].weight.shape == (7, in_channels, 3, 3)
    assert wide.up[0][0].weight.shape == (6, 13 + 6, 3, 3)  # decoder block 0 reads [stage 2, skip of stage 1]
    assert sum(p.numel() for p in wide.parameters()) > sum(p.numel() for p in net.parameters())
    x = torch.rand(2, in_channels, 32, 48) * 4.0 - 2.0
    with torch.no_grad():
        ref = net(x)
        assert float(ref.std(dim=(2, 3)).min()) > 1e-3  # every output map varies: no dead network
        np.testing.assert_allclose(wide(x).numpy(), ref.numpy(), atol=1e-5 * float(ref.abs().max()))
        # noise moves the copies off their originals: close to the narrow network, no longer equal
        noisy = widen(net, (7, 12, 13), np.random.default_rng(1), noise=0.05).eval()(x)
    diff = float((noisy - ref).abs().max())
    assert 1e-6 < diff < 0.5 * float(ref.abs().max())
    # the narrow network is left as it was
    with torch.no_grad():
        np.testing.assert_array_equal(net(x).numpy(), ref.numpy())


def test_widen_refuses_another_depth_or_a_narrower_stage():
    net = SegUNet((4, 8))
    with pytest.raises(ConfigError, match="depth must stay the same"):
        widen(net, (4, 8, 16), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="new width must be >= the old"):
        widen(net, (2, 8), np.random.default_rng(0))


def test_onnx_channels_reads_the_shipped_model():
    from torm.segmentation.learned import MODELS_DIR

    assert onnx_channels(str(MODELS_DIR / "learned_seg_v4.onnx")) == (12, 24, 32, 48, 64)


def test_training_from_a_narrower_file_starts_from_its_function(tmp_path):
    """``init_from`` an exported narrower model: the run widens it; with a vanishing learning rate the trained wide
    network still computes the file's maps."""
    import onnxruntime as ort

    from torm.segmentation.training.train import TrainConfig, export_onnx, load_best, train

    rng = np.random.default_rng(0)
    masks = np.zeros((2, 48, 80), np.uint8)
    masks[:, 10:30, 12:40] = 1
    rgb = (np.where(masks[..., None] > 0, 200, 60) + rng.integers(0, 20, (*masks.shape, 3))).astype(np.uint8)
    path = export_onnx(_random_bn_net((4, 8), True, 3), tmp_path / "narrow.onnx", (32, 48))
    cfg = TrainConfig(channels=(6, 12), steps=1, batch_size=2, crop=(32, 48), centre_head=True, freeze_bn=True,
                      init_from=str(path), widen_noise=0.0, lr=1e-12, weight_decay=0.0, val_every=1,
                      checkpoint_every=1)
    train(cfg, rgb, masks, rgb, masks, tmp_path / "w", progress=False)
    wide = load_best(tmp_path / "w", cfg)
    assert wide.channels == (6, 12)
    x = rgb[:1, :32, :48].astype(np.float32).transpose(0, 3, 1, 2)
    from torm.segmentation.training.model import normalise

    with torch.no_grad():
        got = wide.eval()(normalise(torch.from_numpy(x))).numpy()
    want = ort.InferenceSession(str(path)).run(None, {"image": x})[0]
    np.testing.assert_allclose(got, want, atol=1e-4 * float(np.abs(want).max()) + 1e-5)
    with pytest.raises(ConfigError, match="new width must be >= the old"):
        train(TrainConfig(**{**cfg.to_dict(), "channels": (2, 8)}), rgb, masks, rgb, masks, tmp_path / "n",
              progress=False)
    with pytest.raises(ConfigError, match="widen_noise"):
        TrainConfig(widen_noise=-0.1)


def test_every_training_recipe_beside_the_models_parses_and_v4w_widens_v4():
    from torm import config as cfgmod
    from torm.segmentation.learned import MODELS_DIR
    from torm.segmentation.training.run import SegTrainingSpec

    recipes = sorted(MODELS_DIR.glob("*_train.yaml"))
    assert len(recipes) >= 6
    specs = {p.name: cfgmod.from_dict(SegTrainingSpec, cfgmod.load_yaml(p), [], where=str(p)) for p in recipes}
    v4w, v4f = specs["learned_seg_v4w_train.yaml"], specs["learned_seg_v4f_train.yaml"]
    # the capacity experiment: v4f's data and schedule, twice the width, from v4 widened
    assert v4w.data == v4f.data
    assert {k: v for k, v in v4w.train.to_dict().items() if k not in ("channels", "widen_noise")} == {
        k: v for k, v in v4f.train.to_dict().items() if k not in ("channels", "widen_noise")}
    assert tuple(v4w.train.channels) == tuple(2 * c for c in v4f.train.channels)
    assert onnx_channels(str(MODELS_DIR.parents[2] / v4w.train.init_from)) == tuple(v4f.train.channels)
