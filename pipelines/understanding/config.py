"""Settings of the scene-understanding stages (``conf/stage/{tokenizer,lora}/``, ``conf/model/world/``).

The components' own configs (selector, projection, fine adapter, alignment, LLM) sit next to their classes in
``model_zoo``; these are the stage recipes and the switches of the ablation tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated

from annotated_types import Ge, Gt, Interval


class LoraMode(StrEnum):
    train = "train"
    zero_shot = "zero_shot"


@dataclass
class WorldConfig:
    """How the world model is put together (the ablation switches of tab:qa-ablation-{conference,journal})."""

    gaussian_tokens: bool = True
    """Insert K_f Gaussian world tokens Z_G (False: the conference table's image-only "Gaussian: No" rows)."""
    train_decoder: bool = True
    """Foundation-feature distillation on: the feature decoding trains with the adapter, through one feature head
    shared by every scene after the frozen per-scene D_F (so held-out scenes use the trained parameters too).
    False (journal rows 1-4): the decoded features are frozen inputs, like the conference's LangSplat features."""
    trajectory_frames: Annotated[int, Ge(1)] = 4
    """Ego-trajectory prior of the driving-aware selector with ``model.selector.path=extrapolated``: past ego
    positions over this many frames, extrapolated as far ahead at constant velocity, in the current ego frame (no
    future ground truth enters the input)."""
    weather: str = "clear"
    """Which weather variant of the images the LLM sees."""


@dataclass
class TrainConfig:
    """One training stage: steps, batch, optimiser, task-aware sampling (Eq. P_m)."""

    steps: Annotated[int, Ge(0)] = 300
    """Optimiser steps."""
    batch_size: Annotated[int, Ge(1)] = 8
    """Samples per step (per worker)."""
    lr: Annotated[float, Gt(0)] = 2e-3
    """AdamW learning rate of every trainable parameter."""
    weight_decay: Annotated[float, Ge(0)] = 0.0
    """AdamW weight decay."""
    warmup_steps: Annotated[int, Ge(0)] = 20
    """Linear learning-rate warm-up."""
    grad_clip: Annotated[float, Ge(0)] = 1.0
    """Gradient-norm clip (0 turns it off)."""
    task_alpha: Annotated[float, Interval(ge=0, le=1)] = 0.5
    """alpha_s of task-aware sampling P_m = n_m^alpha_s / sum_k n_k^alpha_s (1 = proportional, 0 = uniform)."""
    log_every: Annotated[int, Ge(1)] = 10
    """Log the training loss every N steps."""
    eval_samples: Annotated[int, Ge(0)] = 64
    """Held-out (val split) samples scored at the end: LM loss and greedy answers (0 turns it off)."""
    max_new_tokens: Annotated[int, Ge(1)] = 48
    """Greedy decoding budget of the held-out answers."""
    source: str | None = None
    """Take the stage's model from the model zoo instead of training it, e.g. ``zoo:gdwm-lora@champion`` or
    ``zoo:gdwm-lora/3`` (``gdwm run`` pins an alias to its version before planning: the cache key names it);
    the held-out monitor still runs, and nothing new is registered."""


@dataclass
class TokenizerStageConfig(TrainConfig):
    """Stage 1: LLM frozen; feature decoders (when distillation is on), projection and fine adapter train."""


@dataclass
class LoraStageConfig(TrainConfig):
    """Stage 2: peft LoRA on the LLM with the adapter trainable."""

    mode: LoraMode = LoraMode.train
    """``train``, or ``zero_shot``: no training at all and no Gaussian tokens (the conference table's first row)."""
    rank: Annotated[int, Ge(1)] = 16
    """LoRA rank r."""
    alpha: Annotated[int, Gt(0)] = 32
    """LoRA alpha (scaling alpha / r)."""
    dropout: Annotated[float, Interval(ge=0, lt=1)] = 0.05
    """LoRA dropout."""
    target_modules: list[str] = field(
        default_factory=lambda: ["q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj"]
    )
    """Linear layers of the language model that get LoRA (the vision tower never does)."""
