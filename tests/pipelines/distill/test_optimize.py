"""The pieces of distillation: rendering codes' features and initialising each code from the pixels it covers."""

from __future__ import annotations

import torch

from pipelines.distill.optimize import ViewFeatures, initial_features, render_features


def _view(weights_PN: torch.Tensor, target_HWC: torch.Tensor, valid_HW: torch.Tensor) -> ViewFeatures:
    return ViewFeatures(None, False, weights_PN.to_sparse_csr(), target_HWC, valid_HW)


def test_render_features_is_the_weighted_sum_over_gaussians():
    weights_PN = torch.tensor([[1.0, 0.0], [0.25, 0.75]])
    feats_NC = torch.tensor([[4.0, 0.0], [0.0, 8.0]])
    out = render_features(weights_PN.to_sparse_csr(), feats_NC, (1, 2))
    assert out.shape == (1, 2, 2)
    assert out.tolist() == [[[4.0, 0.0], [1.0, 6.0]]]


def test_initial_features_weight_valid_pixels_and_fall_back_to_the_mean():
    # 2 pixels, 3 Gaussians: Gaussian 0 covers both, 1 only the invalid pixel, 2 none
    weights_PN = torch.tensor([[0.5, 0.0, 0.0], [0.5, 1.0, 0.0]])
    target_HWC = torch.tensor([[[2.0], [6.0]]])
    valid_HW = torch.tensor([[True, False]])
    mean_C = torch.tensor([9.0])
    f_NC = initial_features(3, [_view(weights_PN, target_HWC, valid_HW)], mean_C)
    assert f_NC.tolist() == [[2.0], [9.0], [9.0]]


def test_a_view_rendered_with_its_transpose_has_torchs_own_gradient_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    dense_PN = torch.rand(60, 40, generator=g) * (torch.rand(60, 40, generator=g) < 0.2)
    view = _view(dense_PN, torch.zeros(6, 10, 1), torch.ones(6, 10, dtype=torch.bool))
    feats = torch.randn(40, 3, generator=g)
    upstream = torch.randn(6, 10, 3, generator=g)
    grads = []
    for transpose in (None, view.weights_NP):
        f = feats.clone().requires_grad_(True)
        out = render_features(view.weights_PN, f, (6, 10), transpose)
        (out * upstream).sum().backward()
        grads.append((out.detach(), f.grad))
    assert view.weights_NP.layout == torch.sparse_csr and view.weights_NP.shape == (40, 60)
    assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])
    torch.testing.assert_close(grads[1][1], dense_PN.t() @ upstream.reshape(60, 3))
