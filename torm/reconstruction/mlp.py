"""The paper's three-layer perceptron f(v) -> (sdf, deformation) with optional positional encoding."""

from __future__ import annotations

import math

import torch
from torch import nn


class SDFDeformMLP(nn.Module):
    """f(v): normalised position (N, 3) in [-1, 1] -> (N, 4) = (sdf in cells, raw deformation (3,)).

    ``pe_freqs`` > 0 prepends NeRF-style encoding ``sin/cos(2^k * pi * x)``, k < pe_freqs, to the input.
    ``layers`` counts the hidden linear layers (the paper's "three-layer perceptron" = 3), ReLU-activated.
    """

    def __init__(self, hidden: int = 128, layers: int = 3, pe_freqs: int = 4, generator: torch.Generator | None = None):
        super().__init__()
        self.pe_freqs = int(pe_freqs)
        d_in = 3 + 6 * self.pe_freqs
        mods: list[nn.Module] = []
        for i in range(layers):
            mods += [nn.Linear(d_in if i == 0 else hidden, hidden), nn.ReLU()]
        mods.append(nn.Linear(hidden if layers else d_in, 4))
        self.net = nn.Sequential(*mods)
        with torch.no_grad():
            for m in self.net:
                if isinstance(m, nn.Linear):
                    bound = 1.0 / math.sqrt(m.in_features)
                    m.weight.uniform_(-bound, bound, generator=generator)
                    m.bias.uniform_(-bound, bound, generator=generator)

    def encode(self, x_nx3: torch.Tensor) -> torch.Tensor:
        if self.pe_freqs == 0:
            return x_nx3
        freqs = (2.0 ** torch.arange(self.pe_freqs, dtype=x_nx3.dtype, device=x_nx3.device)) * math.pi
        xf = x_nx3[:, :, None] * freqs  # (N, 3, L)
        return torch.cat([x_nx3, torch.sin(xf).flatten(1), torch.cos(xf).flatten(1)], dim=1)

    def forward(self, x_nx3: torch.Tensor) -> torch.Tensor:
        return self.net(self.encode(x_nx3))
