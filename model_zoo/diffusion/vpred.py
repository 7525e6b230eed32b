"""The RGB-D diffusion's pure math (Sec. Instruction-controllable 4D Scene Generation): noising, v-target, pseudo-RGB.

Each function is a closed form from the paper; tests check the first three against diffusers' scheduler methods.
Legend: B batch, C channels, H x W image pixels.
"""

from __future__ import annotations

from typing import Any

import torch


def _per_sample(coef: torch.Tensor | float, like: torch.Tensor) -> torch.Tensor | float:
    """A ``[B]`` coefficient viewed as ``[B, 1, ..., 1]`` so it scales each sample of ``like``; scalars pass through."""
    if isinstance(coef, torch.Tensor) and coef.ndim == 1 and like.ndim > 1:
        return coef.to(like.dtype).view(-1, *([1] * (like.ndim - 1)))
    return coef


def alphas_sigmas(scheduler: Any, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(alpha_t, sigma_t) = (sqrt(alphas_cumprod[t]), sqrt(1 - alphas_cumprod[t])) of a scheduler, each ``[B]``.

    The variance-preserving coefficients of Eq. d_t = alpha_t d + sigma_t eps (alpha_t^2 + sigma_t^2 = 1).
    """
    abar = scheduler.alphas_cumprod.to(t.device)[t.long()]
    return abar.sqrt(), (1.0 - abar).sqrt()


def add_noise(
    d: torch.Tensor, eps: torch.Tensor, alpha_t: torch.Tensor | float, sigma_t: torch.Tensor | float
) -> torch.Tensor:
    """Noisy latent d_t = alpha_t d + sigma_t eps (Eq. d_t, Sec. Dual-condition RGB-D Latent Diffusion).

    ``alpha_t``/``sigma_t`` are scalars or ``[B]`` (one per sample of ``d``).
    """
    return _per_sample(alpha_t, d) * d + _per_sample(sigma_t, d) * eps


def v_target(
    d: torch.Tensor, eps: torch.Tensor, alpha_t: torch.Tensor | float, sigma_t: torch.Tensor | float
) -> torch.Tensor:
    """Denoising target v_t = alpha_t eps - sigma_t d (Eq. v_t, the v-prediction objective)."""
    return _per_sample(alpha_t, d) * eps - _per_sample(sigma_t, d) * d


def depth_to_rgb(depth_BHW: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Pseudo-RGB depth D^rgb ``[B, 3, H, W]`` in [-1, 1]: depth / max_depth (clamped to [0, 1]) replicated 3 times.

    Eq. z_D = E_vae(D^rgb): channel replication lets the RGB VAE encode depth unchanged.
    """
    unit_B1HW = (depth_BHW / max_depth).clamp(0.0, 1.0).unsqueeze(1)
    return (unit_B1HW * 2.0 - 1.0).expand(-1, 3, -1, -1).contiguous()


def rgb_to_depth(x_B3HW: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Depth ``[B, H, W]`` in metres from a decoded pseudo-RGB image: the mean of its 3 channels (Eq. D^_i), rescaled.

    Values outside [-1, 1] (a decoder may overshoot) are clamped, so depth stays in [0, max_depth].
    """
    unit_BHW = (x_B3HW.mean(dim=1).clamp(-1.0, 1.0) + 1.0) / 2.0
    return unit_BHW * max_depth
