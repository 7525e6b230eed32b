"""Failure injection for the test stages (``tests/gdwm/stages.py``, ``tests/gdwm/light_stages.py``), driven by
environment variables; no heavy imports, so a stage module that needs only these starts fast in a Ray worker.

GDWM_TEST_DIR      every execution appends "<stage> <scene>" to executions.log here
GDWM_TEST_KILL     "stage:scene" (or "stage:step=N" for training) — SIGKILL the worker once (marker file)
GDWM_TEST_FAIL     "stage:scene" — raise ValueError in that scene ("stage:seed=N": in that trial seed's execution;
                   "reconstruct:setup": its actors' setup raises KeyError, as a missing environment variable does)
GDWM_TEST_BLOCK    "stage" or "stage:step=N" — wait until GDWM_TEST_DIR/release exists (a test kills the driver)
GDWM_TEST_HOG      "stage:scene" — fill memory until Ray's OOM killer ends the worker (up to 12 GB)
GDWM_TEST_FILL     "stage:PATH" — the stage fills the disk of PATH: writes PATH until no space is left, and leaves it
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from gdwm.stage import StageContext


def _test_dir() -> Path:
    return Path(os.environ["GDWM_TEST_DIR"])


def _record(ctx: StageContext) -> None:
    with open(_test_dir() / "executions.log", "a") as f:
        f.write(f"{ctx.name} {ctx.scene or '-'} {ctx.key[:12]} {os.getpid()}\n")


def _once(tag: str) -> bool:
    marker = _test_dir() / f"marker-{tag}"
    if marker.exists():
        return False
    marker.touch()
    return True


def _inject(ctx: StageContext) -> None:
    target = f"{ctx.name}:{ctx.scene}"
    if os.environ.get("GDWM_TEST_KILL") == target and _once(target.replace(":", "-")):
        os.kill(os.getpid(), signal.SIGKILL)
    if os.environ.get("GDWM_TEST_FAIL") in (target, f"{ctx.name}:seed={ctx.seed}"):
        raise ValueError(f"injected failure in {os.environ['GDWM_TEST_FAIL']}")
    if os.environ.get("GDWM_TEST_BLOCK") == ctx.name:
        _block(ctx.name)
    if os.environ.get("GDWM_TEST_HOG") == target:
        _hog()
    fill, _, path = os.environ.get("GDWM_TEST_FILL", "").partition(":")
    if fill == ctx.name and _once("fill"):
        _fill(Path(path))


def _fill(path: Path) -> None:
    chunk = b"\0" * (1 << 16)
    with open(path, "wb", buffering=0) as f:
        try:
            while True:
                f.write(chunk)
        except OSError:
            pass
    with open(path, "ab", buffering=0) as f:  # the last few bytes too
        try:
            while True:
                f.write(b"\0")
        except OSError:
            pass


def _hog(most_gb: float = 12.0) -> None:
    """Fill memory (touched pages) until Ray's OOM killer ends this worker; give up at ``most_gb``."""
    import numpy

    chunks = []
    while len(chunks) * 0.25 < most_gb:
        chunks.append(numpy.ones(1 << 25))  # 256 MiB, written
        time.sleep(0.05)


def _block(name: str) -> None:
    (_test_dir() / f"blocked-{name}").touch()
    while not (_test_dir() / "release").exists():
        time.sleep(0.1)
