import pytest
import torch

from model_zoo import registry
from model_zoo.distill_math import l_ae
from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder, fit_autoencoder


def _rank4(n: int = 512, d_f: int = 64) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.randn(n, 4, generator=g) @ torch.randn(4, d_f, generator=g)


def test_shapes_and_layers():
    ae = registry.build("feature_tokenizer", "foundation", FeatureAEConfig(d_f=64, d_z=16, hidden=32, layers=3))
    f_NC = torch.randn(10, 64)
    z_NZ = ae.encode(f_NC)
    assert z_NZ.shape == (10, 16)
    assert ae.decode(z_NZ).shape == (10, 64)
    assert ae(f_NC).shape == (10, 64)
    assert (ae.d_f, ae.d_z) == (64, 16)
    assert sum(isinstance(m, torch.nn.Linear) for m in ae.encoder) == 3
    assert [
        m.weight.shape for m in FeatureAutoencoder(FeatureAEConfig(layers=1)).modules() if hasattr(m, "weight")
    ] == [
        (16, 64),
        (64, 16),
    ]


def test_default_foundation_code_width_is_16_and_langsplat3_is_3():
    assert registry.build("feature_tokenizer", "foundation").d_z == 16
    ae = registry.build("feature_tokenizer", "langsplat3")
    assert ae.d_z == 3
    assert ae.encode(torch.randn(5, 64)).shape == (5, 3)
    assert registry.build("feature_tokenizer", "langsplat3", FeatureAEConfig(d_f=128, d_z=3)).d_f == 128
    with pytest.raises(ValueError) as e:
        registry.build("feature_tokenizer", "langsplat3", FeatureAEConfig(d_z=16))
    assert str(e.value) == "feature_tokenizer/langsplat3: d_z is fixed to 3 (the release's _language_feature), got 16"


def test_unknown_variant():
    with pytest.raises(registry.UnknownVariant) as e:
        registry.build("feature_tokenizer", "pca")
    assert (
        str(e.value) == "no variant 'pca' of component 'feature_tokenizer' (registered: ['foundation', 'langsplat3'])"
    )


def test_fit_reduces_l_ae_at_least_10x_on_low_rank_data():
    f_NC = _rank4()
    model, losses = fit_autoencoder(f_NC, FeatureAEConfig(d_f=64, d_z=16), steps=100, lr=1e-2, seed=0)
    assert len(losses) == 100
    final = l_ae(model(f_NC), f_NC).item()
    print(f"L_ae {losses[0]:.3f} -> {final:.4f} ({losses[0] / final:.0f}x)")
    assert losses[0] / final >= 10
    assert not model.training


def test_fit_is_deterministic_with_a_seed_and_leaves_the_global_rng_alone():
    f_NC = _rank4(128)
    cfg = FeatureAEConfig(d_f=64, d_z=8, hidden=32)
    state = torch.random.get_rng_state()
    m1, l1 = fit_autoencoder(f_NC, cfg, steps=10, lr=1e-2, seed=3, batch_size=32)
    assert torch.equal(torch.random.get_rng_state(), state)
    m2, l2 = fit_autoencoder(f_NC, cfg, steps=10, lr=1e-2, seed=3, batch_size=32)
    _, l3 = fit_autoencoder(f_NC, cfg, steps=10, lr=1e-2, seed=4, batch_size=32)
    assert l1 == l2
    assert l1 != l3
    assert all(torch.equal(a, b) for a, b in zip(m1.state_dict().values(), m2.state_dict().values(), strict=True))


def test_fit_rejects_features_of_the_wrong_width():
    with pytest.raises(ValueError) as e:
        fit_autoencoder(torch.zeros(4, 32), FeatureAEConfig(d_f=64), steps=1)
    assert str(e.value) == "fit_autoencoder: expected features [N > 0, d_f=64], got [4, 32]"


def test_the_variant_fixes_the_code_width_the_caller_asks_for():
    """The distill stage asks the variant for its config: ``langsplat3`` answers 3 dims whatever d_z is set."""
    foundation = registry.get("feature_tokenizer", "foundation")
    langsplat3 = registry.get("feature_tokenizer", "langsplat3")
    assert foundation.configure(32, 8, 64) == FeatureAEConfig(d_f=32, d_z=8, hidden=64)
    assert langsplat3.configure(32, 16, 64) == FeatureAEConfig(d_f=32, d_z=3, hidden=64)
    assert (foundation.fixed_d_z, langsplat3.fixed_d_z) == (None, 3)
    assert foundation.configure() == FeatureAEConfig()
