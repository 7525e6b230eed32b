"""Losses of foundation-feature distillation, as pure functions (Sec. Foundation-feature Gaussian Tokenizer).

Legend: ``V`` views, ``H, W`` pixels, ``C`` feature channels (``d_f``), ``N`` features.
"""

from __future__ import annotations

import torch


def l_distill(rendered_HWC: torch.Tensor, target_HWC: torch.Tensor, valid_HW: torch.Tensor) -> torch.Tensor:
    """Pixel-level L1 distillation loss (Eq. L_distill).

    ``L = 1 / sum_v |Omega_v| * sum_v sum_{u in Omega_v} || F^_v(u) - F_v(u) ||_1``: the L1 norm of each valid
    pixel's feature difference (summed over channels), averaged over the valid pixels of all views. Takes one view
    (``[H, W, C]`` with ``valid [H, W]``) or stacked views (``[V, H, W, C]`` with ``valid [V, H, W]``). Invalid
    pixels contribute nothing (not even NaNs); with no valid pixel the loss is 0, still connected to the graph.
    """
    if rendered_HWC.shape != target_HWC.shape or rendered_HWC.ndim not in (3, 4):
        raise ValueError(
            f"l_distill: rendered {list(rendered_HWC.shape)} and target {list(target_HWC.shape)} must both be "
            f"[H, W, C] or [V, H, W, C]"
        )
    if valid_HW.dtype != torch.bool or valid_HW.shape != rendered_HWC.shape[:-1]:
        raise ValueError(
            f"l_distill: valid must be bool {list(rendered_HWC.shape[:-1])}, "
            f"got {valid_HW.dtype} {list(valid_HW.shape)}"
        )
    per_pixel = (rendered_HWC[valid_HW] - target_HWC[valid_HW]).abs().sum(dim=-1)
    return per_pixel.sum() / max(per_pixel.numel(), 1)


def l_ae(recon_NC: torch.Tensor, f_NC: torch.Tensor) -> torch.Tensor:
    """Compact feature autoencoding loss (Eq. L_ae): ``1/N * sum_i || f~_i - f_i ||_2^2``."""
    if recon_NC.shape != f_NC.shape or recon_NC.ndim != 2 or recon_NC.shape[0] == 0:
        raise ValueError(
            f"l_ae: reconstruction {list(recon_NC.shape)} and features {list(f_NC.shape)} must both be [N > 0, C]"
        )
    return (recon_NC - f_NC).pow(2).sum(dim=-1).mean()
