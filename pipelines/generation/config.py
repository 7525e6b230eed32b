"""Settings of the generation stages (``conf/stage/{diffusion_vae,diffusion}/``). The model's own config is
``model_zoo.diffusion.rgbd_dual.DiffusionConfig`` (``conf/model/diffusion/``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from annotated_types import Ge, Gt, Interval

from gdwm.api import SEED

VIEW_TARGETS = {
    "cameras": "projects the Gaussians into the target camera",
    "images": "its targets and references are camera images",
    "depth": "its depth targets",
    "ego_poses": "its shift and future targets move the camera along the ego path",
}
"""Dataset tables the generation stages on camera views read (``gdwm.stage.stage(needs=...)``)."""


@dataclass
class VaeStageConfig:
    """The tiny flavor's VAE, fitted once to the training views (RGB and pseudo-RGB depth) and then frozen."""

    steps: Annotated[int, Ge(0)] = 300
    """Adam steps."""
    lr: Annotated[float, Gt(0)] = 1e-3
    """Adam learning rate."""
    views_per_scene: Annotated[int, Ge(1)] = 60
    """Training (frame, camera) views per scene, each giving one RGB and one depth image."""
    seed: Annotated[int, SEED] = 0
    """Seed of view sampling and of the fit."""


@dataclass
class DiffusionStageConfig:
    """Stage 3: the UNet with v-prediction on shift, future and weather targets of the training scenes."""

    steps: Annotated[int, Ge(0)] = 600
    """Optimiser steps."""
    batch_size: Annotated[int, Ge(1)] = 8
    """Examples per step (per worker)."""
    lr: Annotated[float, Gt(0)] = 1e-3
    """AdamW learning rate of the UNet (and the null token)."""
    warmup_steps: Annotated[int, Ge(0)] = 20
    """Linear learning-rate warm-up."""
    grad_clip: Annotated[float, Ge(0)] = 1.0
    """Gradient-norm clip (0 turns it off)."""
    cameras: list[str] = field(default_factory=lambda: ["CAM_FRONT"])
    """Cameras whose views become targets."""
    shifts_m: Annotated[list[float], Interval(ge=-100, le=100)] = field(
        default_factory=lambda: [1.0, -1.0, 2.0, -2.0, 4.0, -4.0]
    )
    """Lateral shift targets, metres (+ = left). Ground truth exists only where the data can re-render (synthetic)."""
    horizons_s: Annotated[list[float], Gt(0)] = field(default_factory=lambda: [1.0, 2.0])
    """Future targets, seconds ahead on the recorded ego trajectory."""
    weathers: list[str] = field(default_factory=lambda: ["rain", "fog", "night"])
    """Weather-editing targets (pairs from the dataset's weather variants)."""
    weather_targets: bool = True
    """Train on the ``weathers`` targets at all. The dual-condition table (``sweep=dual_condition``) turns them off
    in every row: a weather target's low-level conditions are the clear frame's Gaussians projected into the same
    camera, so without C_L (the low-level-only row) rain, fog and night arrive as identical inputs and the UNet can
    only learn their average; the rows would then differ in the task, not just in the conditions they are given."""
    log_every: Annotated[int, Ge(1)] = 10
    """Log the training loss every N steps."""
