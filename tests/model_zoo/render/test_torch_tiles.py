import functools

import pytest
import torch

import model_zoo.render as render
from model_zoo.render import rasterize
from model_zoo.render.project import project_gaussians
from model_zoo.render.torch_tiles import bin_tiles, splat_tiles
from tests.model_zoo.render import pinhole, random_scene

GROUPS = ["means", "scales", "quats", "opacities", "colors", "features"]


@pytest.fixture
def small_chunks(monkeypatch):
    """Walk tile lists 2 Gaussians at a time, so transmittance is carried across chunks."""
    monkeypatch.setattr(render, "splat_tiles", functools.partial(splat_tiles, chunk=2))


def _loss(out, weights):
    w_rgb, w_depth, w_alpha, w_feat = weights
    return (
        (out.rgb * w_rgb).sum()
        + (out.depth * w_depth).sum()
        + (out.alpha * w_alpha).sum()
        + (out.features * w_feat).sum()
    )


def _tiny():
    cam = pinhole(12, 10, f=12.0)
    # Footprints of several pixels, opacities well clear of ALPHA_MAX, transmittance well above T_MIN.
    scene = random_scene(4, cam, seed=7, n_features=2, depth=(3.0, 5.0), log_scale=(-1.0, -0.3), opacity=(0.3, 0.7))
    g = torch.Generator().manual_seed(1)
    weights = [torch.randn(10, 12, *s, generator=g, dtype=torch.float64) for s in [(3,), (), (), (2,)]]
    return cam, scene, weights


@pytest.mark.parametrize("group", GROUPS)
def test_gradients_match_central_finite_differences(group, small_chunks):
    cam, scene, weights = _tiny()
    bg = torch.tensor([0.2, 0.5, 0.1], dtype=torch.float64)

    def loss_of(scene):
        return _loss(rasterize(**scene, camera=cam, background=bg, backend="torch", tile_size=4), weights)

    param = scene[group].clone().requires_grad_()
    loss_of(scene | {group: param}).backward()
    fd = torch.zeros_like(param)
    eps = 1e-6
    for i in range(param.numel()):
        plus, minus = param.detach().clone(), param.detach().clone()
        plus.view(-1)[i] += eps
        minus.view(-1)[i] -= eps
        fd.view(-1)[i] = (loss_of(scene | {group: plus}) - loss_of(scene | {group: minus})) / (2 * eps)
    assert fd.abs().max() > 1e-2  # the loss really depends on this group
    torch.testing.assert_close(param.grad, fd, rtol=1e-5, atol=1e-6)


def test_matches_dense_reference_values_and_gradients(small_chunks):
    cam = pinhole(40, 32, f=30.0, dtype=torch.float32)
    scene = random_scene(300, cam, seed=0, n_features=5, dtype=torch.float32)
    g = torch.Generator().manual_seed(2)
    weights = [torch.randn(32, 40, *s, generator=g) for s in [(3,), (), (), (5,)]]
    outs, grads = {}, {}
    for backend in ("torch", "dense"):
        leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
        outs[backend] = rasterize(**leaves, camera=cam, backend=backend, tile_size=8)
        _loss(outs[backend], weights).backward()
        grads[backend] = {k: v.grad for k, v in leaves.items()}
    t, d = outs["torch"], outs["dense"]
    assert t.n_visible == d.n_visible and 250 < t.n_visible < 300  # some fall outside the frame
    assert 0.3 < t.alpha.mean() < 0.95
    for field in ("rgb", "depth", "alpha", "features"):
        torch.testing.assert_close(getattr(t, field), getattr(d, field), atol=1e-5, rtol=1e-5)
    for k in scene:
        scale = grads["dense"][k].abs().max()
        torch.testing.assert_close(grads["torch"][k], grads["dense"][k], atol=1e-4 * scale, rtol=1e-3)


@pytest.mark.parametrize(("tile_size", "chunk"), [(16, 64), (5, 3), (64, 1000)])
def test_result_does_not_depend_on_tiling(tile_size, chunk):
    cam = pinhole(37, 23, f=25.0)
    scene = random_scene(120, cam, seed=5, n_features=3)
    ref = rasterize(**scene, camera=cam, backend="dense")
    p = project_gaussians(scene["means"], scene["scales"], scene["quats"], scene["opacities"], cam, eps2d=0.3)
    s = splat_tiles(p, torch.cat([scene["colors"], scene["features"]], -1), cam, tile_size=tile_size, chunk=chunk)
    assert s.n_visible == ref.n_visible
    torch.testing.assert_close(s.values_HWD, torch.cat([ref.rgb, ref.features], -1), atol=1e-12, rtol=0)
    torch.testing.assert_close(s.alpha_HW, ref.alpha, atol=1e-12, rtol=0)


