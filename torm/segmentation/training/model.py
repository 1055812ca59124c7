"""A small U-Net (torch): RGB in, two logit maps out (object foreground, instance boundary band).

Encoder: ``len(channels)`` stages of two 3x3 conv + BatchNorm + ReLU, max-pool 2 between stages; decoder:
bilinear x2 upsampling, concatenation with the encoder stage of the same size, two 3x3 convs. Input height
and width must be multiples of ``2 ** (len(channels) - 1)`` (16 for the default). The exported wrapper
(:class:`ExportWrapper`) takes (1, 3, H, W) float32 RGB in [0, 255] and normalises inside the graph.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

#: per-channel RGB mean / std (of [0, 1] values) the network is normalised with (ImageNet statistics)
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)
OUTPUTS = ("foreground", "boundary")


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
    )


class SegUNet(nn.Module):
    """U-Net with ``channels`` per stage; forward (B, 3, H, W) normalised RGB -> (B, 2, H, W) logits."""

    def __init__(self, channels: tuple[int, ...] = (12, 24, 32, 48, 64)) -> None:
        super().__init__()
        self.channels = tuple(channels)
        self.down = nn.ModuleList()
        cin = 3
        for c in channels:
            self.down.append(_block(cin, c))
            cin = c
        self.up = nn.ModuleList()
        for c_skip in reversed(channels[:-1]):
            self.up.append(_block(cin + c_skip, c_skip))
            cin = c_skip
        self.head = nn.Conv2d(cin, len(OUTPUTS), 1)

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


def normalise(rgb255_bx3xhxw: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 255] (float32) -> ImageNet-normalised input."""
    return (rgb255_bx3xhxw - _MEAN_1x3x1x1) / _STD_1x3x1x1


class ExportWrapper(nn.Module):
    """What the ONNX file holds: ``image`` (1, 3, H, W) RGB in [0, 255] -> ``logits`` (1, 2, H, W)."""

    def __init__(self, net: SegUNet) -> None:
        super().__init__()
        self.net = net
        self.register_buffer("mean", _MEAN_1x3x1x1.clone())
        self.register_buffer("std", _STD_1x3x1x1.clone())

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.net((image - self.mean) / self.std)
