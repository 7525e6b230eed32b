"""Timing helpers and the result record every benchmark returns."""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

TINY_SCENES = ["data.num_scenes=2", "data.width=64", "data.height=36"]
"""A small synthetic_mini: 2 scenes at 64x36."""
TINY_FLAVORS = [
    "stage/reconstruct=tiny",
    "stage/distill=tiny",
    "stage/tokenizer=tiny",
    "stage/lora=tiny",
    "stage/evaluate_qa=tiny",
    "run.live=false",
]
"""The understanding branch's stages in their seconds-long flavors."""


def gdwm(*args: str) -> tuple[float, str]:
    """Wall seconds and stdout of one ``gdwm`` command in its own process (raises with its stderr if it fails)."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"gdwm {' '.join(args)} failed:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0, r.stdout


@dataclass
class Result:
    """One measured figure; ``target`` is checked with ``op`` (``<=`` or ``>=``)."""

    bench: str
    metric: str
    value: float
    unit: str
    target: float | None = None
    op: str = "<="
    detail: str = ""

    @property
    def passed(self) -> bool | None:
        if self.target is None:
            return None
        return self.value <= self.target if self.op == "<=" else self.value >= self.target

    def to_dict(self) -> dict:
        return {**asdict(self), "passed": self.passed}


def median_time(fn: Callable[[], object], repeats: int, warmup: int = 1) -> tuple[float, list[float]]:
    """Median wall seconds of ``fn`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times
