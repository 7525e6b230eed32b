"""Shared scene builders for the rasterizer tests."""

from __future__ import annotations

import torch

from model_zoo.render import Camera


def pinhole(
    width: int, height: int, f: float, cx: float | None = None, cy: float | None = None, dtype=torch.float64, **kw
) -> Camera:
    """A camera at the world origin looking down +z (world frame == OpenCV camera frame)."""
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    K = torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(K, torch.eye(4, dtype=dtype), width, height, **kw)


def random_scene(
    n: int,
    camera: Camera,
    seed: int = 0,
    n_features: int = 0,
    depth: tuple[float, float] = (2.0, 8.0),
    log_scale: tuple[float, float] = (-2.5, -1.0),
    opacity: tuple[float, float] = (0.1, 0.9),
    dtype=torch.float64,
) -> dict[str, torch.Tensor]:
    """Gaussians spread through the camera's frustum (a little beyond its edges); keyword arguments of rasterize."""
    g = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=g, dtype=dtype) * (hi - lo) + lo

    K = camera.K_33.to(dtype)
    z = uniform(*depth, n)
    u = uniform(-0.1 * camera.width, 1.1 * camera.width, n)
    v = uniform(-0.1 * camera.height, 1.1 * camera.height, n)
    x, y = (u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z
    scene = {
        "means": torch.stack([x, y, z], dim=-1),
        "scales": torch.exp(uniform(*log_scale, n, 3)),
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "opacities": uniform(*opacity, n),
        "colors": torch.rand(n, 3, generator=g, dtype=dtype),
    }
    if n_features:
        scene["features"] = torch.randn(n, n_features, generator=g, dtype=dtype)
    return scene
