import pytest
import torch

from model_zoo.render import BACKENDS, rasterize
from tests.model_zoo.render import pinhole, random_scene


@pytest.fixture
def scene():
    cam = pinhole(16, 12, f=14.0, dtype=torch.float32)
    return cam, random_scene(8, cam, seed=1, n_features=2, dtype=torch.float32)


def test_outputs_have_the_documented_shapes(scene):
    cam, s = scene
    out = rasterize(**s, camera=cam)
    assert (tuple(out.rgb.shape), tuple(out.depth.shape), tuple(out.alpha.shape)) == ((12, 16, 3), (12, 16), (12, 16))
    assert tuple(out.features.shape) == (12, 16, 2)
    assert rasterize(**(s | {"features": None}), camera=cam).features is None


def test_background_fills_what_alpha_leaves_and_features_get_none(scene):
    cam, s = scene
    bg = torch.tensor([0.1, 0.6, 0.3])
    plain = rasterize(**s, camera=cam)
    over = rasterize(**s, camera=cam, background=bg)
    torch.testing.assert_close(over.rgb, plain.rgb + (1 - plain.alpha)[..., None] * bg)
    assert torch.equal(over.features, plain.features)


def test_depth_is_normalised_by_alpha_and_zero_where_empty(scene):
    cam, s = scene
    one_depth = s | {"means": s["means"] * torch.tensor([1.0, 1.0, 0.0]) + torch.tensor([0.0, 0.0, 3.0])}
    out = rasterize(**one_depth, camera=cam)
    assert (out.alpha == 0).any() and (out.alpha > 0.1).any()
    drawn = out.alpha > 0
    torch.testing.assert_close(out.depth[drawn], torch.full_like(out.depth[drawn], 3.0))
    assert (out.depth[~drawn] == 0).all()


def test_auto_picks_torch_on_cpu_and_unknown_backend_names_the_choices(scene):
    cam, s = scene
    torch.testing.assert_close(rasterize(**s, camera=cam).rgb, rasterize(**s, camera=cam, backend="torch").rgb)
    with pytest.raises(
        ValueError, match=r"unknown backend 'cuda'; choose one of \['auto', 'torch', 'gsplat', 'dense'\]"
    ):
        rasterize(**s, camera=cam, backend="cuda")
    assert BACKENDS == ("auto", "torch", "gsplat", "dense")


def test_nothing_visible_still_backpropagates_zeros(scene):
    cam, s = scene
    behind = {k: v.clone().requires_grad_() for k, v in (s | {"means": s["means"] * -1}).items()}
    out = rasterize(**behind, camera=cam)
    assert out.n_visible == 0 and (out.alpha == 0).all()
    out.rgb.sum().backward()
    assert behind["means"].grad is not None and (behind["means"].grad == 0).all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"means": "nan"}, r"means \(shape \(8, 3\)\) contains NaN or inf"),
        ({"means": torch.zeros(8, 2)}, r"means must have shape \[N, 3\], got \(8, 2\)"),
        ({"scales": torch.ones(8, 2)}, r"scales must have shape \[N, 3\] with N=8 \(from means\), got \(8, 2\)"),
        ({"quats": torch.ones(7, 4)}, r"quats must have shape \[N, 4\] with N=8 \(from means\), got \(7, 4\)"),
        ({"opacities": torch.ones(8, 1)}, r"opacities must have shape \[N\] with N=8 \(from means\), got \(8, 1\)"),
        ({"colors": torch.ones(8, 4)}, r"colors must have shape \[N, 3\] with N=8 \(from means\), got \(8, 4\)"),
        ({"features": torch.ones(9, 2)}, r"features must have shape \[N, C\] with N=8 \(from means\), got \(9, 2\)"),
        ({"background": torch.ones(4)}, r"background must have shape \[3\] with N=8 \(from means\), got \(4,\)"),
        ({"scales": -torch.ones(8, 3)}, r"scales must be > 0"),
        ({"quats": torch.zeros(8, 4)}, r"quats has an all-zero row"),
        ({"colors": torch.ones(8, 3, dtype=torch.float64)}, r"colors is torch.float64 on cpu, means is torch.float32"),
        ({"opacities": [0.5] * 8}, r"opacities must be a tensor, got list"),
    ],
)
def test_bad_input_names_the_argument_and_shape(scene, change, message):
    cam, s = scene
    if change.get("means") == "nan":
        change = {"means": s["means"].clone()}
        change["means"][3, 1] = float("nan")
    with pytest.raises(ValueError, match=message):
        rasterize(**(s | change), camera=cam)


def test_composite_weights_reproduce_rendered_features():
    from model_zoo.render import Camera, composite_weights, rasterize

    g = torch.Generator().manual_seed(3)
    n = 300
    means = torch.randn(n, 3, generator=g) * torch.tensor([2.0, 1.0, 1.0]) + torch.tensor([0.0, 0.0, 6.0])
    scales = torch.rand(n, 3, generator=g) * 0.2 + 0.05
    quats = torch.randn(n, 4, generator=g)
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g)
    feats = torch.randn(n, 5, generator=g)
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]])
    cam = Camera(K, torch.eye(4), 48, 32)
    out = rasterize(means, scales, quats, opac, colors, cam, features=feats)
    W = composite_weights(means, scales, quats, opac, cam)
    assert W.shape == (48 * 32, n) and W._nnz() > 0
    # built coalesced without a coalesce: what coalescing the same entries gives (sorted, no pair twice)
    again = torch.sparse_coo_tensor(W.indices().flip(1), W.values().flip(0), W.shape).coalesce()
    assert W.is_coalesced() and torch.equal(again.indices(), W.indices()) and torch.equal(again.values(), W.values())
    torch.testing.assert_close(torch.sparse.mm(W, feats).reshape(32, 48, 5), out.features, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(torch.sparse.sum(W, dim=1).to_dense().reshape(32, 48), out.alpha, atol=1e-5, rtol=1e-5)
