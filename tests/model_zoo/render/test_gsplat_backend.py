import importlib.util
import sys

import pytest
import torch

from model_zoo.render import rasterize
from model_zoo.render.gsplat_backend import splat_gsplat
from tests.model_zoo.render import pinhole, random_scene

HAS_GSPLAT = torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def test_missing_gsplat_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # makes `import gsplat` raise ImportError
    cam = pinhole(8, 6, f=8.0, dtype=torch.float32)
    s = random_scene(3, cam, dtype=torch.float32)
    with pytest.raises(ImportError, match=r"pip install gdwm\[gpu\]"):
        rasterize(**s, camera=cam, backend="gsplat")
    with pytest.raises(ImportError, match=r"pip install gdwm\[gpu\]"):
        splat_gsplat(s["means"], s["scales"], s["quats"], s["opacities"], s["colors"], cam, 16, 0.3)


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GSPLAT, reason="needs CUDA and gsplat")
def test_gsplat_matches_the_torch_backend():
    cam = pinhole(64, 48, f=50.0, dtype=torch.float32)
    # Opacities below ALPHA_MAX: gsplat clamps at 0.999, we at 0.99, so keep every alpha below both.
    scene = random_scene(400, cam, seed=0, n_features=5, dtype=torch.float32, opacity=(0.1, 0.9))
    bg = torch.tensor([0.2, 0.3, 0.4])
    outs, grads = {}, {}
    for backend, device in (("torch", "cpu"), ("gsplat", "cuda")):
        leaves = {k: v.to(device).requires_grad_() for k, v in scene.items()}
        out = rasterize(**leaves, camera=cam, background=bg.to(device), backend=backend)
        (out.rgb.sum() + out.features.square().sum() + out.alpha.sum()).backward()
        outs[backend], grads[backend] = out, {k: v.grad.cpu() for k, v in leaves.items()}
    t, g = outs["torch"], outs["gsplat"]
    # gsplat rounds footprint radii up to whole pixels and culls against the image edge, we against pixel centres.
    assert abs(t.n_visible - g.n_visible) <= 0.05 * t.n_visible
    for field in ("rgb", "alpha", "features"):
        torch.testing.assert_close(getattr(g, field).cpu(), getattr(t, field), atol=1e-4, rtol=1e-4)
    solid = t.alpha > 0.05
    torch.testing.assert_close(g.depth.cpu()[solid], t.depth[solid], atol=1e-3, rtol=1e-4)
    for k in ("means", "opacities", "colors", "features"):
        scale = grads["torch"][k].abs().max()
        torch.testing.assert_close(grads["gsplat"][k], grads["torch"][k], atol=1e-3 * scale, rtol=1e-2)
