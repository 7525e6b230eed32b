"""Differentiable 3D Gaussian rasterizer: one interface, backends ``torch`` (CPU tiles), ``gsplat`` (CUDA), ``dense``.

    out = rasterize(means, scales, quats, opacities, colors, camera, features=feats)
    out.rgb  # [H, W, 3]; out.depth, out.alpha [H, W]; out.features [H, W, C]

Legend: N Gaussians, C feature channels, H x W image. ``torch`` and ``dense`` share ``project.py`` (EWA projection,
culling); gsplat projects with the same conventions in CUDA. All share this file's input checks and post-processing
(background, depth normalisation), so backends differ only in how they project and composite.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from model_zoo.render.camera import Camera
from model_zoo.render.dense import splat_dense
from model_zoo.render.project import Splatted, project_gaussians
from model_zoo.render.torch_tiles import splat_tiles, splat_weights

__all__ = ["BACKENDS", "Camera", "RenderOutput", "composite_weights", "rasterize"]

BACKENDS = ("auto", "torch", "gsplat", "dense")


@dataclass
class RenderOutput:
    """One rendered view."""

    rgb: Tensor
    """``[H, W, 3]`` colours composited over ``background``."""
    depth: Tensor
    """``[H, W]`` expected camera-z depth ``sum_i w_i z_i / max(alpha, 1e-6)``; 0 where nothing was drawn."""
    alpha: Tensor
    """``[H, W]`` accumulated opacity ``sum_i w_i``."""
    features: Tensor | None
    """``[H, W, C]`` features composited with the same weights ``w_i`` as ``rgb``, no background."""
    n_visible: int
    """Gaussians that survived culling (depth range, opacity, footprint on the image)."""


_SHAPES = {"scales": "[N, 3]", "quats": "[N, 4]", "opacities": "[N]", "colors": "[N, 3]", "background": "[3]"}


def _check_inputs(named: dict[str, Tensor | None]) -> None:
    """Shapes, device/dtype agreement, finiteness; errors name the argument and its shape."""
    means = named["means"]
    if not isinstance(means, Tensor) or means.dim() != 2 or means.shape[1] != 3:
        got = tuple(means.shape) if isinstance(means, Tensor) else type(means).__name__
        raise ValueError(f"rasterize: means must have shape [N, 3], got {got}")
    n = means.shape[0]
    for name, t in named.items():
        if t is None or name == "means":
            continue
        if not isinstance(t, Tensor):
            raise ValueError(f"rasterize: {name} must be a tensor, got {type(t).__name__}")
        if name == "features":
            ok, want = t.dim() == 2 and t.shape[0] == n, "[N, C]"
        else:
            want = _SHAPES[name]
            ok = tuple(t.shape) == tuple(n if d == "N" else int(d) for d in want.strip("[]").split(", "))
        if not ok:
            raise ValueError(f"rasterize: {name} must have shape {want} with N={n} (from means), got {tuple(t.shape)}")
        if t.device != means.device or t.dtype != means.dtype:
            raise ValueError(f"rasterize: {name} is {t.dtype} on {t.device}, means is {means.dtype} on {means.device}")
    for name, t in named.items():
        if t is not None and not bool(torch.isfinite(t).all()):
            raise ValueError(f"rasterize: {name} (shape {tuple(t.shape)}) contains NaN or inf")
    if n and not bool((named["scales"] > 0).all()):
        raise ValueError("rasterize: scales must be > 0 (standard deviations, not log-scales)")
    if n and not bool((named["quats"].norm(dim=-1) > 0).all()):
        raise ValueError("rasterize: quats has an all-zero row (cannot normalise)")


@functools.cache
def _gsplat_imports() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def _pick_backend(backend: str, means: Tensor) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: unknown backend {backend!r}; choose one of {list(BACKENDS)}")
    if backend != "auto":
        return backend
    return "gsplat" if means.is_cuda and torch.cuda.is_available() and _gsplat_imports() else "torch"


def rasterize(
    means: Tensor,
    scales: Tensor,
    quats: Tensor,
    opacities: Tensor,
    colors: Tensor,
    camera: Camera,
    features: Tensor | None = None,
    background: Tensor | None = None,
    backend: str = "auto",
    tile_size: int = 16,
    eps2d: float = 0.3,
) -> RenderOutput:
    """Render N Gaussians into ``camera`` (3DGS: EWA projection, depth sort, front-to-back alpha compositing).

    Args:
        means: ``[N, 3]`` world centres.
        scales: ``[N, 3]`` standard deviations (> 0) along the Gaussian's own axes.
        quats: ``[N, 4]`` rotations (w, x, y, z), normalised inside.
        opacities: ``[N]`` in [0, 1].
        colors: ``[N, 3]``.
        camera: intrinsics, world→camera (OpenCV), size, near/far.
        features: ``[N, C]`` extra channels composited with the same weights as ``colors``.
        background: ``[3]`` colour behind the Gaussians (default black).
        backend: ``auto`` (gsplat for CUDA tensors when installed, else torch), ``torch``, ``gsplat`` or ``dense``.
        tile_size: tile edge in pixels (torch and gsplat backends).
        eps2d: low-pass added to the 2D covariance's diagonal (3DGS), in pixels^2.
    """
    named = {"means": means, "scales": scales, "quats": quats, "opacities": opacities, "colors": colors}
    named |= {"features": features, "background": background}
    _check_inputs(named)
    name = _pick_backend(backend, means)
    if tile_size <= 0:
        raise ValueError(f"rasterize: tile_size must be positive, got {tile_size}")
    cam = camera.to(means.device, means.dtype)
    values = colors if features is None else torch.cat([colors, features], dim=-1)

    if name == "gsplat":
        from model_zoo.render.gsplat_backend import splat_gsplat

        s: Splatted = splat_gsplat(means, scales, quats, opacities, values, cam, tile_size, eps2d)
    else:
        projected = project_gaussians(means, scales, quats, opacities, cam, eps2d)
        s = splat_tiles(projected, values, cam, tile_size) if name == "torch" else splat_dense(projected, values, cam)

    values_HWD, alpha = s.values_HWD, s.alpha_HW
    if (
        torch.is_grad_enabled()
        and not alpha.requires_grad
        and any(t.requires_grad for t in named.values() if t is not None)
    ):
        # Nothing visible: keep the graph connected so loss.backward() still works (all gradients zero).
        zero = sum(t.sum() for t in named.values() if t is not None and t.requires_grad) * 0
        values_HWD, alpha = values_HWD + zero, alpha + zero
    rgb = values_HWD[..., :3]
    if background is not None:
        rgb = rgb + (1.0 - alpha)[..., None] * background
    depth = s.depth_HW / alpha.clamp(min=1e-6)
    feats = values_HWD[..., 3:] if features is not None else None
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, features=feats, n_visible=s.n_visible)


def composite_weights(
    means: Tensor,
    scales: Tensor,
    quats: Tensor,
    opacities: Tensor,
    camera: Camera,
    tile_size: int = 16,
    eps2d: float = 0.3,
) -> Tensor:
    """Sparse ``[H*W, N]`` compositing weights of fixed Gaussians in ``camera`` (no gradient).

    ``(W @ values).reshape(H, W, -1)`` equals ``rasterize(..., features=values).features``: what distillation
    needs when only per-Gaussian values are optimised.
    """
    _check_inputs({"means": means, "scales": scales, "quats": quats, "opacities": opacities})
    with torch.no_grad():
        cam = camera.to(means.device, means.dtype)
        return splat_weights(project_gaussians(means, scales, quats, opacities, cam, eps2d), cam, tile_size)
