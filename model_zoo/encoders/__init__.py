"""Frozen encoders E_F: ``daisy`` (CPU default) and ``qwen3_vl_vision`` (full runs, ``tiny`` for tests) as the
foundation encoder; ``langsplat_proxy``, the stand-in for LangSplat's region-level language features (the ablations'
"Distillation ✗" arm)."""

from model_zoo.encoders.base import EncoderSettings, FoundationEncoder, upsample_grid
from model_zoo.encoders.daisy import DaisyConfig, DaisyEncoder, build_daisy
from model_zoo.encoders.langsplat_proxy import LangSplatProxyConfig, LangSplatProxyEncoder, build_langsplat_proxy
from model_zoo.encoders.qwen3_vl_vision import QwenVisionConfig, QwenVisionEncoder, build_qwen3_vl_vision

__all__ = [
    "DaisyConfig",
    "DaisyEncoder",
    "EncoderSettings",
    "FoundationEncoder",
    "LangSplatProxyConfig",
    "LangSplatProxyEncoder",
    "QwenVisionConfig",
    "QwenVisionEncoder",
    "build_daisy",
    "build_langsplat_proxy",
    "build_qwen3_vl_vision",
    "upsample_grid",
]
