"""Widening a trained :class:`~.model.SegUNet` without changing what it computes (Net2WiderNet).

Chen, Goodfellow and Shlens 2016, "Net2Net: accelerating learning via knowledge transfer" (ICLR), section 2.2: a
layer with ``o`` output channels becomes one with ``n >= o`` by copying channels. New channel ``j`` copies old
channel ``g(j)`` (``g(j) = j`` for ``j < o``, a random old channel otherwise): its convolution filter, bias and
BatchNorm statistics. Every layer that reads those channels divides its input weights for a copied channel by the
number of copies of it, so its output is unchanged (ReLU acts per channel, so copies stay equal up to the
consumer). A wider network can then be fine-tuned from a trained narrow one instead of trained from scratch: the
run starts from the narrow model's scores and only capacity differs.

Copies are symmetric: they receive the same gradients and would stay copies. ``noise`` (a fraction of each input
weight tensor's standard deviation) perturbs the new channels' filters to break that symmetry; with ``noise = 0``
the wide network computes exactly what the narrow one computes (up to float rounding), which the tests check.

The channel flow of a :class:`SegUNet` with stages ``c_0 .. c_{S-1}``: each block is conv -> BN -> ReLU -> conv ->
BN -> ReLU; encoder block ``i`` reads encoder block ``i - 1`` (the image for ``i = 0``); decoder block ``k`` reads
the concatenation [previous decoder block (encoder block ``S - 1`` for ``k = 0``), encoder block ``S - 2 - k``];
the head reads the last decoder block. Input image channels are never widened.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from torm.errors import ConfigError
from torm.segmentation.training.model import SegUNet


def copy_map(old: int, new: int, rng: np.random.Generator) -> np.ndarray:
    """Net2Net's map g: (new,) int64, ``g[:old] = 0 .. old - 1``, the rest drawn uniformly from ``0 .. old - 1``."""
    if new < old or old < 1:
        raise ConfigError(f"cannot widen {old} channels to {new}: the new width must be >= the old one (>= 1)")
    return np.concatenate([np.arange(old), rng.integers(0, old, new - old)]).astype(np.int64)


def _out(conv: nn.Conv2d, bn: nn.BatchNorm2d, new_conv: nn.Conv2d, new_bn: nn.BatchNorm2d, g: np.ndarray,
         w_in_oxixkxk: torch.Tensor) -> None:
    """Fill ``new_conv`` (output channels by ``g``, input weights already mapped: ``w_in``) and ``new_bn``."""
    gi = torch.from_numpy(g)
    new_conv.weight.copy_(w_in_oxixkxk[gi])
    if conv.bias is not None:
        new_conv.bias.copy_(conv.bias[gi])
    for name in ("weight", "bias", "running_mean", "running_var"):
        getattr(new_bn, name).copy_(getattr(bn, name)[gi])
    new_bn.num_batches_tracked.copy_(bn.num_batches_tracked)


def _in(w_oxixkxk: torch.Tensor, segments: list[tuple[int, np.ndarray | None]]) -> torch.Tensor:
    """Input-side mapping of a weight tensor whose input is a concatenation of ``segments``.

    Each segment is (old width, g or None = not widened). A copied channel's weights are divided by its number of
    copies, so the layer's output is unchanged. Returns (O, I_new, k, k).
    """
    parts, start = [], 0
    for width, g in segments:
        w = w_oxixkxk[:, start:start + width]
        start += width
        if g is None:
            parts.append(w)
            continue
        counts = np.bincount(g, minlength=width).astype(np.float32)
        parts.append(w[:, torch.from_numpy(g)] / torch.from_numpy(counts[g]).view(1, -1, 1, 1))
    if start != w_oxixkxk.shape[1]:
        raise ValueError(f"segments cover {start} input channels of {w_oxixkxk.shape[1]}")
    return torch.cat(parts, dim=1)


def widen(net: SegUNet, channels: tuple[int, ...], rng: np.random.Generator, noise: float = 0.0) -> SegUNet:
    """A :class:`SegUNet` with ``channels`` per stage computing what ``net`` computes (Net2WiderNet).

    ``net``: the trained network (any BatchNorm statistics; compare in eval mode). ``channels``: as many stages as
    ``net.channels``, each >= the old width. ``rng``: draws which channels are copied. ``noise``: standard deviation
    of the Gaussian perturbation added to the new channels' filters, as a fraction of the layer's weight standard
    deviation (0 = exact). Returns a new network (``net`` is not modified), same head and input channels.
    """
    channels = tuple(int(c) for c in channels)
    if len(channels) != len(net.channels):
        raise ConfigError(f"widen: {len(channels)} stages {channels} for a network of {len(net.channels)} stages "
                          f"{net.channels}; the depth must stay the same")
    if noise < 0:
        raise ConfigError(f"widen: noise {noise} must be >= 0")
    wide = SegUNet(channels, net.head.out_channels == 5, net.in_channels)
    s = len(channels)

    def block(old: nn.Sequential, new: nn.Sequential, segments: list[tuple[int, np.ndarray | None]],
              width_new: int) -> np.ndarray:
        """Widen one block (conv, bn, relu, conv, bn, relu) reading ``segments``; returns its output map."""
        g1 = copy_map(old[0].out_channels, width_new, rng)
        _out(old[0], old[1], new[0], new[1], g1, _in(old[0].weight, segments))
        g2 = copy_map(old[3].out_channels, width_new, rng)
        _out(old[3], old[4], new[3], new[4], g2, _in(old[3].weight, [(old[3].in_channels, g1)]))
        if noise:  # perturb the copies (output channels >= the old width) so that they can diverge
            for conv, o in ((new[0], old[0].out_channels), (new[3], old[3].out_channels)):
                if width_new > o:
                    std = float(conv.weight.std()) * noise
                    conv.weight[o:] += torch.from_numpy(
                        rng.normal(0.0, std, tuple(conv.weight[o:].shape)).astype(np.float32))
        return g2

    with torch.no_grad():
        enc_maps: list[np.ndarray] = []
        prev: list[tuple[int, np.ndarray | None]] = [(net.in_channels, None)]
        for i in range(s):
            g = block(net.down[i], wide.down[i], prev, channels[i])
            enc_maps.append(g)
            prev = [(net.channels[i], g)]
        for k in range(s - 1):
            j = s - 2 - k  # the encoder stage this decoder block's skip comes from
            g = block(net.up[k], wide.up[k], prev + [(net.channels[j], enc_maps[j])], channels[j])
            prev = [(net.channels[j], g)]
        wide.head.weight.copy_(_in(net.head.weight, prev))
        wide.head.bias.copy_(net.head.bias)
    return wide


def onnx_channels(path: str) -> tuple[int, ...]:
    """The stage widths of an exported learned_seg ``.onnx`` file (from its folded convolutions' shapes)."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    inits = {i.name: i for i in graph.initializer}
    outs = [int(numpy_helper.to_array(inits[n.input[1]]).shape[0]) for n in graph.node
            if n.op_type == "Conv" and n.input[1] != "net.head.weight"]
    stages = (len(outs) + 2) // 4  # 2 convs per encoder stage, 2 per decoder stage (one fewer decoder stage)
    if 4 * stages - 2 != len(outs):
        raise ConfigError(f"{path}: {len(outs)} convolutions is not a SegUNet's 4 * stages - 2")
    return tuple(outs[1:2 * stages:2])
