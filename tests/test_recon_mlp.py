"""The paper's MLP f(v): the closed-form input gradient (eq. 4) against autograd's double backward."""

from __future__ import annotations

import pytest
import torch

from torm.reconstruction import losses
from torm.reconstruction.mlp import SDFDeformMLP


@pytest.mark.parametrize(("hidden", "layers", "pe_freqs"), [(32, 3, 4), (16, 1, 0), (8, 0, 2)])
def test_sdf_input_gradient_equals_the_double_backward(hidden, layers, pe_freqs):
    torch.manual_seed(0)
    mlp = SDFDeformMLP(hidden, layers, pe_freqs, generator=torch.Generator().manual_seed(1)).double()
    x = torch.rand((200, 3), generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 2 - 1
    params = list(mlp.parameters())
    # the reference: d f_sdf / dx by autograd with a graph, then eq. (4) differentiated through it
    xr = x.clone().requires_grad_(True)
    (g_ref,) = torch.autograd.grad(mlp(xr)[:, 0].sum(), xr, create_graph=True)
    loss_ref = losses.eikonal_loss_grad(0.3 * g_ref)
    grads_ref = torch.autograd.grad(loss_ref, params, allow_unused=True)
    g = mlp.sdf_input_gradient(x)
    assert g.shape == (200, 3) and torch.allclose(g, g_ref.detach(), atol=1e-12)
    loss = losses.eikonal_loss_grad(0.3 * g)
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    assert torch.allclose(loss, loss_ref.detach(), atol=1e-12)
    reached = 0
    for p, a, b in zip(params, grads_ref, grads, strict=True):
        want = torch.zeros_like(p) if a is None else a
        got = torch.zeros_like(p) if b is None else b
        assert torch.allclose(got, want, atol=1e-12), p.shape
        reached += int(bool(got.abs().max() > 0))
    assert reached == layers + 1  # every weight matrix, no bias


def test_sdf_input_gradient_matches_finite_differences():
    mlp = SDFDeformMLP(16, 2, 3, generator=torch.Generator().manual_seed(3)).double()
    x = torch.tensor([[0.1, -0.2, 0.3], [-0.5, 0.4, 0.05]], dtype=torch.float64)
    g = mlp.sdf_input_gradient(x).detach()
    eps = 1e-6
    for j in range(3):
        d = torch.zeros(3, dtype=torch.float64)
        d[j] = eps
        with torch.no_grad():
            fd = (mlp(x + d)[:, 0] - mlp(x - d)[:, 0]) / (2 * eps)
        assert torch.allclose(g[:, j], fd, atol=1e-6)