def test_bin_tiles_lists_every_touched_tile_in_input_order():
    # Boxes (u0, u1, v0, v1) on a 3 x 2 grid of 4-px tiles: one spans 2 x 2 tiles, one sits in tile 5, one in tile 0.
    box = torch.tensor([[2, 5, 1, 6], [9, 10, 5, 7], [0, 0, 0, 0]])
    gauss, start, count = bin_tiles(box, tile_size=4, n_tiles_x=3, n_tiles=6)
    lists = [gauss[s : s + c].tolist() for s, c in zip(start.tolist(), count.tolist(), strict=True)]
    assert lists == [[0, 2], [0], [], [0], [0], [1]]


RED, BLUE = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]


def _pair(z_red, z_blue, opacity, n_red=1):
    zs = [z_red] * n_red + [z_blue]
    return dict(
        means=torch.tensor([[0.0, 0.0, z] for z in zs], dtype=torch.float64),
        scales=torch.full((len(zs), 3), 0.5, dtype=torch.float64),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * len(zs), dtype=torch.float64),
        opacities=torch.full((len(zs),), opacity, dtype=torch.float64),
        colors=torch.tensor([RED] * n_red + [BLUE], dtype=torch.float64),
    )


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_front_gaussian_occludes_the_back_one(backend):
    cam = pinhole(17, 17, f=10.0, cx=8.5, cy=8.5)  # pixel (8, 8) is centred on both means: alpha = opacity there
    red_front = rasterize(**_pair(3.0, 5.0, 0.9), camera=cam, backend=backend)
    blue_front = rasterize(**_pair(5.0, 3.0, 0.9), camera=cam, backend=backend)
    # C = a_1 c_1 + a_2 (1 - a_1) c_2 with a = 0.9.
    torch.testing.assert_close(red_front.rgb[8, 8], torch.tensor([0.9, 0.0, 0.09], dtype=torch.float64))
    torch.testing.assert_close(blue_front.rgb[8, 8], torch.tensor([0.09, 0.0, 0.9], dtype=torch.float64))
    torch.testing.assert_close(red_front.depth[8, 8], torch.tensor((0.9 * 3 + 0.09 * 5) / 0.99, dtype=torch.float64))


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_opaque_front_hides_the_back_and_sets_depth(backend):
    cam = pinhole(17, 17, f=10.0, cx=8.5, cy=8.5)
    # Three reds of alpha 0.95 leave T = 0.05^3 = 1.25e-4 >= T_MIN; blue would take it to 6.25e-6: compositing stops.
    out = rasterize(**_pair(3.0, 5.0, 0.95, n_red=3), camera=cam, backend=backend)
    torch.testing.assert_close(out.rgb[8, 8], torch.tensor([1 - 0.05**3, 0.0, 0.0], dtype=torch.float64))
    assert out.depth[8, 8].item() == pytest.approx(3.0, abs=1e-12)


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_features_equal_to_colors_render_exactly_like_rgb(backend):
    cam = pinhole(40, 32, f=30.0, dtype=torch.float32)
    scene = random_scene(200, cam, seed=4, dtype=torch.float32)
    out = rasterize(**scene, camera=cam, features=scene["colors"], backend=backend)
    assert out.alpha.max() > 0.5
    assert torch.equal(out.features, out.rgb)


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_culled_gaussians_do_not_contribute(backend):
    cam = pinhole(20, 16, f=16.0)
    kept = random_scene(5, cam, seed=9, depth=(2.0, 4.0), log_scale=(-2.0, -1.5))
    kept["means"][:, :2] *= 0.5  # well inside the frame
    culled = {
        "means": torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, 0.01], [0.0, 0.0, 2e3], [40.0, 0.0, 3.0], [0, -40.0, 3.0]]),
        "scales": torch.full((5, 3), 0.2),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * 5),
        "opacities": torch.full((5,), 0.9),
        "colors": torch.ones(5, 3),
    }
    both = {k: torch.cat([kept[k], culled[k].double()]) for k in kept}
    only = rasterize(**kept, camera=cam, backend=backend)
    out = rasterize(**both, camera=cam, backend=backend)
    assert (only.n_visible, out.n_visible) == (5, 5)
    torch.testing.assert_close(out.rgb, only.rgb, atol=0, rtol=0)


@pytest.mark.parametrize("backend", ["torch", "dense"])
def test_gaussian_just_outside_the_frame_still_reaches_in(backend):
    cam = pinhole(20, 16, f=16.0)
    # Centre 2 px left of the image; footprint ~ sqrt(2 ln(0.9 * 255)) * 2 px = 6.6 px.
    scene = {
        "means": torch.tensor([[(-2.0 - 10.0) / 16.0 * 4.0, 0.0, 4.0]], dtype=torch.float64),
        "scales": torch.full((1, 3), 0.5, dtype=torch.float64),
        "quats": torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        "opacities": torch.tensor([0.9], dtype=torch.float64),
        "colors": torch.ones(1, 3, dtype=torch.float64),
    }
    out = rasterize(**scene, camera=cam, backend=backend)
    assert out.n_visible == 1
    assert (out.alpha[:, :4] > 0).sum() > 0 and (out.alpha[:, 6:] == 0).all()
