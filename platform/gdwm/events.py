"""Progress events: the one model every launch (``gdwm run``, ``gdwm sweep``, ``gdwm regress``) reports, whatever
renders it -- the live board in a terminal, timestamped lines in a log, a dashboard in another process.

Units. A launch runs *trials* (one per row and seed); each trial needs *stages*; a stage's unit of work is its
cache key, so trials that share a key (a seed-free stage across seeds, a common upstream across rows) share one
execution. A per-scene stage's execution processes *scenes*; a training stage reports *steps*.

States (``STATES``) of an execution, a scene, a trial or the launch:

- ``pending``  not started yet;
- ``running``  started (a training stage reports ``step`` / ``steps`` and ``loss``; a per-scene stage ``done`` /
  ``total`` scenes);
- ``cached``   its output came from the cache: nothing ran;
- ``shared``   (a trial's stage) another trial's execution of the same key produced it;
- ``done``     finished now;
- ``failed``   raised: ``cause`` is one line (exception type and message, stage, scene), ``traceback`` the file
  holding the full traceback;
- ``blocked``  never ran because a stage upstream failed.

The events file. Every launch appends its events to ``<workdir>/logs/<launch>/events.jsonl`` (``LAUNCH_DIR``), one
JSON object per line, written and flushed as they happen (a reader may see a partial last line: skip it). Fields,
absent when empty:

=============  ===========================================================================================
``t``          unix time (seconds, float)
``kind``       ``launch`` (started / finished: ``state``), ``stage`` (an execution changed state), ``scene``
               (a scene of a per-scene stage), ``step`` (a training step), ``progress`` (a stage's own
               ``ctx.progress``), ``trial`` (a trial finished), ``heartbeat`` (a stage still running),
               ``bootstrap`` (``gdwm compare`` / ``regress`` resampling)
``state``      one of ``STATES``
``launch``     the launch id: ``<kind>-<name>-<YYYYmmdd-HHMMSS>-<pid>`` (the folder's name)
``stage``      stage name; ``key`` its cache key (the execution's id, 64 hex)
``scene``      scene id (``scene`` events, and a failed per-scene stage's scene)
``trials``     labels of the trials the execution serves (``trial`` events: the one trial)
``done``       x of x / N: scenes, resamples, or (``launch`` / ``trial`` / ``stage`` events) executions finished
``total``      N of x / N
``step``       training step reached (1-based) of ``steps``; ``loss`` its loss
``duration_s`` how long the execution (or the launch) took; ``eta_s`` estimated seconds left
``message``    a stage's own progress text, or what a ``launch`` event says
``cause``      one line: ``stage 'lora' failed: ValueError: rank must be >= 0``
``traceback``  path of the full traceback, relative to the workdir
``snapshot``   ``launch`` events: the whole state as in the MLflow snapshot below
=============  ===========================================================================================

MLflow. The driver keeps a compact snapshot of the launch on the launch's run (the sweep's run, ``gdwm run``'s run),
at most every ``run.snapshot_s`` seconds and once at the end: tags ``gdwm.state`` (running / done / failed),
``gdwm.trials_done``, ``gdwm.trials_failed``, ``gdwm.trials_total``, ``gdwm.progress`` (one line) and
``gdwm.events`` (the events file, relative to the workdir), and the artifact ``progress/snapshot.json``
(``SNAPSHOT_ARTIFACT``; ``gdwm.progress.LaunchProgress.snapshot`` documents its fields). A dashboard that reads only
the tracking server sees the live state from these.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

STATES = ("pending", "running", "cached", "shared", "done", "failed", "blocked")
FINISHED = ("cached", "shared", "done", "failed", "blocked")
"""States an execution or a trial does not leave."""
KINDS = ("launch", "stage", "scene", "step", "progress", "trial", "heartbeat", "bootstrap")
LAUNCH_DIR = "logs"
"""Under the workdir: one folder per launch with ``events.jsonl`` and ``tracebacks/``."""
EVENTS_FILE = "events.jsonl"
TRACEBACKS_DIR = "tracebacks"
SNAPSHOT_ARTIFACT = "progress/snapshot.json"
FORMAT = 1


@dataclass
class Event:
    """One thing that happened (see the module docstring for every field)."""

    kind: str
    state: str | None = None
    stage: str | None = None
    key: str | None = None
    scene: str | None = None
    trials: list[str] = field(default_factory=list)
    done: int | None = None
    total: int | None = None
    step: int | None = None
    steps: int | None = None
    loss: float | None = None
    duration_s: float | None = None
    eta_s: float | None = None
    message: str | None = None
    cause: str | None = None
    traceback: str | None = None
    launch: str | None = None
    snapshot: dict[str, Any] | None = None
    t: float = field(default_factory=time.time)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"event kind {self.kind!r} is not one of {KINDS}")
        if self.state is not None and self.state not in STATES:
            raise ValueError(f"event state {self.state!r} is not one of {STATES}")

    def to_dict(self) -> dict[str, Any]:
        """The event as written: empty fields left out, ``t`` first."""
        d = {k: v for k, v in asdict(self).items() if v is not None and v != [] and k != "t"}
        return {"t": round(self.t, 3), **d}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Event:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


class EventLog:
    """Appends events to a launch's ``events.jsonl``, one flushed line each, so another process can follow it."""

    def __init__(self, path: Path):
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(path, "a", encoding="utf-8")  # noqa: SIM115 -- held for the launch, closed by close()

    def write(self, event: Event) -> None:
        self._f.write(json.dumps(event.to_dict(), ensure_ascii=False, default=str) + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def read_events(path: Path) -> Iterator[Event]:
    """The events of a launch's file, in order; a partial last line (the launch is still writing) is skipped."""
    with open(path, encoding="utf-8") as f:
        for line in f:
            if not line.endswith("\n"):
                return
            yield Event.from_dict(json.loads(line))


def launch_id(kind: str, name: str, now: float | None = None) -> str:
    """``<kind>-<name>-<YYYYmmdd-HHMMSS>-<pid>``: the launch's folder under ``<workdir>/logs``."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now or time.time()))
    safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in name)[:60]
    return f"{kind}-{safe}-{stamp}-{os.getpid()}"
