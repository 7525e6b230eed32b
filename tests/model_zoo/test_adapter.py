import math

import pytest
import torch
import torch.nn.functional as F

from model_zoo import registry
from model_zoo.adapter import (
    AttributeProjection,
    FineAdapterConfig,
    ProjectionConfig,
    fourier_embedding,
    pooled_text,
)

B, K, H, C, L = 2, 12, 32, 8, 5


def _attrs(seed: int = 0, b: int = B, k: int = K) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(b, k, 3, generator=g) * 20,
        torch.rand(b, k, 3, generator=g) + 0.1,
        torch.randn(b, k, 4, generator=g),
        torch.rand(b, k, generator=g),
        torch.randn(b, k, C, generator=g),
    )


def _text(seed: int = 0, b: int = B) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, L, H, generator=g), torch.ones(b, L, dtype=torch.bool)


def test_projection_shape_and_parameter_widths():
    torch.manual_seed(0)
    proj = AttributeProjection(ProjectionConfig(), hidden=H, feature_dim=C)
    assert proj(*_attrs()).shape == (B, K, H)
    assert proj.fourier.weight.shape == (16, 3)
    assert {a: m.in_features for a, m in proj.proj.items()} == {"x": 32, "s": 3, "r": 4, "o": 1, "f": C}
    assert proj.mlp[0].out_features == 2 * H
    assert torch.equal(proj.gates.detach(), torch.ones(5))


def test_fourier_init_std_follows_the_config():
    torch.manual_seed(0)
    proj = AttributeProjection(ProjectionConfig(fourier_features=512, fourier_scale=0.05), hidden=H, feature_dim=C)
    assert proj.fourier.weight.std().item() == pytest.approx(0.05, rel=0.05)


def test_fourier_embedding_matches_the_formula_by_hand():
    b = torch.nn.Linear(3, 2, bias=False)
    with torch.no_grad():
        b.weight.copy_(torch.tensor([[0.25, 0.0, 0.0], [0.0, 0.5, 0.125]]))
    x = torch.tensor([[[1.0, 1.0, 2.0]]])
    # B x = [0.25, 0.75]; 2 pi B x = [pi/2, 3 pi/2]
    expected = torch.tensor([[[1.0, -1.0, 0.0, 0.0]]])
    torch.testing.assert_close(fourier_embedding(x, b), expected, atol=1e-6, rtol=0)
    assert math.isclose(fourier_embedding(x, b)[0, 0, 0].item(), math.sin(2 * math.pi * 0.25), abs_tol=1e-6)


def test_gates_receive_gradients():
    torch.manual_seed(0)
    proj = AttributeProjection(ProjectionConfig(), hidden=H, feature_dim=C)
    proj(*_attrs()).square().sum().backward()
    assert isinstance(proj.gates, torch.nn.Parameter)
    assert proj.gates.grad is not None and proj.gates.grad.shape == (5,)
    assert (proj.gates.grad.abs() > 0).all()
    assert proj.fourier.weight.grad is not None and proj.fourier.weight.grad.abs().sum() > 0


def test_dropping_f_makes_output_independent_of_the_feature():
    torch.manual_seed(0)
    proj = AttributeProjection(ProjectionConfig(attributes=("x", "s", "r", "o")), hidden=H, feature_dim=C)
    xyz, scale, rot, opa, feat = _attrs()
    assert "f" not in proj.proj and proj.gates.shape == (4,)
    torch.testing.assert_close(
        proj(xyz, scale, rot, opa, feat), proj(xyz, scale, rot, opa, feat * 7 + 3), rtol=0, atol=0
    )
    full = AttributeProjection(ProjectionConfig(), hidden=H, feature_dim=C)
    assert not torch.allclose(full(xyz, scale, rot, opa, feat), full(xyz, scale, rot, opa, feat + 1))


def test_rotation_is_normalised_and_zero_scale_stays_finite():
    torch.manual_seed(0)
    proj = AttributeProjection(ProjectionConfig(), hidden=H, feature_dim=C)
    xyz, scale, rot, opa, feat = _attrs()
    torch.testing.assert_close(proj(xyz, scale, rot, opa, feat), proj(xyz, scale, rot * 3.5, opa, feat))
    assert torch.isfinite(proj(xyz, torch.zeros_like(scale), rot, opa, feat)).all()


def test_unknown_attribute_is_named():
    with pytest.raises(ValueError) as e:
        AttributeProjection(ProjectionConfig(attributes=("x", "color")), hidden=H, feature_dim=C)
    assert str(e.value) == (
        "attribute projection: attributes must be distinct names from ['x', 's', 'r', 'o', 'f'], got ['x', 'color']"
    )


