"""Shared fixtures of the pipelines tests (synthetic_mini ones are named ``synth_*``)."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
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
    "model.llm.pretrain_steps=20",  # the tiny LLM's warm-up: 200 steps take about a minute
]
"""``gdwm run`` overrides of the understanding branch in seconds: tiny flavors on 2 small scenes."""


@pytest.fixture(scope="session")
def synth_small_cfg() -> SynthConfig:
    """2 scenes (a bend and a stop) x 10 frames at 64x36: every task family, a few seconds to build."""
    return SynthConfig(num_scenes=2, num_frames=10, width=64, height=36, seed=0)


@pytest.fixture(scope="session")
def synth_small(synth_small_cfg, tmp_path_factory) -> Path:
    return build(synth_small_cfg, tmp_path_factory.mktemp("synth") / "small")


REPO = Path(__file__).resolve().parents[2]


def gdwm_cli(*args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    """One ``gdwm`` command in its own process (test configs on GDWM_CONF_PATH); it must exit 0."""
    env = {**os.environ, "GDWM_CONF_PATH": str(REPO / "tests" / "conf")}
    r = subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=timeout, env=env)
    assert r.returncode == 0, r.stderr[-4000:]
    return r


@dataclass(frozen=True)
class TinyRun:
    work: Path
    data: Path
    args: list[str]
    """The command's overrides (workdir, data root, TINY_RUN)."""
    stdout: str


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> TinyRun:
    """The real understanding branch once from scratch (data generated first): what the end-to-end test inspects and
    the determinism test repeats. Tests that run more commands in its workdir come after the ones that read it."""
    work = tmp_path_factory.mktemp("tiny") / "w"
    args = [f"workdir={work}", f"data.root={work / 'data'}", *TINY_RUN]
    r = gdwm_cli("run", *args)
    return TinyRun(work, work / "data", args, r.stdout)


@dataclass(frozen=True)
class DemoSweep:
    work: Path
    stdout: str


@pytest.fixture(scope="session")
def demo_sweep(tmp_path_factory) -> DemoSweep:
    """``make demo``'s sweep once (journal_ablation, experiment=demo, its data generated first): the demo table's test
    reads its report, and the nightly suite records its baseline in the same workdir, where seed 0 of the nightly's
    model is the sweep's last row (``experiment=demo`` composes to that row's config), every stage of it cached."""
    work = tmp_path_factory.mktemp("demo") / "w"
    r = gdwm_cli("sweep", "sweep=journal_ablation", "experiment=demo", f"workdir={work}", timeout=3000)
    return DemoSweep(work, r.stdout)
