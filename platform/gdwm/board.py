"""Two renderings of one ``LaunchProgress``: the live board a terminal redraws, and the lines a log keeps.

Lines (``Lines``), for CI logs, ``kubectl logs`` and files, one per event at ``normal`` verbosity::

    2026-12-03 09:33:20 [ 3/ 9] tokenizer · rank 4, rank 8, rank 2: done in 5.2 s (shared by 3 trials) · trials 0/3
    2026-12-03 09:33:50 [ 3/ 9] lora · rank 4: running 30 s, step 2/3, loss 0.333, ETA 15 s
    2026-12-03 09:33:52 [ 4/ 9] lora · rank 8: failed in 4.1 s: ValueError: ... (traceback: logs/.../lora-1a2b3c4d.txt)

``[x/ N]`` counts the launch's stage executions finished. A stage still running gets a heartbeat every
``heartbeat_s`` (step, loss, scenes, ETA); ``quiet`` prints failures only, ``verbose`` adds starts and scenes.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

from rich.console import Group
from rich.table import Table
from rich.text import Text

from gdwm.events import Event
from gdwm.progress import Execution, LaunchProgress, duration
from gdwm.term import NORMAL, QUIET, VERBOSE

STYLE = {"cached": "cyan", "shared": "cyan", "done": "green", "failed": "red", "running": "yellow",
         "blocked": "magenta", "pending": "dim"}  # fmt: skip
BOARD_TRIALS = 12
"""The board lists at most this many trials (running and failed first); the rest as counts."""


@contextlib.contextmanager
def resampling_progress(command: str, every_s: float = 5.0, verbosity: int = NORMAL) -> Iterator[None]:
    """While it is open, a bootstrap (``gdwm.compare.stats``) prints a line every ``every_s``: the stage, resamples
    scored of those planned, elapsed and ETA (and the ``bootstrap`` events of ``gdwm.events`` in the same words)."""
    from gdwm.compare.stats import ON_RESAMPLE
    from gdwm.term import console

    state: dict[str, float] = {}

    def hook(stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        start = state.setdefault(f"start:{stage}", now)
        if verbosity == QUIET or now - state.get("last", start) < every_s:
            return
        state["last"] = now
        done_shown = min(done, total)
        eta = (now - start) * (total - done_shown) / done_shown if done_shown < total else 0.0
        line = f"{command}: bootstrap {stage}: {done_shown}/{total} resamples, {duration(now - start)} elapsed"
        console.print(f"{_stamp(time.time())} {line}, ETA {duration(eta)}", markup=False, highlight=False)

    token = ON_RESAMPLE.set(hook)
    try:
        yield
    finally:
        ON_RESAMPLE.reset(token)


def _stamp(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def _who(lp: LaunchProgress, ex: Execution) -> str:
    if len(lp.trials) <= 1 or not ex.trials:
        return ex.stage
    shown = ", ".join(ex.trials[:3]) + (f" +{len(ex.trials) - 3}" if len(ex.trials) > 3 else "")
    return f"{ex.stage} · {shown}"


def detail(ex: Execution, now: float) -> str:
    """What a running execution is at: step and loss, scenes, its own progress text, ETA."""
    parts = []
    if ex.steps or ex.step is not None:
        parts.append(f"step {ex.step or 0}/{ex.steps or '?'}")
        if ex.loss is not None:
            parts.append(f"loss {ex.loss:.4g}")
    if ex.scenes_total:
        parts.append(f"scenes {ex.scenes_done()}/{ex.scenes_total}")
    if ex.total:
        parts.append(f"{ex.done}/{ex.total}" + (f" {ex.message}" if ex.message else ""))
    left = ex.remaining_s(now)
    if left is not None and not ex.finished:
        parts.append(f"ETA {duration(left)}")
    return ", ".join(parts)


class Lines:
    """Turns events into log lines (``line``) and emits heartbeats for executions still running (``heartbeats``)."""

    def __init__(self, lp: LaunchProgress, verbosity: int = NORMAL, heartbeat_s: float = 30.0):
        self.lp, self.verbosity, self.heartbeat_s = lp, verbosity, heartbeat_s

    def _count(self) -> str:
        c = self.lp.counts()
        width = len(str(c["executions"]))
        return f"[{c['executions_finished']:>{width}}/{c['executions']:>{width}}]"

    def _trials(self) -> str:
        c = self.lp.counts()
        return f" · trials {c['trials_done'] + c['trials_failed']}/{c['trials']}" if c["trials"] > 1 else ""

    def line(self, ev: Event, ex: Execution | None) -> str | None:
        """The line this (already fed) event prints at this verbosity, or None."""
        v, when = self.verbosity, _stamp(ev.t)
        if ev.kind == "trial" and ev.trials and len(self.lp.trials) > 1:
            if v >= NORMAL or ev.state == "failed":
                what = ev.message or ev.state
                return f"{when} {self._count()} trial '{ev.trials[0]}' {what}{self._trials()}"
            return None
        if ex is None:
            return None
        if ev.kind == "stage":
            ex.last_line = ev.t
            if ev.state == "failed":  # the cause names the stage; a sweep's line names the trials too
                who = f"{_who(self.lp, ex)}: " if len(self.lp.trials) > 1 else ""
                return f"{when} {self._count()} {who}{ev.cause or ex.stage + ' failed'}"
            if ev.state == "running" and v >= VERBOSE:
                return f"{when} {self._count()} {_who(self.lp, ex)}: running"
            if ev.state in ("done", "cached") and v >= NORMAL:
                took = f" in {duration(ev.duration_s)}" if ev.state == "done" and ev.duration_s is not None else ""
                shared = f" (shared by {len(ex.trials)} trials)" if len(ex.trials) > 1 else ""
                extra = f", {ev.message}" if ev.message else ""
                eta = self.lp.eta_s(ev.t)
                left = f" · ETA {duration(eta)}" if eta is not None and self.lp.running() else ""
                what = f"{ev.state}{took}{extra}{shared}"
                return f"{when} {self._count()} {_who(self.lp, ex)}: {what}{self._trials()}{left}"
            return None
        if ev.kind == "scene" and v >= VERBOSE and ev.state in ("done", "cached", "failed"):
            scenes = f"scenes {ex.scenes_done()}/{ex.scenes_total}"
            return f"{when} {self._count()} {_who(self.lp, ex)} {ev.scene}: {ev.state} ({scenes})"
        return None

    def blocked(self, when: float, blocked: list[Execution], because: str) -> str | None:
        """One line for every execution an upstream failure blocked at once."""
        if not blocked or self.verbosity < NORMAL:
            return None
        names = ", ".join(dict.fromkeys(_who(self.lp, e) for e in blocked))
        return f"{_stamp(when)} {self._count()} blocked ({because}): {names}"

    def heartbeats(self, now: float) -> list[str]:
        """A line for each running execution not reported for ``heartbeat_s``."""
        if self.verbosity < NORMAL:
            return []
        out = []
        for ex in self.lp.running():
            last = ex.last_line if ex.last_line is not None else ex.started
            if last is not None and now - last >= self.heartbeat_s:
                ex.last_line = now
                info = detail(ex, now)
                out.append(f"{_stamp(now)} {self._count()} {_who(self.lp, ex)}: running "
                           f"{duration(ex.elapsed(now))}" + (f", {info}" if info else ""))  # fmt: skip
        return out


def board(lp: LaunchProgress) -> Group:
    """The live board: a header line (launch, trials and stages done, elapsed, ETA) over a table: per stage for a
    one-trial launch, else trials x stages (running and failed trials first, at most ``BOARD_TRIALS``)."""
    now = lp.clock()
    head = Text.assemble((f"{lp.kind} {lp.name}", "bold"), "  ", lp.summary())
    if len(lp.trials) <= 1:
        return Group(head, _stage_table(lp, now))
    return Group(head, _trial_table(lp, now))


def _state(state: str) -> Text:
    return Text(state, style=STYLE.get(state, ""))


def _stage_table(lp: LaunchProgress, now: float) -> Table:
    t = Table(header_style="bold", expand=False)
    for col in ("stage", "status", "progress", "wall", "key"):
        t.add_column(col)
    (trial,) = lp.trials or {"": []}
    for stage in lp.stages:
        state, ex = lp.cell(trial, stage)
        if ex is None:
            continue
        wall = duration(ex.elapsed(now)) if ex.started is not None else ""
        cause = ex.cause if ex.state == "failed" else ""
        t.add_row(stage, _state(state), cause or detail(ex, now), wall, ex.key[:12])
    return t


def _trial_table(lp: LaunchProgress, now: float) -> Table:
    t = Table(header_style="bold", expand=False)
    t.add_column("trial")
    t.add_column("state")
    for s in lp.stages:
        t.add_column(s)
    order = {"running": 0, "failed": 1, "pending": 2, "done": 3}
    trials = sorted(lp.trials, key=lambda n: order.get(lp.trial_state(n), 4))
    for name in trials[:BOARD_TRIALS]:
        cells = []
        for s in lp.stages:
            state, ex = lp.cell(name, s)
            text = _state(state)
            if ex is not None and state == "running" and (info := detail(ex, now)):
                text.append(f" {info}", style="")
            cells.append(text)
        t.add_row(name, _state(lp.trial_state(name)), *cells)
    if len(trials) > BOARD_TRIALS:
        rest = trials[BOARD_TRIALS:]
        tally = {}
        for n in rest:
            tally[lp.trial_state(n)] = tally.get(lp.trial_state(n), 0) + 1
        t.add_row(f"+{len(rest)} more", ", ".join(f"{k} {v}" for k, v in tally.items()))
    return t