def test_pooled_text_averages_valid_positions_and_is_zero_when_none():
    text = torch.arange(2 * 3 * 2, dtype=torch.float32).reshape(2, 3, 2)
    mask = torch.tensor([[True, False, True], [False, False, False]])
    torch.testing.assert_close(pooled_text(text, mask), torch.tensor([[2.0, 3.0], [0.0, 0.0]]))


def test_registered_variant_names():
    assert registry.variants("fine_adapter") == [
        ("fine_adapter", "identity"),
        ("fine_adapter", "query_xattn"),
        ("fine_adapter", "similarity"),
    ]
    assert registry.variants("alignment") == [("alignment", "kl"), ("alignment", "none")]


@pytest.mark.parametrize("name", ["similarity", "query_xattn", "identity"])
def test_every_fine_adapter_gives_k_f_tokens(name: str):
    torch.manual_seed(0)
    adapter = registry.build("fine_adapter", name, FineAdapterConfig(name=name, k_f=6, heads=4), H)
    k = 6 if name == "identity" else K  # identity takes exactly K_f candidates
    g = torch.randn(B, k, H)
    z, z_mask = adapter(g, torch.ones(B, k, dtype=torch.bool), *_text())
    assert z.shape == (B, 6, H) and z_mask.shape == (B, 6) and z_mask.dtype == torch.bool
    assert z_mask.all()


def _unit(v: list[float]) -> torch.Tensor:
    return F.normalize(torch.tensor(v), dim=0)


def test_similarity_picks_exact_top_k_by_cosine_in_descending_order():
    e = torch.zeros(4)
    e[0] = 1.0
    text = e.expand(1, 3, 4).clone()  # pooled text = e, whatever its length
    # g_i = cos_i * e + sin_i * e_1 (times a per-token norm, which cosine ignores)
    cosines = [0.1, 0.9, -0.5, 0.7, 0.3, 0.95]
    norms = [1.0, 2.0, 0.5, 3.0, 1.5, 0.7]
    g = torch.stack([n * torch.tensor([c, math.sqrt(1 - c * c), 0, 0]) for c, n in zip(cosines, norms, strict=True)])
    g = g.unsqueeze(0).requires_grad_(True)
    mask = torch.ones(1, 6, dtype=torch.bool)
    mask[0, 5] = False  # the best cosine is padding and must not be picked
    adapter = registry.build("fine_adapter", "similarity", FineAdapterConfig(k_f=3), 4)
    z, z_mask = adapter(g, mask, text, torch.ones(1, 3, dtype=torch.bool))
    torch.testing.assert_close(z, g[:, [1, 3, 4]])
    assert z_mask.tolist() == [[True, True, True]]
    z.sum().backward()
    assert g.grad[0, :, 0].tolist() == [0.0, 1.0, 0.0, 1.0, 1.0, 0.0]


def test_similarity_pads_when_fewer_valid_than_k_f():
    g = torch.randn(2, 4, 8)
    mask = torch.tensor([[True, False, True, False], [False] * 4])
    adapter = registry.build("fine_adapter", "similarity", FineAdapterConfig(k_f=6), 8)
    z, z_mask = adapter(g, mask, torch.randn(2, 3, 8), torch.ones(2, 3, dtype=torch.bool))
    assert z.shape == (2, 6, 8)
    assert z_mask.tolist() == [[True, True] + [False] * 4, [False] * 6]
    assert z[~z_mask].abs().sum().item() == 0.0
    assert sorted(z[0, :2].sum(dim=1).tolist()) == sorted(g[0, [0, 2]].sum(dim=1).tolist())


def test_query_xattn_ignores_padded_candidates():
    torch.manual_seed(0)
    adapter = registry.build("fine_adapter", "query_xattn", FineAdapterConfig(k_f=5, heads=4), H)
    g = torch.randn(B, K, H)
    mask = torch.ones(B, K, dtype=torch.bool)
    mask[:, 8:] = False
    text = _text()
    z, z_mask = adapter(g, mask, *text)
    g2 = g.clone()
    g2[:, 8:] = torch.randn(B, K - 8, H) * 100
    g2[0, 9] = torch.nan
    z2, _ = adapter(g2, mask, *text)
    torch.testing.assert_close(z, z2, rtol=0, atol=0)
    assert z_mask.all()
    g3 = g.clone()
    g3[:, 0] += 1.0
    assert not torch.allclose(adapter(g3, mask, *text)[0], z)


