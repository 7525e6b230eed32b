"""Settings of the reconstruct stage (``conf/stage/reconstruct/*.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated

from annotated_types import Ge, Gt, Interval

from gdwm.api import SEED


class Backend(StrEnum):
    auto = "auto"
    torch = "torch"
    gsplat = "gsplat"


@dataclass
class ReconstructConfig:
    """LiDAR-initialised 3DGS per scene; defaults are the CPU settings of synthetic_mini."""

    iterations: Annotated[int, Ge(1)] = 800
    """Optimisation steps (one training view per step)."""
    max_gaussians: Annotated[int, Ge(1)] = 30000
    """Cap on initial Gaussians after voxel down-sampling of the aggregated LiDAR."""
    voxel_m: Annotated[float, Gt(0)] = 0.15
    """Voxel size of the LiDAR down-sampling, metres."""
    drop_moving: bool = True
    """Model moving objects' returns in their own box frames (posed per frame) instead of the static field."""
    moving_speed_mps: Annotated[float, Ge(0)] = 0.5
    """Speed above which a box counts as moving."""
    holdout_every: Annotated[int, Ge(0)] = 8
    """Every n-th (frame, camera) view is held out for evaluation (0 = none)."""
    ssim_weight: Annotated[float, Interval(ge=0, le=1)] = 0.2
    """lambda of (1 - lambda) L1 + lambda D-SSIM."""
    depth_weight: Annotated[float, Ge(0)] = 0.05
    """Weight of the L1 loss between rendered depth and projected LiDAR depth (0 = off)."""
    lr_means: Annotated[float, Gt(0)] = 0.00016
    """Adam lr of the centres, times the scene extent (3DGS convention)."""
    lr_scales: Annotated[float, Gt(0)] = 0.005
    """Adam lr of the log-scales."""
    lr_quats: Annotated[float, Gt(0)] = 0.001
    """Adam lr of the rotations."""
    lr_opacities: Annotated[float, Gt(0)] = 0.05
    """Adam lr of the opacity logits."""
    lr_colors: Annotated[float, Gt(0)] = 0.01
    """Adam lr of the colours (logits)."""
    densify_from: Annotated[int, Ge(0)] = 100
    """First step of densification."""
    densify_until: Annotated[int, Ge(0)] = 600
    """Last step of densification."""
    densify_every: Annotated[int, Ge(1)] = 50
    """Densify / prune every n steps."""
    densify_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.05
    """Share of Gaussians with the largest mean positional gradient cloned (small) or split (large) per round."""
    max_total_gaussians: Annotated[int, Ge(1)] = 60000
    """Densification stops growing past this many Gaussians."""
    split_scale_m: Annotated[float, Gt(0)] = 0.3
    """Gaussians larger than this (max scale, metres) are split rather than cloned."""
    prune_opacity: Annotated[float, Interval(ge=0, lt=1)] = 0.01
    """Gaussians less opaque than this are pruned."""
    opacity_reset_every: Annotated[int, Ge(0)] = 0
    """Reset opacities to a low value every n steps (0 = never: at a few hundred steps the reset costs more than
    the floaters it removes; 21.1 vs 22.1 dB held-out on synthetic_mini scene-0000)."""
    min_psnr_db: Annotated[float, Ge(0)] = 18.0
    """Frames whose held-out PSNR falls below this are excluded and recorded in the manifest."""
    background: Annotated[list[float] | None, Interval(ge=0, le=1)] = None
    """Fixed background RGB; null learns one colour per scene."""
    seed: Annotated[int, SEED] = 0
    """Seed of view order and initialisation."""
    backend: Backend = Backend.auto
    """Rasterizer backend: ``auto`` (gsplat on CUDA when it imports, else torch), ``torch`` or ``gsplat``."""
