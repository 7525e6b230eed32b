"""Gaussian-image distribution alignment (Sec. Geometry-aware Gaussian Adapter, Gaussian--Image Distribution Alignment).

The world tokens' diagonal Gaussian ``N(mu_G, sigma_G^2 + eps)`` is pulled toward the image tokens'
``N(mu_I, sigma_I^2 + eps)``, whose statistics are a stop-gradient target:
``L_KL = (1/H) KL(N_G || N_I)`` (Eq. L_KL), added to the LM loss as ``lambda_KL * alpha(t) * L_KL``.

Variants: ``alignment/kl`` and ``alignment/none`` (the ablation without alignment). Both modules:
``forward(z_BFH, z_mask_BF, image_BMH, image_mask_BM, step) -> (weighted_loss, raw_kl)``, scalar tensors.

Legend: ``B`` batch, ``F`` world tokens (``K_f``), ``M`` image tokens, ``N`` any token count, ``H`` LLM hidden size.
"""

from __future__ import annotations

import torch
from torch import nn

from model_zoo.config import AlignmentConfig  # torch-free, so config composition never loads torch
from model_zoo.registry import register


def token_stats(tokens_BNH: torch.Tensor, mask_BN: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. mu_G / sigma_G^2 (and mu_I / sigma_I^2): mean and biased variance over the valid tokens, ``[B, H]`` each.

    A sample with no valid token gets zeros; padded tokens never enter the result, whatever their values.
    """
    valid_BN1 = mask_BN.unsqueeze(-1)
    count_B1 = mask_BN.sum(dim=1, keepdim=True).clamp_min(1).to(tokens_BNH.dtype)
    x_BNH = tokens_BNH.masked_fill(~valid_BN1, 0)
    mu_BH = x_BNH.sum(dim=1) / count_B1
    dev_BNH = (x_BNH - mu_BH.unsqueeze(1)).masked_fill(~valid_BN1, 0)
    return mu_BH, dev_BNH.square().sum(dim=1) / count_B1


def kl_diag_gaussians(mu_g: torch.Tensor, var_g: torch.Tensor, mu_i: torch.Tensor, var_i: torch.Tensor) -> torch.Tensor:
    """Closed-form ``KL(N(mu_g, diag var_g) || N(mu_i, diag var_i))``, summed over the last dim (Eq. L_KL before 1/H).

    ``0.5 * sum(log(var_i / var_g) + (var_g + (mu_g - mu_i)^2) / var_i - 1)``; variances must be > 0.
    """
    terms = var_i.log() - var_g.log() + (var_g + (mu_g - mu_i).square()) / var_i - 1
    return 0.5 * terms.sum(dim=-1)


def warmup(step: int, warmup_steps: int) -> float:
    """alpha(t) = min(1, t / warmup_steps), linear; ``warmup_steps == 0`` gives 1 at every step."""
    if warmup_steps < 0 or step < 0:
        raise ValueError(f"alignment warm-up: step and warmup_steps must be >= 0, got {step} and {warmup_steps}")
    return 1.0 if warmup_steps == 0 else min(1.0, step / warmup_steps)


class KLAlignment(nn.Module):
    """``lambda_KL * alpha(t) * L_KL`` with ``L_KL = (1/H) KL(N_G || N_I)`` (Eq. L_KL); image statistics detached.

    ``L_KL`` is the mean over the samples with at least one valid world token and one valid image token; the others
    are left out (0 if no sample qualifies). Statistics and KL are computed in float32 for bf16 inputs.
    """

    def __init__(self, cfg: AlignmentConfig) -> None:
        super().__init__()
        if cfg.eps <= 0 or cfg.warmup_steps < 0 or cfg.weight < 0:
            raise ValueError(f"alignment/kl: eps must be > 0, warmup_steps and weight >= 0, got {cfg}")
        self.cfg = cfg

    def forward(
        self,
        z_BFH: torch.Tensor,
        z_mask_BF: torch.Tensor,
        image_BMH: torch.Tensor,
        image_mask_BM: torch.Tensor,
        step: int,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if z_BFH.shape[0] != image_BMH.shape[0] or z_BFH.shape[-1] != image_BMH.shape[-1]:
            raise ValueError(
                f"alignment/kl: world tokens {list(z_BFH.shape)} and image tokens {list(image_BMH.shape)} "
                "differ in batch or hidden size"
            )
        mu_g, var_g = token_stats(z_BFH.float(), z_mask_BF)
        mu_i, var_i = token_stats(image_BMH.detach().float(), image_mask_BM)  # Eq. mu_I, sigma_I^2: sg(.)
        eps = self.cfg.eps
        kl_B = kl_diag_gaussians(mu_g, var_g + eps, mu_i, var_i + eps) / z_BFH.shape[-1]
        valid_B = z_mask_BF.any(dim=1) & image_mask_BM.any(dim=1)
        raw = torch.where(valid_B, kl_B, torch.zeros_like(kl_B)).sum() / valid_B.sum().clamp_min(1)
        return self.cfg.weight * warmup(step, self.cfg.warmup_steps) * raw, raw


class NoAlignment(nn.Module):
    """The ablation without alignment: both losses are exactly 0."""

    def forward(
        self,
        z_BFH: torch.Tensor,
        z_mask_BF: torch.Tensor,
        image_BMH: torch.Tensor,
        image_mask_BM: torch.Tensor,
        step: int,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        # a zero that requires grad when z does, so `loss.backward()` works even if this is the only term
        zero = torch.zeros((), dtype=torch.float32, device=z_BFH.device, requires_grad=z_BFH.requires_grad)
        return zero, zero.detach()


@register("alignment", "kl")
def build_kl(cfg: AlignmentConfig | None = None) -> KLAlignment:
    """KL alignment; ``AlignmentConfig()`` is its tiny flavor (it has no parameters)."""
    return KLAlignment(AlignmentConfig() if cfg is None else cfg)


@register("alignment", "none")
def build_none(cfg: AlignmentConfig | None = None) -> NoAlignment:
    """No alignment; ``cfg`` is ignored."""
    return NoAlignment()
