"""DMTet-Multi losses: eq. (1)-(4) and the robust per-view weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torm.errors import ConfigError
from torm.reconstruction.losses import (
    alpha_schedule,
    eikonal_loss_edges,
    eikonal_loss_grad,
    envelope_mask_loss,
    mask_loss_init,
    robust_view_weights,
    zero_crossing_edges,
    zero_crossing_points,
)


def test_mask_losses_match_equations():
    rng = np.random.default_rng(0)
    pred = torch.tensor(rng.random((3, 5, 7)))
    tgt = torch.tensor((rng.random((3, 5, 7)) > 0.5).astype(float))
    l1 = mask_loss_init(pred, tgt)
    assert l1.shape == (3,)
    assert np.allclose(l1.numpy(), ((pred - tgt) ** 2).numpy().reshape(3, -1).mean(1))
    l2 = envelope_mask_loss(pred, tgt, 3.0)
    assert np.allclose(l2.numpy(), ((pred.numpy() - 3.0 * tgt.numpy()) ** 2).reshape(3, -1).mean(1))
    assert torch.allclose(envelope_mask_loss(pred, tgt, 1.0), l1)
    # alpha > 1: an uncovered object pixel pulls outward 3x harder than a covered background pixel pulls in
    p = torch.tensor([[[0.0, 1.0]]], requires_grad=True)
    envelope_mask_loss(p, torch.tensor([[[1.0, 0.0]]]), 3.0).sum().backward()
    assert p.grad[0, 0, 0] == pytest.approx(-3.0) and p.grad[0, 0, 1] == pytest.approx(1.0)


@pytest.mark.parametrize("t", [0, 1, 37, 249.5, 499, 500, 501, 10_000])
def test_alpha_schedule_equation_3(t):
    a_max, a_min, T = 3.0, 1.0, 500
    expected = a_max - (a_max - a_min) / T * t if t < T else a_min
    assert alpha_schedule(t, a_max, a_min, T) == pytest.approx(expected)


def test_alpha_schedule_shape_and_errors():
    vals = [alpha_schedule(t, 3.0, 1.0, 100) for t in range(200)]
    assert vals[0] == 3.0 and vals[50] == pytest.approx(2.0) and vals[100:] == [1.0] * 100
    assert all(a >= b for a, b in zip(vals, vals[1:], strict=False))
    with pytest.raises(ConfigError):
        alpha_schedule(1, 3, 1, 0)
    with pytest.raises(ConfigError):
        alpha_schedule(-1, 3, 1, 10)


def test_eikonal_edges_zero_for_true_distance_and_positive_otherwise():
    # 1-D chain of vertices along x with spacing 0.1; s = x - 0.25 is a unit-gradient SDF
    x = torch.arange(6, dtype=torch.float64) * 0.1
    verts = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], dim=1)
    edges = torch.tensor([[i, i + 1] for i in range(5)])
    s = x - 0.25
    assert zero_crossing_edges(s, edges).tolist() == [[2, 3]]
    assert float(eikonal_loss_edges(s, verts, edges)) == pytest.approx(0.0, abs=1e-12)
    s2 = 3.0 * (x - 0.25)  # |grad| = 3 -> (3 - 1)^2 = 4
    assert float(eikonal_loss_edges(s2, verts, edges)) == pytest.approx(4.0)
    # the paper's v0 sits where the SDF crosses zero
    assert zero_crossing_points(s2, verts, edges)[0, 0].item() == pytest.approx(0.25)
    # no crossing -> 0 but still differentiable
    sp = (x + 1.0).requires_grad_(True)
    lp = eikonal_loss_edges(sp, verts, edges)
    lp.backward()
    assert float(lp.detach()) == 0.0


def test_eikonal_from_gradients():
    g = torch.tensor([[0.0, 0.0, 1.0], [0.0, 2.0, 0.0]])
    assert float(eikonal_loss_grad(g)) == pytest.approx(0.5)
    assert float(eikonal_loss_grad(torch.zeros((0, 3)))) == 0.0


def test_robust_view_weights_downweight_outliers_only():
    losses = torch.tensor([0.010, 0.011, 0.009, 0.012, 0.010, 0.2])
    w = robust_view_weights(losses, "mad", 3.0)
    assert torch.all(w[:5] == 1.0) and 0 < w[5] < 0.1
    wg = robust_view_weights(losses, "gm", 3.0)
    assert wg[5] < 0.01 and torch.all(wg[:5] > 0.5)
    # a view better than typical is never down-weighted; identical losses -> all ones
    assert robust_view_weights(torch.tensor([0.1, 0.1, 0.1, 0.0]), "mad").tolist() == [1.0] * 4
    assert robust_view_weights(torch.tensor([1.0, 5.0])).tolist() == [1.0, 1.0]
    # weights carry no gradient
    lv = losses.clone().requires_grad_(True)
    assert not robust_view_weights(lv).requires_grad
    with pytest.raises(ConfigError):
        robust_view_weights(losses, "huber?")
