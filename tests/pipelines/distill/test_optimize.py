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
