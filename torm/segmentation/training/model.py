"""A small U-Net (torch): RGB in, per-pixel maps out: object foreground and instance boundary band (logits),
optionally an instance-centre heatmap (logit) and the offset to the instance's centre (2 channels, px / OFFSET_SCALE).

Encoder: ``len(channels)`` stages of two 3x3 conv + BatchNorm + ReLU, max-pool 2 between stages; decoder:
bilinear x2 upsampling, concatenation with the encoder stage of the same size, two 3x3 convs. Input height
and width must be multiples of ``2 ** (len(channels) - 1)`` (16 for the default). The exported wrapper
(:class:`ExportWrapper`) takes (1, 3, H, W) float32 RGB in [0, 255] and normalises inside the graph; a
reference-mode network (``in_channels`` 6) takes the scene's RGB then the empty workspace's RGB of the same view,
(1, 6, H, W).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

#: per-channel RGB mean / std (of [0, 1] values) the network is normalised with (ImageNet statistics)
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)
OUTPUTS = ("foreground", "boundary")
#: the outputs with the centre head (Panoptic-DeepLab-style grouping): channels 2-4
OUTPUTS_CENTRE = (*OUTPUTS, "centre", "offset_y", "offset_x")
#: offsets are predicted in units of this many pixels (of the network input): y_px = OFFSET_SCALE * output
OFFSET_SCALE = 10.0


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )


class SegUNet(nn.Module):
    """U-Net with ``channels`` per stage; forward (B, 3, H, W) normalised RGB -> (B, C, H, W) maps.

    ``centre_head`` False: C = 2 (:data:`OUTPUTS`); True: C = 5 (:data:`OUTPUTS_CENTRE`). The heads are one 1x1
    convolution on the last decoder stage.
    """

    def __init__(self, channels: tuple[int, ...] = (12, 24, 32, 48, 64), centre_head: bool = False,
                 in_channels: int = 3) -> None:
        super().__init__()
        if in_channels not in (3, 6):
            raise ValueError(f"in_channels = {in_channels}; valid: 3 (RGB) or 6 (RGB + reference RGB)")
        self.channels = tuple(channels)
        self.in_channels = int(in_channels)
        self.down = nn.ModuleList()
        cin = in_channels
        for c in channels:
            self.down.append(_block(cin, c))
            cin = c
        self.up = nn.ModuleList()
        for c_skip in reversed(channels[:-1]):
            self.up.append(_block(cin + c_skip, c_skip))
            cin = c_skip
        self.head = nn.Conv2d(cin, len(OUTPUTS_CENTRE if centre_head else OUTPUTS), 1)

    @property
    def stride(self) -> int:
        """Input sizes must be multiples of this."""
        return 2 ** (len(self.channels) - 1)

    def forward(self, x_bx3xhxw: torch.Tensor) -> torch.Tensor:
        skips = []
        x = x_bx3xhxw
        for i, blk in enumerate(self.down):
            x = blk(x)
            if i < len(self.down) - 1:
                skips.append(x)
                x = F.max_pool2d(x, 2)
        for blk, s in zip(self.up, reversed(skips), strict=True):
            x = F.interpolate(x, size=s.shape[-2:], mode="bilinear", align_corners=False)
            x = blk(torch.cat([x, s], dim=1))
        return self.head(x)


_MEAN_1x3x1x1 = torch.tensor(RGB_MEAN).view(1, 3, 1, 1) * 255.0
_STD_1x3x1x1 = torch.tensor(RGB_STD).view(1, 3, 1, 1) * 255.0


def normalise(rgb255_bxcxhxw: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 255] (float32; C = 3, or 6 = two RGB images) -> ImageNet-normalised input."""
    k = rgb255_bxcxhxw.shape[1] // 3
    return (rgb255_bxcxhxw - _MEAN_1x3x1x1.repeat(1, k, 1, 1)) / _STD_1x3x1x1.repeat(1, k, 1, 1)


class ExportWrapper(nn.Module):
    """What the ONNX file holds: ``image`` (1, 3 or 6, H, W) RGB in [0, 255] -> ``logits`` (1, C, H, W), C = 2 or
    5."""

    def __init__(self, net: SegUNet) -> None:
        super().__init__()
        self.net = net
        k = getattr(net, "in_channels", 3) // 3
        self.register_buffer("mean", _MEAN_1x3x1x1.repeat(1, k, 1, 1).clone())
        self.register_buffer("std", _STD_1x3x1x1.repeat(1, k, 1, 1).clone())

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.net((image - self.mean) / self.std)


def load_onnx_weights(net: SegUNet, path: str | Path) -> SegUNet:
    """Load an exported model's weights into ``net`` (same ``channels``); returns ``net``.

    The exporter folds each BatchNorm into its convolution, so the file's Conv nodes carry one (weight, bias)
    per 3x3 convolution, in the graph's order (the module order), plus the head. They go into ``net``'s
    convolutions, and every BatchNorm becomes the identity plus the folded bias (mean 0, variance 1 - eps,
    scale 1): ``net`` in eval mode computes what the file computes. Fine-tune such a network with its
    BatchNorms kept in eval mode (``TrainConfig.freeze_bn``). A file with a 2-channel head loaded into a
    centre-head network fills the first two head channels; the centre channels keep their initialisation. An RGB
    file loaded into a reference-mode network (6 input channels) fills the RGB half of the first convolution and
    zeroes the reference half: the network starts out computing exactly what the file computes.
    """
    import onnx
    from onnx import numpy_helper

    from torm.errors import ModelFileError

    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path} does not exist; point train.init_from at an exported learned_seg .onnx file")
    graph = onnx.load(str(path)).graph
    inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d) and m is not net.head]
    bns = [m for m in net.modules() if isinstance(m, nn.BatchNorm2d)]
    # (weight, bias) of every Conv node but the head's, in graph order
    folded = [(inits[n.input[1]], inits[n.input[2]]) for n in graph.node if n.op_type == "Conv"
              and n.input[1] != "net.head.weight" and len(n.input) == 3]
    def fits(w: np.ndarray, conv: nn.Conv2d) -> bool:
        t = tuple(conv.weight.shape)
        return w.shape == t or (conv is convs[0] and w.shape[1] == 3 and t[1] == 6 and w.shape[0] == t[0])

    if len(folded) != len(convs) or not all(fits(w, c) for (w, _), c in zip(folded, convs, strict=False)):
        raise ModelFileError(f"{path}: its convolutions {[w.shape for w, _ in folded]} do not match a "
                             f"SegUNet with channels {net.channels}; train.channels must be the file's")
    with torch.no_grad():
        for (w, b), conv, bn in zip(folded, convs, bns, strict=True):
            w = np.array(w)
            if w.shape[1] != conv.weight.shape[1]:  # RGB weights into a reference-mode first convolution
                w = np.concatenate([w, np.zeros_like(w)], axis=1)
            conv.weight.copy_(torch.from_numpy(w))
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
            bn.weight.fill_(1.0)
            bn.bias.copy_(torch.from_numpy(np.array(b)))
        hw, hb = inits["net.head.weight"], inits["net.head.bias"]
        c = min(len(hw), net.head.out_channels)
        net.head.weight[:c].copy_(torch.from_numpy(np.array(hw[:c])))
        net.head.bias[:c].copy_(torch.from_numpy(np.array(hb[:c])))
    return net
