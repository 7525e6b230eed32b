"""Distillation of one scene (Sec. Foundation-feature Gaussian Tokenizer): the frozen features of every view
(Eq. F_v = E_F(I_v)), the compact autoencoder on pixel features (Eq. L_ae), per-Gaussian codes optimised so the
rendered decoded features match (Eqs. f_i = D_F(z_i), F_v(u) = sum_i w_iu f_i, L_distill), and the held-out
comparison with the per-scene mean feature.

Legend: N canonical Gaussians, P = H*W pixels of a view, C = d_f feature dims, Z = d_z code dims.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from model_zoo.distill_math import l_distill
from model_zoo.encoders.base import FoundationEncoder
from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder, fit_autoencoder
from pipelines.distill.config import DistillConfig
from pipelines.distill.field import Field, view_weights
from pipelines.recon.init import View


@dataclass
class ViewFeatures:
    """One view's supervision: its compositing weights over the canonical rows and E_F's features where defined."""

    view: View
    held: bool
    """A held-out view (``views.json`` of the reconstruction): evaluated, never trained on."""
    weights_PN: torch.Tensor
    """Sparse CSR compositing weights w_iu."""
    target_HWC: torch.Tensor
    valid_HW: torch.Tensor
    """Omega_v: E_F defined and the Gaussians' alpha at least ``min_alpha``."""

    @functools.cached_property
    def weights_NP(self) -> torch.Tensor:
        """The weights transposed, as CSR: made once for a view's every step (``render_features``)."""
        return self.weights_PN.t().to_sparse_csr()


@dataclass
class Distilled:
    ae: FeatureAutoencoder
    """E_z / D_F, frozen after L_ae."""
    codes_NZ: torch.Tensor
    ae_losses: list[float]
    l_distill_final: float
    """The last step's L_distill (NaN without steps)."""
    mean_feature_C: torch.Tensor
    """The baseline: the mean pixel feature of the training views' samples."""


class _WeightedSum(torch.autograd.Function):
    """``W @ F`` whose backward is ``W^T @ grad`` with W^T given: torch's own backward transposes the sparse W on
    every call, most of a distillation step's time on CPU. The same gradient, bit for bit (its transpose is this
    CSR one)."""

    @staticmethod
    def forward(ctx, weights_PN: torch.Tensor, weights_NP: torch.Tensor, feats_NC: torch.Tensor) -> torch.Tensor:
        ctx.weights_NP = weights_NP
        return weights_PN @ feats_NC

    @staticmethod
    def backward(ctx, grad_PC: torch.Tensor):
        return None, None, ctx.weights_NP @ grad_PC


def render_features(
    weights_PN: torch.Tensor, feats_NC: torch.Tensor, hw: tuple[int, int], weights_NP: torch.Tensor | None = None
) -> torch.Tensor:
    """Eq. F_v(u) = sum_i w_iu D_F(z_i), with the view's precomputed weights: ``[H, W, C]``. ``weights_NP``, their
    transpose (``ViewFeatures.weights_NP``), makes the gradient of a view rendered many times cheap."""
    if weights_NP is not None and feats_NC.requires_grad:
        return _WeightedSum.apply(weights_PN, weights_NP, feats_NC).reshape(*hw, -1)
    return (weights_PN @ feats_NC).reshape(*hw, -1)


def encode_views(
    encoder: FoundationEncoder,
    field: Field,
    views: list[View],
    held_set: set[tuple[int, str]],
    cfg: DistillConfig,
    progress: Callable[[int, int], None],
) -> list[ViewFeatures]:
    """Every view's features and weights; ``progress(done, total)`` after each."""
    out = []
    for i, v in enumerate(views):
        h, w = v.rgb_HW3.shape[:2]
        target = encoder.encode((v.rgb_HW3 * 255).round().astype(np.uint8), out_hw=(h, w)).float()
        weights, _ = view_weights(field, v, cfg.min_weight)
        alpha = (weights @ torch.ones(weights.shape[1], 1)).reshape(h, w)
        valid = encoder.valid_mask(h, w, out_hw=(h, w)) & (alpha >= cfg.min_alpha)
        out.append(ViewFeatures(v, (v.frame, v.camera) in held_set, weights, target, valid))
        progress(i + 1, len(views))
    return out


