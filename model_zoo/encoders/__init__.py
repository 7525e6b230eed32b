"""Frozen foundation encoders E_F: ``daisy`` (CPU default) and ``qwen3_vl_vision`` (full runs, ``tiny`` for tests)."""

from model_zoo.encoders.base import FoundationEncoder, upsample_grid
from model_zoo.encoders.daisy import DaisyConfig, DaisyEncoder, build_daisy
from model_zoo.encoders.qwen3_vl_vision import QwenVisionConfig, QwenVisionEncoder, build_qwen3_vl_vision

__all__ = [
    "DaisyConfig",
    "DaisyEncoder",
    "FoundationEncoder",
    "QwenVisionConfig",
    "QwenVisionEncoder",
    "build_daisy",
    "build_qwen3_vl_vision",
    "upsample_grid",
]
