"""Photometric losses and metrics of the reconstruction (3DGS: (1 - lambda) L1 + lambda D-SSIM)."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F


@functools.cache
def _window(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :])[None, None]


def ssim(a_HW3: torch.Tensor, b_HW3: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004, Gaussian window 11 / 1.5, C1 = 0.01^2, C2 = 0.03^2), differentiable.

    Written here (about 15 lines) because none of our dependencies ships a differentiable SSIM.
    """
    a = a_HW3.permute(2, 0, 1)[:, None]
    b = b_HW3.permute(2, 0, 1)[:, None]
    w = _window(size, sigma).to(a)
    pad = size // 2
    mu_a, mu_b = F.conv2d(a, w, padding=pad), F.conv2d(b, w, padding=pad)
    var_a = F.conv2d(a * a, w, padding=pad) - mu_a**2
    var_b = F.conv2d(b * b, w, padding=pad) - mu_b**2
    cov = F.conv2d(a * b, w, padding=pad) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.mean()


def psnr(a_HW3: torch.Tensor, b_HW3: torch.Tensor) -> float:
    mse = torch.mean((a_HW3.clamp(0, 1) - b_HW3) ** 2).item()
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()


def photometric(pred_HW3: torch.Tensor, gt_HW3: torch.Tensor, ssim_weight: float) -> torch.Tensor:
    l1 = (pred_HW3 - gt_HW3).abs().mean()
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(pred_HW3, gt_HW3))
