"""Settings of the distill stage (``conf/stage/distill/*.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated

from annotated_types import Ge, Gt, Interval

from gdwm.api import SEED


class Encoder(StrEnum):
    daisy = "daisy"
    qwen3_vl_vision = "qwen3_vl_vision"
    langsplat_proxy = "langsplat_proxy"
    langsplat = "langsplat"


class FeatureTokenizer(StrEnum):
    foundation = "foundation"
    langsplat3 = "langsplat3"


@dataclass
class DistillConfig:
    """E_F frozen; E_z / D_F fitted with L_ae; per-Gaussian codes z_i optimised with L_distill."""

    encoder: Encoder = Encoder.daisy
    """E_F: the foundation encoder, ``daisy`` (CPU) or ``qwen3_vl_vision`` (a local Qwen3-VL checkpoint); or
    ``langsplat_proxy``, the stand-in for LangSplat's region-level language features that the ablations' "Distillation
    ✗" rows distil instead (with ``feature_tokenizer=langsplat3``, see ``model_zoo.encoders.langsplat_proxy``); or
    ``langsplat``, LangSplat's own 3-d codes as a dataset ships them (the GaussianDWM release, whose pipeline takes
    them as they are: ``pipelines.stages.given``; nothing computes them from images here)."""
    language_encoder: Encoder = Encoder.langsplat_proxy
    """What the "Distillation ✗" rows of the shipped sweeps take as LangSplat's language features (they set
    ``encoder=${stage.distill.language_encoder}``): ``langsplat_proxy`` computed from the images, or ``langsplat``
    on a dataset that ships the codes (``experiment=gaussiandwm_release`` sets it)."""
    encoder_path: str | None = None
    """Local checkpoint directory of ``qwen3_vl_vision``."""
    encoder_tiny: bool = False
    """Use the encoder's tiny random flavor (tests, smoke runs)."""
    d_f: Annotated[int, Ge(1)] = 64
    """Feature dimension of ``daisy`` and ``langsplat_proxy`` (the Qwen encoder's is fixed by its checkpoint)."""
    feature_tokenizer: FeatureTokenizer = FeatureTokenizer.foundation
    """Compact code variant: ``foundation`` (``d_z`` dims) or ``langsplat3`` (3 dims, like the public release)."""
    d_z: Annotated[int, Ge(1)] = 16
    """Code dimension of ``foundation``."""
    ae_hidden: Annotated[int, Ge(1)] = 128
    """Hidden width of E_z / D_F."""
    ae_steps: Annotated[int, Ge(0)] = 400
    """Adam steps of the autoencoder on pixel features (L_ae)."""
    ae_lr: Annotated[float, Gt(0)] = 0.003
    """Adam lr of the autoencoder."""
    ae_pixels_per_view: Annotated[int, Ge(1)] = 512
    """Valid pixels sampled per training view for the autoencoder."""
    distill_steps: Annotated[int, Ge(0)] = 200
    """Adam steps on the codes z_i."""
    views_per_step: Annotated[int, Ge(1)] = 8
    """Training views sampled per step (stochastic L_distill)."""
    min_weight: Annotated[float, Interval(ge=0, lt=1)] = 0.01
    """Compositing weights below this are dropped from the precomputed per-view weight matrices (3x fewer entries,
    about 1% of the rendered mass)."""
    distill_lr: Annotated[float, Gt(0)] = 0.05
    """Adam lr of the codes."""
    min_alpha: Annotated[float, Interval(ge=0, le=1)] = 0.5
    """Pixels count in Omega_v only where the Gaussians cover them (rendered alpha >= this) and E_F is defined."""
    seed: Annotated[int, SEED] = 0
    """Seed of pixel sampling and initialisation."""
