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

    def sdf_input_gradient(self, x_nx3: torch.Tensor) -> torch.Tensor:
        """d f_sdf / d x (N, 3) at the normalised positions ``x_nx3`` (no gradient needed on them), differentiable
        w.r.t. the weights: eq. (4)'s gradient without a double backward.

        The ReLU activation pattern is piecewise constant in the weights, so it is taken from a gradient-free
        forward pass; the chain ``w_out^T D_L W_L ... D_1 W_1 dPE/dx`` is then built from ordinary products, whose
        backward gives the weights' gradients that autograd's double backward gives (almost everywhere; the biases'
        are zero; ``tests/test_recon_paper_mode.py`` checks both against ``torch.autograd.grad(create_graph=True)``).
        """
        linears = [m for m in self.net if isinstance(m, nn.Linear)]
        with torch.no_grad():
            h = self.encode(x_nx3)
            masks = []
            for lin in linears[:-1]:
                z = lin(h)
                masks.append((z > 0).to(z.dtype))
                h = z.clamp_min(0.0)
        a = linears[-1].weight[0].expand(len(x_nx3), -1)  # d f_sdf / d (last hidden layer)
        for lin, m in zip(reversed(linears[:-1]), reversed(masks), strict=True):
            a = (a * m) @ lin.weight
        if self.pe_freqs == 0:
            return a
        n, L = len(x_nx3), self.pe_freqs
        freqs = (2.0 ** torch.arange(L, dtype=x_nx3.dtype, device=x_nx3.device)) * math.pi
        with torch.no_grad():
            xf = x_nx3[:, :, None] * freqs  # (N, 3, L), the encoding's phases
            d_sin, d_cos = freqs * torch.cos(xf), -freqs * torch.sin(xf)
        g_sin = a[:, 3:3 + 3 * L].reshape(n, 3, L)
        g_cos = a[:, 3 + 3 * L:].reshape(n, 3, L)
        return a[:, :3] + (g_sin * d_sin).sum(-1) + (g_cos * d_cos).sum(-1)
