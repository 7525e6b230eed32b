"""Where progress events come from and what the driver makes of them (the events themselves: ``gdwm.events``).

Stage tasks, scene actors and training workers hold a ``Reporter`` (their execution's stage and key, and the handle
of a zero-CPU ``ProgressActor`` on the driver's node) and send ``running``, scene, ``ctx.progress`` and training-step
events; the driver drains the actor every poll, adds what only it knows (an execution's outcome: done, cached,
failed with its cause, blocked, and which trials it served), and feeds everything to one ``LaunchProgress``: the
state of every execution and trial, counts, durations and ETAs. ``gdwm.board`` renders that state as a live board or
as log lines; ``snapshot`` is what the MLflow run and the launch's ``events.jsonl`` carry for other processes.

ETA: an execution's remaining seconds come from its own rate where it reports one (steps, scenes done), else from
its estimate: the median duration of earlier finished runs of the stage in the store (``gdwm.capacity``'s model,
per task; a per-scene stage's scenes run in waves of its actor pool), replaced by the median of this launch's own
finished executions of the stage once there are any. The launch's ETA is the longest remaining running execution
plus every pending one's estimate: an upper bound where independent stages overlap. Unknown durations make it None.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from gdwm.events import FINISHED, Event

STEP_INTERVAL_S = 1.0
"""A worker sends at most one step or progress event per execution (and scene) this often; the last always goes."""


class EventQueue:
    """Events from the workers until the driver drains them; ``ProgressActor`` is its Ray actor form."""

    def __init__(self) -> None:
        self.events: list[dict] = []

    def put(self, event: dict) -> None:
        self.events.append(event)

    def drain(self) -> list[dict]:
        out, self.events = self.events, []
        return out


def __getattr__(name: str) -> Any:
    """``ProgressActor``, the Ray actor form of ``EventQueue``, made on first use: a reader of progress (``gdwm ui``)
    imports this module without Ray."""
    if name == "ProgressActor":
        import ray

        actor = ray.remote(num_cpus=0)(EventQueue)
        globals()["ProgressActor"] = actor
        return actor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class Reporter:
    """One execution's way to report (picklable: the actor handle, the stage and key). Sends are fire-and-forget;
    step and progress events are thinned to one per ``STEP_INTERVAL_S``: one that comes too soon is held and sent
    when the interval ends unless a newer one replaces it (a throttle with a trailing edge), so a stage that stops
    reporting (blocked, or in a long step) still shows the last step it reached; a final one goes at once."""

    def __init__(self, actor: Any, stage: str, key: str):
        self.actor, self.stage, self.key = actor, stage, key
        self._last: dict[str | None, float] = {}
        self._held: dict[str | None, dict] = {}
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        return {"actor": self.actor, "stage": self.stage, "key": self.key}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["actor"], state["stage"], state["key"])

    def _send(self, **kw: Any) -> None:
        self.actor.put.remote(Event(stage=self.stage, key=self.key, **kw).to_dict())

    def _throttled(self, what: str, final: bool, **kw: Any) -> None:
        with self._lock:
            now = time.monotonic()
            wait = self._last.get(what, -math.inf) + STEP_INTERVAL_S - now
            if final or wait <= 0:
                self._held.pop(what, None)
                self._last[what] = now
                self._send(**kw)
                return
            first = what not in self._held
            self._held[what] = kw
        if first:  # one timer per held slot; later events only replace what it will send
            timer = threading.Timer(wait, self._flush, args=(what,))
            timer.daemon = True
            timer.start()

    def _flush(self, what: str) -> None:
        with self._lock:
            kw = self._held.pop(what, None)
            if kw is None:
                return
            self._last[what] = time.monotonic()
            self._send(**kw)

    def state(self, state: str, scene: str | None = None, message: str | None = None) -> None:
        self._send(kind="scene" if scene else "stage", state=state, scene=scene, message=message or None)

    def progress(self, scene: str | None, done: int, total: int, message: str = "") -> None:
        self._throttled(f"p:{scene}", done >= total, kind="progress", scene=scene, done=int(done), total=int(total),
                        message=message or None)  # fmt: skip

    def step(self, step: int, steps: int | None, loss: float | None) -> None:
        self._throttled("step", steps is not None and step >= steps, kind="step", step=int(step), steps=steps,
                        loss=loss)  # fmt: skip


@dataclass
class Execution:
    """One stage key of the launch and what is known of it."""

    stage: str
    key: str
    trials: list[str]
    """The trials it serves, in launch order (the first one is the one that "runs" it)."""
    scenes_total: int = 0
    """Scenes it processes (per-scene stages), else 0."""
    estimate_s: float | None = None
    """Expected seconds (see the module docstring); 0 for a stage the plan found cached."""
    state: str = "pending"
    started: float | None = None
    ended: float | None = None
    scenes: dict[str, str] = field(default_factory=dict)
    """Scene -> its state."""
    done: int | None = None
    total: int | None = None
    message: str | None = None
    step: int | None = None
    steps: int | None = None
    loss: float | None = None
    cause: str | None = None
    traceback: str | None = None
    last_line: float | None = None
    """When a line last reported it (heartbeats go out ``heartbeat_s`` after it)."""

    @property
    def finished(self) -> bool:
        return self.state in FINISHED

    def elapsed(self, now: float) -> float | None:
        return None if self.started is None else (self.ended or now) - self.started

    def scenes_done(self) -> int:
        return sum(1 for s in self.scenes.values() if s in FINISHED)

    def remaining_s(self, now: float) -> float | None:
        """Seconds left: from its own rate (steps, scenes, its ``progress``) once it has one, else its estimate."""
        if self.finished:
            return 0.0
        elapsed = self.elapsed(now)
        if elapsed is None:
            return self.estimate_s
        for done, total in ((self.step, self.steps), (self.scenes_done(), self.scenes_total), (self.done, self.total)):
            if done and total and done < total:
                return elapsed * (total - done) / done
        return None if self.estimate_s is None else max(self.estimate_s - elapsed, 0.0)


class LaunchProgress:
    """The state of one launch, fed with events (``feed``); pure Python, so it renders and tests without Ray."""

    def __init__(
        self,
        kind: str,
        name: str,
        launch: str,
        trials: Mapping[str, Sequence[tuple[str, str]]],
        executions: Sequence[Execution],
        clock: Callable[[], float] = time.time,
    ):
        self.kind, self.name, self.launch = kind, name, launch
        self.trials = {t: list(ks) for t, ks in trials.items()}
        """Trial label -> its (stage, key) in stage order."""
        self.executions = {(e.stage, e.key): e for e in executions}
        self.stages = list(dict.fromkeys(s for ks in self.trials.values() for s, _ in ks))
        self.clock = clock
        self.started = clock()
        self.ended: float | None = None
        self.trial_done: dict[str, str] = {}
        """Trials with an outcome (``done`` / ``failed``), in the order they finished."""
        self.observed: dict[str, list[float]] = {}
        """Stage -> durations of its executions that ran in this launch."""

    # ---- feeding -------------------------------------------------------------------------------------------------
    def feed(self, ev: Event) -> Execution | None:
        """Apply one event; returns the execution it concerns (None for launch and trial events)."""
        if ev.kind == "trial":
            if ev.state is not None and ev.trials:
                self.trial_done[ev.trials[0]] = ev.state
            return None
        if ev.kind == "launch":
            if ev.state in FINISHED:
                self.ended = ev.t
            return None
        ex = self.executions.get((ev.stage, ev.key))
        if ex is None:
            return None
        if ev.kind == "stage" and ev.state is not None:
            self._stage(ex, ev)
        elif ev.kind == "scene" and ev.scene is not None and ev.state is not None:
            ex.scenes[ev.scene] = ev.state
            if ex.started is None and ev.state == "running":
                ex.started, ex.state = ev.t, "running"
        elif ev.kind == "progress" and ev.scene is None:
            ex.done, ex.total, ex.message = ev.done, ev.total, ev.message or ex.message
        elif ev.kind == "step":
            ex.step, ex.steps, ex.loss = ev.step, ev.steps or ex.steps, ev.loss if ev.loss is not None else ex.loss
            if ex.state == "pending":
                ex.state, ex.started = "running", ex.started or ev.t
        return ex

    def _stage(self, ex: Execution, ev: Event) -> None:
        if ex.finished:
            return  # an outcome is final (a late worker event must not undo it)
        ex.state = ev.state
        if ev.state == "running" and ex.started is None:
            ex.started = ev.t
        if ev.state in FINISHED:
            ex.ended = ev.t
            ex.cause, ex.traceback = ev.cause or ex.cause, ev.traceback or ex.traceback
            if ev.state == "done" and ex.started is not None:
                self.observed.setdefault(ex.stage, []).append(ev.t - ex.started)
                self._refine(ex.stage)

    def _refine(self, stage: str) -> None:
        """This launch's own durations of ``stage`` replace the store's for its pending non-scene executions."""
        median = statistics.median(self.observed[stage])
        for e in self.executions.values():
            if e.stage == stage and e.state == "pending" and not e.scenes_total and e.estimate_s != 0:
                e.estimate_s = median

    # ---- reading -------------------------------------------------------------------------------------------------
    def cell(self, trial: str, stage: str) -> tuple[str, Execution | None]:
        """A trial's stage as the board shows it: ``shared`` where another trial's execution produced it."""
        key = dict(self.trials[trial]).get(stage)
        ex = self.executions.get((stage, key)) if key else None
        if ex is None:
            return "", None
        if ex.state == "done" and ex.trials and ex.trials[0] != trial:
            return "shared", ex
        return ex.state, ex

    def trial_state(self, trial: str) -> str:
        if trial in self.trial_done:
            return self.trial_done[trial]
        states = [self.cell(trial, s)[0] for s, _ in self.trials[trial]]
        if "failed" in states or "blocked" in states:
            return "failed" if all(s in FINISHED for s in states) else "running"
        if any(s in ("running",) for s in states) or any(s in FINISHED for s in states):
            return "running"
        return "pending"

    def counts(self) -> dict[str, int]:
        ex = list(self.executions.values())
        return {
            "executions": len(ex),
            "executions_finished": sum(e.finished for e in ex),
            "trials": len(self.trials),
            "trials_done": sum(1 for s in self.trial_done.values() if s == "done"),
            "trials_failed": sum(1 for s in self.trial_done.values() if s == "failed"),
        }

    def running(self) -> list[Execution]:
        return [e for e in self.executions.values() if e.state == "running"]

    def elapsed(self) -> float:
        return (self.ended or self.clock()) - self.started

    def eta_s(self, now: float | None = None) -> float | None:
        """Seconds until every execution has finished (module docstring); None while some duration is unknown."""
        now = self.clock() if now is None else now
        left = [e.remaining_s(now) for e in self.running()]
        todo = [e.estimate_s for e in self.executions.values() if e.state == "pending"]
        if any(x is None for x in [*left, *todo]):
            return None
        return max(left, default=0.0) + sum(todo)  # type: ignore[arg-type]

    def state(self) -> str:
        c = self.counts()
        if self.ended is None:
            return "running"
        return "failed" if c["trials_failed"] else "done"

    def summary(self) -> str:
        """One line: trials and executions done, elapsed, ETA."""
        c, eta = self.counts(), self.eta_s()
        failed = f", {c['trials_failed']} failed" if c["trials_failed"] else ""
        head = f"trials {c['trials_done']}/{c['trials']} done{failed}" if c["trials"] > 1 else ""
        parts = [head, f"stages {c['executions_finished']}/{c['executions']}", f"{duration(self.elapsed())} elapsed"]
        if self.ended is None:
            parts.append(f"ETA {duration(eta)}" if eta is not None else "ETA ? (no earlier runs of some stages)")
        return " · ".join(p for p in parts if p)

    def snapshot(self, events_path: str | None = None) -> dict[str, Any]:
        """The launch as a dashboard needs it (JSON): ``launch``, ``kind``, ``name``, ``state``, ``started``,
        ``updated``, ``elapsed_s``, ``eta_s``, ``counts`` (``counts``), ``summary``, ``events`` (the events file,
        relative to the workdir), ``stages`` (the stage order), ``trials`` (per trial: ``state`` and per stage
        ``{state, key, started, duration_s, step, steps, loss, done, total, scenes_done, scenes_total, eta_s, cause,
        traceback}`` with empty fields left out) and ``failures`` (every failed execution: stage, key, trials, cause,
        traceback)."""
        now = self.clock()
        trials = {}
        for t, keys in self.trials.items():
            cells = {}
            for stage, _ in keys:
                state, ex = self.cell(t, stage)
                if ex is not None:
                    cells[stage] = _cell(state, ex, now)
            trials[t] = {"state": self.trial_state(t), "stages": cells}
        failures = [
            {"stage": e.stage, "key": e.key, "trials": e.trials, "cause": e.cause, "traceback": e.traceback}
            for e in self.executions.values()
            if e.state == "failed"
        ]
        eta = self.eta_s(now)
        return {
            "format": 1,
            "launch": self.launch,
            "kind": self.kind,
            "name": self.name,
            "state": self.state(),
            "started": round(self.started, 3),
            "updated": round(now, 3),
            "elapsed_s": round(self.elapsed(), 1),
            "eta_s": None if eta is None or self.ended else round(eta, 1),
            "counts": self.counts(),
            "summary": self.summary(),
            "events": events_path,
            "stages": self.stages,
            "trials": trials,
            "failures": failures,
        }


def _cell(state: str, ex: Execution, now: float) -> dict[str, Any]:
    out = {
        "state": state,
        "key": ex.key,
        "started": ex.started,
        "duration_s": None if ex.elapsed(now) is None else round(ex.elapsed(now), 1),
        "step": ex.step,
        "steps": ex.steps,
        "loss": ex.loss,
        "done": ex.done,
        "total": ex.total,
        "scenes_done": ex.scenes_done() if ex.scenes_total else None,
        "scenes_total": ex.scenes_total or None,
        "eta_s": None if ex.finished or ex.remaining_s(now) is None else round(ex.remaining_s(now), 1),
        "cause": ex.cause,
        "traceback": ex.traceback,
    }
    return {k: v for k, v in out.items() if v is not None}


def duration(seconds: float | None) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``; ``?`` when unknown."""
    if seconds is None or math.isnan(seconds):
        return "?"
    s = round(seconds)
    if s < 60:
        return f"{seconds:.1f} s" if seconds < 10 else f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"
