import pytest
import torch
import torch.nn.functional as F

from model_zoo.distill_math import l_ae, l_distill


def test_l_distill_one_view_hand_computed_and_invalid_pixels_ignored():
    rendered = torch.tensor([[[1.0, 2.0], [float("nan"), 9.0]], [[3.0, -1.0], [5.0, 5.0]]], requires_grad=True)
    target = torch.tensor([[[0.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, float("inf")]]])
    valid = torch.tensor([[True, False], [True, False]])
    loss = l_distill(rendered, target, valid)
    # valid pixels: |1| + |2| = 3 and |3 - 1| + |-1| = 3 -> (3 + 3) / 2 valid pixels
    assert loss.item() == 3.0
    loss.backward()
    expected_grad = torch.tensor([[[0.5, 0.5], [0.0, 0.0]], [[0.5, -0.5], [0.0, 0.0]]])
    assert torch.equal(rendered.grad, expected_grad)


def test_l_distill_normalises_by_valid_pixels_of_all_views():
    rendered = torch.zeros(2, 2, 2, 1)
    target = torch.zeros(2, 2, 2, 1)
    target[0, 0, 0, 0] = 4.0  # view 0: one valid pixel, L1 4
    target[1, 0, 0, 0] = 1.0  # view 1: three valid pixels, L1 1 + 2 + 3
    target[1, 0, 1, 0] = -2.0
    target[1, 1, 0, 0] = 3.0
    target[1, 1, 1, 0] = 100.0  # invalid
    valid = torch.tensor([[[True, False], [False, False]], [[True, True], [True, False]]])
    # (4 + 6) / (1 + 3) -- not the mean of per-view means (4 + 2) / 2 = 3
    assert l_distill(rendered, target, valid).item() == 2.5


def test_l_distill_sums_channels_so_it_is_C_times_mean_l1_when_all_valid():
    g = torch.Generator().manual_seed(0)
    rendered, target = torch.randn(5, 7, 6, generator=g), torch.randn(5, 7, 6, generator=g)
    loss = l_distill(rendered, target, torch.ones(5, 7, dtype=torch.bool))
    torch.testing.assert_close(loss, 6 * F.l1_loss(rendered, target))


def test_l_distill_without_valid_pixels_is_zero_and_differentiable():
    rendered = torch.ones(2, 3, 4, requires_grad=True)
    loss = l_distill(rendered, torch.zeros(2, 3, 4), torch.zeros(2, 3, dtype=torch.bool))
    assert loss.item() == 0.0
    loss.backward()
    assert torch.equal(rendered.grad, torch.zeros(2, 3, 4))


def test_l_distill_errors_name_the_shapes():
    with pytest.raises(ValueError) as e:
        l_distill(torch.zeros(2, 3, 4), torch.zeros(2, 3, 5), torch.ones(2, 3, dtype=torch.bool))
    assert str(e.value) == "l_distill: rendered [2, 3, 4] and target [2, 3, 5] must both be [H, W, C] or [V, H, W, C]"
    with pytest.raises(ValueError) as e:
        l_distill(torch.zeros(2, 3, 4), torch.zeros(2, 3, 4), torch.ones(2, 3))
    assert str(e.value) == "l_distill: valid must be bool [2, 3], got torch.float32 [2, 3]"


def test_l_ae_hand_computed():
    recon = torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    f = torch.tensor([[0.0, 0.0], [3.0, 4.0]])
    # (1 + 4 + 9 + 16) / 2
    assert l_ae(recon, f).item() == 15.0
    torch.testing.assert_close(l_ae(recon, f), 2 * F.mse_loss(recon, f))


def test_l_ae_errors_name_the_shapes():
    with pytest.raises(ValueError) as e:
        l_ae(torch.zeros(3, 2), torch.zeros(3, 4))
    assert str(e.value) == "l_ae: reconstruction [3, 2] and features [3, 4] must both be [N > 0, C]"
