import pytest
import torch
from torch.distributions import Independent, Normal, kl_divergence

from model_zoo import registry
from model_zoo.alignment import AlignmentConfig, kl_diag_gaussians, token_stats, warmup

B, F, M, H = 3, 6, 10, 16


def _tokens(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(B, F, H, generator=g) * 0.5 + 1.0
    image = torch.randn(B, M, H, generator=g) * 2.0 - 0.3
    return z, image


def _ones(b: int, n: int) -> torch.Tensor:
    return torch.ones(b, n, dtype=torch.bool)


def test_kl_matches_torch_distributions_on_random_stats():
    g = torch.Generator().manual_seed(0)
    mu_g, mu_i = torch.randn(4, H, generator=g), torch.randn(4, H, generator=g)
    var_g, var_i = torch.rand(4, H, generator=g) + 0.05, torch.rand(4, H, generator=g) + 0.05
    ref = kl_divergence(Independent(Normal(mu_g, var_g.sqrt()), 1), Independent(Normal(mu_i, var_i.sqrt()), 1))
    torch.testing.assert_close(kl_diag_gaussians(mu_g, var_g, mu_i, var_i), ref, atol=1e-5, rtol=1e-5)
    assert kl_diag_gaussians(mu_g, var_g, mu_g, var_g).abs().max().item() < 1e-6


def test_kl_module_equals_reference_over_h_with_eps():
    z, image = _tokens()
    cfg = AlignmentConfig(weight=0.1, warmup_steps=0, eps=1e-4)
    weighted, raw = registry.build("alignment", "kl", cfg)(z, _ones(B, F), image, _ones(B, M), step=0)
    var_g = z.var(dim=1, unbiased=False) + 1e-4
    var_i = image.var(dim=1, unbiased=False) + 1e-4
    ref_B = kl_divergence(
        Independent(Normal(z.mean(dim=1), var_g.sqrt()), 1), Independent(Normal(image.mean(dim=1), var_i.sqrt()), 1)
    )
    expected = (ref_B / H).mean()
    assert raw.shape == () and weighted.shape == ()
    assert raw.item() == pytest.approx(expected.item(), abs=1e-5)
    assert weighted.item() == pytest.approx(0.1 * expected.item(), abs=1e-6)


def test_token_stats_are_mean_and_biased_variance_of_valid_tokens():
    x = torch.tensor([[[1.0], [3.0], [100.0]]])
    mu, var = token_stats(x, torch.tensor([[True, True, False]]))
    assert mu.tolist() == [[2.0]] and var.tolist() == [[1.0]]
    mu, var = token_stats(x, torch.tensor([[False, False, False]]))
    assert mu.tolist() == [[0.0]] and var.tolist() == [[0.0]]


def test_no_gradient_reaches_the_image_tokens():
    z, image = _tokens()
    z.requires_grad_(True)
    image.requires_grad_(True)
    weighted, _ = registry.build("alignment", "kl", AlignmentConfig(warmup_steps=0))(
        z, _ones(B, F), image, _ones(B, M), step=5
    )
    weighted.backward()
    assert image.grad is None or image.grad.abs().sum().item() == 0.0
    assert z.grad is not None and z.grad.abs().sum().item() > 0


def test_warmup_values():
    assert warmup(0, 100) == 0.0
    assert warmup(50, 100) == 0.5
    assert warmup(100, 100) == 1.0
    assert warmup(1000, 100) == 1.0
    assert warmup(0, 0) == 1.0
    with pytest.raises(ValueError) as e:
        warmup(3, -1)
    assert str(e.value) == "alignment warm-up: step and warmup_steps must be >= 0, got 3 and -1"


def test_weighted_loss_follows_the_warmup():
    z, image = _tokens()
    align = registry.build("alignment", "kl", AlignmentConfig(weight=0.2, warmup_steps=100))
    args = (z, _ones(B, F), image, _ones(B, M))
    w0, raw0 = align(*args, step=0)
    w50, raw50 = align(*args, step=50)
    w200, raw200 = align(*args, step=200)
    assert raw0.item() > 0 and raw0.item() == raw50.item() == raw200.item()
    assert w0.item() == 0.0
    assert w50.item() == pytest.approx(0.2 * 0.5 * raw0.item(), rel=1e-6)
    assert w200.item() == pytest.approx(0.2 * raw0.item(), rel=1e-6)


def test_none_returns_exactly_zero():
    z, image = _tokens()
    z.requires_grad_(True)
    weighted, raw = registry.build("alignment", "none", AlignmentConfig(name="none"))(
        z, _ones(B, F), image, _ones(B, M), step=500
    )
    assert weighted.item() == 0.0 and raw.item() == 0.0
    assert weighted.shape == () and raw.shape == ()
    (weighted + z.sum()).backward()  # adds to a real loss without breaking autograd
    assert torch.equal(z.grad, torch.ones_like(z))


def test_padded_tokens_do_not_change_the_loss():
    z, image = _tokens()
    align = registry.build("alignment", "kl", AlignmentConfig(warmup_steps=0))
    _, raw = align(z, _ones(B, F), image, _ones(B, M), step=0)
    z_pad = torch.cat([z, torch.full((B, 4, H), 1e3)], dim=1)
    z_mask = torch.cat([_ones(B, F), torch.zeros(B, 4, dtype=torch.bool)], dim=1)
    image_pad = torch.cat([image, torch.randn(B, 7, H) * 50], dim=1)
    image_mask = torch.cat([_ones(B, M), torch.zeros(B, 7, dtype=torch.bool)], dim=1)
    _, raw_pad = align(z_pad, z_mask, image_pad, image_mask, step=0)
    assert raw_pad.item() == pytest.approx(raw.item(), rel=1e-6)


def test_samples_without_valid_tokens_are_left_out_without_nan():
    z, image = _tokens()
    z.requires_grad_(True)
    align = registry.build("alignment", "kl", AlignmentConfig(warmup_steps=0))
    z_mask, image_mask = _ones(B, F), _ones(B, M)
    z_mask[1] = False
    image_mask[2] = False
    _, raw = align(z, z_mask, image, image_mask, step=0)
    _, raw_first = align(z[:1], _ones(1, F), image[:1], _ones(1, M), step=0)
    assert raw.item() == pytest.approx(raw_first.item(), rel=1e-6)
    raw.backward()
    assert torch.isfinite(z.grad).all() and z.grad[1].abs().sum().item() == 0.0
    weighted, raw = align(z, torch.zeros(B, F, dtype=torch.bool), image, image_mask, step=0)
    assert weighted.item() == 0.0 and raw.item() == 0.0


def test_bad_config_is_named():
    with pytest.raises(ValueError) as e:
        registry.build("alignment", "kl", AlignmentConfig(eps=0.0))
    assert str(e.value) == (
        "alignment/kl: eps must be > 0, warmup_steps and weight >= 0, "
        "got AlignmentConfig(name='kl', weight=0.1, warmup_steps=100, eps=0.0)"
    )
