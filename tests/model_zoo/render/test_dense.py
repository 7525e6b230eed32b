import math

import pytest
import torch

from model_zoo.render import rasterize
from model_zoo.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN, project_gaussians
from tests.model_zoo.render import pinhole, random_scene


def _loop_render(scene, cam, eps2d=0.3):
    """3DGS's per-pixel loop, written out literally (one pixel, one Gaussian at a time)."""
    p = project_gaussians(scene["means"], scene["scales"], scene["quats"], scene["opacities"], cam, eps2d)
    order = [i for i in torch.argsort(p.depth_N).tolist() if p.valid_N[i]]
    rgb = torch.zeros(cam.height, cam.width, 3, dtype=torch.float64)
    alpha_img = torch.zeros(cam.height, cam.width, dtype=torch.float64)
    for v in range(cam.height):
        for u in range(cam.width):
            T = 1.0
            for i in order:
                dx, dy = u + 0.5 - p.means2d_N2[i, 0].item(), v + 0.5 - p.means2d_N2[i, 1].item()
                a, b, c = p.conic_N3[i].tolist()
                power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                alpha = min(ALPHA_MAX, p.opacity_N[i].item() * math.exp(-power))
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) < T_MIN:
                    break
                rgb[v, u] += alpha * T * scene["colors"][i]
                alpha_img[v, u] += alpha * T
                T *= 1 - alpha
    return rgb, alpha_img


@pytest.mark.parametrize(
    ("n", "log_scale", "opacity"),
    [(6, (-0.5, 0.3), (0.1, 0.9)), (12, (0.0, 0.7), (0.9, 1.0))],
    ids=["translucent", "opaque-early-stop"],
)
def test_dense_reference_equals_the_literal_per_pixel_loop(n, log_scale, opacity):
    cam = pinhole(9, 7, f=8.0)
    scene = random_scene(n, cam, seed=3, opacity=opacity, log_scale=log_scale, depth=(2.0, 4.0))
    out = rasterize(**scene, camera=cam, backend="dense")
    rgb, alpha = _loop_render(scene, cam)
    assert alpha.max() > 0.5
    torch.testing.assert_close(out.rgb, rgb, atol=1e-12, rtol=0)
    torch.testing.assert_close(out.alpha, alpha, atol=1e-12, rtol=0)
