"""Shared fixtures of the pipelines tests (synthetic_mini ones are named ``synth_*``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipelines.data.synth.build import build
from pipelines.data.synth.config import SynthConfig

TINY_RUN = [
    "targets=[evaluate_qa]",
    "stage/reconstruct=tiny",
    "stage/distill=tiny",
    "stage/tokenizer=tiny",
    "stage/lora=tiny",
    "stage/evaluate_qa=tiny",
    "data.num_scenes=2",
    "data.width=64",
    "data.height=36",
]
"""``gdwm run`` overrides of the understanding branch in seconds: tiny flavors on 2 small scenes."""


@pytest.fixture(scope="session")
def synth_small_cfg() -> SynthConfig:
    """2 scenes (a bend and a stop) x 10 frames at 64x36: every task family, a few seconds to build."""
    return SynthConfig(num_scenes=2, num_frames=10, width=64, height=36, seed=0)


@pytest.fixture(scope="session")
def synth_small(synth_small_cfg, tmp_path_factory) -> Path:
    return build(synth_small_cfg, tmp_path_factory.mktemp("synth") / "small")