def test_query_xattn_is_modulated_by_the_text():
    torch.manual_seed(0)
    adapter = registry.build("fine_adapter", "query_xattn", FineAdapterConfig(k_f=5, heads=4), H)
    g = torch.randn(B, K, H)
    mask = torch.ones(B, K, dtype=torch.bool)
    z_a, _ = adapter(g, mask, *_text(seed=1))
    z_b, _ = adapter(g, mask, *_text(seed=2))
    assert (z_a - z_b).abs().max().item() > 1e-3
    # padding in the text does not count towards e_q
    text, text_mask = _text(seed=1)
    text_mask[:, 3:] = False
    text_junk = text.clone()
    text_junk[:, 3:] = 50.0
    torch.testing.assert_close(adapter(g, mask, text, text_mask)[0], adapter(g, mask, text_junk, text_mask)[0])


def test_query_xattn_empty_scene_gives_finite_zeros_and_no_nan_gradient():
    torch.manual_seed(0)
    adapter = registry.build("fine_adapter", "query_xattn", FineAdapterConfig(k_f=5, heads=4), H)
    g = torch.randn(B, K, H, requires_grad=True)
    mask = torch.ones(B, K, dtype=torch.bool)
    mask[1] = False
    z, z_mask = adapter(g, mask, *_text())
    assert z_mask.tolist() == [[True] * 5, [False] * 5]
    assert torch.isfinite(z).all()
    assert z[1].abs().sum().item() == 0.0
    assert z[0].abs().sum().item() > 0
    z.sum().backward()
    assert torch.isfinite(g.grad).all()
    assert g.grad[1].abs().sum().item() == 0.0
    assert torch.isfinite(adapter.queries_FH.grad).all()


def test_query_xattn_parameters_and_heads_check():
    adapter = registry.build("fine_adapter", "query_xattn", FineAdapterConfig(k_f=7, heads=4), H)
    assert adapter.queries_FH.shape == (7, H)
    assert adapter.text_mod.weight.shape == (H, H)
    assert adapter.attn.num_heads == 4 and adapter.attn.batch_first
    with pytest.raises(ValueError) as e:
        registry.build("fine_adapter", "query_xattn", FineAdapterConfig(heads=5), H)
    assert str(e.value) == "fine_adapter/query_xattn: heads=5 must divide the hidden size 32"


def test_identity_passes_k_f_candidates_through_unchanged():
    g = torch.randn(2, 4, 8)
    mask = torch.tensor([[True, True, False, True], [True, False, False, False]])
    text = (torch.randn(2, 3, 8), torch.ones(2, 3, dtype=torch.bool))
    z, z_mask = registry.build("fine_adapter", "identity", FineAdapterConfig(k_f=4), 8)(g, mask, *text)
    assert torch.equal(z, g) and torch.equal(z_mask, mask)


@pytest.mark.parametrize("k_c", [3, 6])
def test_identity_refuses_k_c_other_than_k_f(k_c: int):
    """Keeping the first K_f of more candidates dropped the uniform branch of topk_uniform (issue 17)."""
    adapter = registry.build("fine_adapter", "identity", FineAdapterConfig(k_f=4), 8)
    text = (torch.randn(2, 3, 8), torch.ones(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError) as e:
        adapter(torch.randn(2, k_c, 8), torch.ones(2, k_c, dtype=torch.bool), *text)
    assert str(e.value) == (
        f"fine_adapter/identity: got K_c={k_c} candidates for K_f=4 world tokens; "
        "model.selector.k_c must equal model.fine_adapter.k_f"
    )


def test_fine_adapter_names_a_bad_mask():
    adapter = registry.build("fine_adapter", "identity", FineAdapterConfig(k_f=3), 8)
    with pytest.raises(ValueError) as e:
        adapter(torch.randn(2, 4, 8), torch.ones(2, 4), torch.randn(2, 3, 8), torch.ones(2, 3, dtype=torch.bool))
    assert str(e.value) == (
        "fine_adapter/identity: expected g [B, K, H] and a bool mask [B, K], got [2, 4, 8] and [2, 4] torch.float32"
    )


def test_projection_feeds_query_xattn_end_to_end():
    torch.manual_seed(0)
    proj = AttributeProjection(ProjectionConfig(), hidden=H, feature_dim=C)
    adapter = registry.build("fine_adapter", "query_xattn", FineAdapterConfig(k_f=4), H)
    z, z_mask = adapter(proj(*_attrs()), torch.ones(B, K, dtype=torch.bool), *_text())
    z.square().mean().backward()
    assert z.shape == (B, 4, H) and z_mask.all()
    assert (proj.gates.grad.abs() > 0).all()