def sample_pixels(train: list[ViewFeatures], per_view: int, gen: torch.Generator) -> torch.Tensor:
    """``[M, C]``: up to ``per_view`` random valid pixel features of each training view (the L_ae data)."""
    samples = []
    for t in train:
        pix = t.target_HWC[t.valid_HW]
        take = torch.randperm(len(pix), generator=gen)[:per_view]
        samples.append(pix[take])
    return torch.cat(samples)


def initial_features(n: int, train: list[ViewFeatures], mean_feature_C: torch.Tensor) -> torch.Tensor:
    """``[N, C]``: each Gaussian's features of the pixels it covers, weighted by w_iu; the mean where it covers none."""
    acc, mass = torch.zeros(n, mean_feature_C.shape[0]), torch.zeros(n)
    for t in train:
        wt = t.weights_NP
        acc += wt @ (t.target_HWC * t.valid_HW[..., None]).reshape(-1, t.target_HWC.shape[-1])
        mass += (wt @ t.valid_HW.reshape(-1, 1).float()).squeeze(1)
    return torch.where(mass[:, None] > 1e-6, acc / mass.clamp(min=1e-6)[:, None], mean_feature_C)


def distill_codes(
    n: int,
    train: list[ViewFeatures],
    ae_cfg: FeatureAEConfig,
    cfg: DistillConfig,
    log: Callable[[int, dict[str, float]], None],
    where: str,
) -> Distilled:
    """Fit E_z / D_F with L_ae, then optimise the ``n`` codes with Adam on L_distill over ``cfg.views_per_step``
    random training views a step; ``log(step, {"l_ae": ...})`` every 10 L_ae steps, then ``log(step, {"l_distill":
    ...})`` every 10 steps and at the last. ``where`` names the scene in errors."""
    gen = torch.Generator().manual_seed(cfg.seed)
    f_train = sample_pixels(train, cfg.ae_pixels_per_view, gen)
    ae, ae_losses = fit_autoencoder(f_train, ae_cfg, steps=cfg.ae_steps, lr=cfg.ae_lr, seed=cfg.seed)
    for step in range(0, len(ae_losses), 10):
        log(step, {"l_ae": ae_losses[step]})
    ae.requires_grad_(False)
    mean_feature = f_train.mean(0)
    z = ae.encode(initial_features(n, train, mean_feature)).detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=cfg.distill_lr)
    loss = torch.tensor(float("nan"))
    for step in range(cfg.distill_steps):
        decoded = ae.decode(z)
        batch = [train[i] for i in torch.randperm(len(train), generator=gen)[: cfg.views_per_step].tolist()]
        loss = l_distill(
            torch.stack([render_features(t.weights_PN, decoded, t.target_HWC.shape[:2], t.weights_NP) for t in batch]),
            torch.stack([t.target_HWC for t in batch]),
            torch.stack([t.valid_HW for t in batch]),
        )
        if not torch.isfinite(loss):
            raise FloatingPointError(f"{where}: L_distill is {loss.item()} at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 10 == 0 or step == cfg.distill_steps - 1:
            log(step, {"l_distill": loss.item()})
    return Distilled(ae, z.detach(), ae_losses, loss.item(), mean_feature)


def heldout_l1(d: Distilled, held: list[ViewFeatures]) -> tuple[list[float], list[float]]:
    """L1 over Omega_v of each held-out view: (the distilled field, the per-scene mean feature)."""
    with torch.no_grad():
        decoded = d.ae.decode(d.codes_NZ)
        ours = [
            float(l_distill(render_features(t.weights_PN, decoded, t.target_HWC.shape[:2]), t.target_HWC, t.valid_HW))
            for t in held
        ]
        base = [float(l_distill(d.mean_feature_C.expand_as(t.target_HWC), t.target_HWC, t.valid_HW)) for t in held]
    return ours, base
