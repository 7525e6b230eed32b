"""Dense reference rasterizer: every pixel against every Gaussian. The correctness oracle for tests and benchmarks.

Legend: P pixels, N Gaussians (depth-sorted), E channels (values, depth, 1); ``alpha_PN`` per-pixel opacities.
It shares only the projection (``project.py``) with the fast backends: no tiles, no footprint boxes, no chunked
transmittance; a Gaussian's reach is decided per pixel by the ``ALPHA_MIN`` skip alone.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from model_zoo.render.camera import Camera
from model_zoo.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected, Splatted


def composite_pixels(
    pix_P2: Tensor, means2d_N2: Tensor, conic_N3: Tensor, opacity_N: Tensor, values_NE: Tensor
) -> Tensor:
    """Front-to-back alpha compositing (3DGS Eq. 3): ``sum_i w_i v_i`` with ``w_i = alpha_i prod_{j<i} (1 - alpha_j)``.

    ``alpha_i = min(ALPHA_MAX, o_i exp(-d^T conic d / 2))`` at the pixel centre, zero below ``ALPHA_MIN``; a Gaussian
    counts only while the transmittance after it stays >= ``T_MIN`` (3DGS's early stop). Returns ``[P, E]``.
    """
    dx = pix_P2[:, 0, None] - means2d_N2[None, :, 0]
    dy = pix_P2[:, 1, None] - means2d_N2[None, :, 1]
    a, b, c = conic_N3.unbind(-1)
    power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha_PN = torch.clamp(opacity_N * torch.exp(-power), max=ALPHA_MAX)
    alpha_PN = torch.where(alpha_PN >= ALPHA_MIN, alpha_PN, torch.zeros_like(alpha_PN))
    log_1m = torch.log1p(-alpha_PN)
    log_T_incl = torch.cumsum(log_1m, dim=1)
    w_PN = alpha_PN * torch.exp(log_T_incl - log_1m) * (log_T_incl >= math.log(T_MIN))
    return w_PN @ values_NE


def splat_dense(projected: Projected, values_ND: Tensor, camera: Camera, pair_budget: int = 8_000_000) -> Splatted:
    """Composite every pixel against all depth-valid Gaussians, ``pair_budget`` pixel-Gaussian pairs at a time.

    Pixel chunks are activation-checkpointed when gradients are needed, so memory stays O(pair_budget) at the cost
    of recomputing each chunk's forward in backward.
    """
    p, W, H = projected, camera.width, camera.height
    idx = p.valid_N.nonzero().squeeze(1)
    idx = idx[torch.argsort(p.depth_N[idx].detach(), stable=True)]
    ones = torch.ones_like(p.depth_N[idx, None])
    values_NE = torch.cat([values_ND[idx], p.depth_N[idx, None], ones], dim=-1)  # values, z, 1 -> alpha
    means2d, conic, opacity = p.means2d_N2[idx], p.conic_N3[idx], p.opacity_N[idx]

    vs, us = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pix_P2 = torch.stack([us.reshape(-1), vs.reshape(-1)], dim=-1).to(means2d) + 0.5
    step = max(1, pair_budget // max(1, idx.numel()))
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (values_NE, means2d, conic, opacity))
    outs = []
    for s in range(0, pix_P2.shape[0], step):
        args = (pix_P2[s : s + step], means2d, conic, opacity, values_NE)
        outs.append(checkpoint(composite_pixels, *args, use_reentrant=False) if needs_grad else composite_pixels(*args))
    out_HWE = torch.cat(outs).reshape(H, W, -1)
    n_visible = int(p.visible_N.sum())
    return Splatted(out_HWE[..., :-2], out_HWE[..., -2], out_HWE[..., -1], n_visible)
