"""Where a command's start-up and teardown time goes: named phases, as JSON lines appended to ``$GDWM_PHASES``.

Off (one environment lookup per phase) unless ``GDWM_PHASES`` names a file. The start-up benchmark sets it and splits
a toy ``gdwm run`` by phase from what the driver wrote: ``{"phase": NAME, "start": T0, "end": T1}`` in
``time.time()`` seconds, one line per phase, so the time between phases (and before the first, from the process'
start) is visible too.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Iterator

ENV = "GDWM_PHASES"


def record(name: str, start: float, end: float) -> None:
    """Append one phase to ``$GDWM_PHASES`` (nothing when it is unset)."""
    path = os.environ.get(ENV)
    if path:
        with open(path, "a") as f:
            f.write(json.dumps({"phase": name, "start": start, "end": end, "pid": os.getpid()}) + "\n")


@contextlib.contextmanager
def phase(name: str) -> Iterator[None]:
    """Time the block as phase ``name`` (recorded even when it raises)."""
    if not os.environ.get(ENV):
        yield
        return
    t0 = time.time()
    try:
        yield
    finally:
        record(name, t0, time.time())


def mark(name: str) -> None:
    """A zero-length phase: the moment the command got here."""
    now = time.time()
    record(name, now, now)
