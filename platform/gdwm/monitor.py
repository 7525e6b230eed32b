"""The driver's side of a launch's progress: every event is fed to the ``LaunchProgress``, appended to the launch's
``events.jsonl``, printed (a line, or the live board in a terminal) and, at most every ``run.snapshot_s``, written
as a snapshot onto the launch's MLflow run (``gdwm.events`` documents all three). A failure's full traceback goes to
a file in the launch's folder, and its one line names that file."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import ray
from rich.live import Live

from gdwm.board import Lines, board
from gdwm.events import EVENTS_FILE, SNAPSHOT_ARTIFACT, TRACEBACKS_DIR, Event, EventLog
from gdwm.progress import Execution, LaunchProgress
from gdwm.term import NORMAL, QUIET, console
from gdwm.tracking.writes import RunWrite

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
KEEPALIVE_S = 60.0
"""The snapshot is rewritten at least this often while the launch runs, changed or not: its ``updated`` time tells a
dashboard on another host that the driver is alive (``gdwm.ui.live``)."""


class Monitor:
    """Holds one launch's progress state, its events file, its rendering and its MLflow snapshot."""

    def __init__(
        self,
        lp: LaunchProgress,
        workdir: Path,
        shown_workdir: str,
        *,
        actor: Any = None,
        tracking: Any = None,
        run_id: str | None = None,
        verbosity: int = NORMAL,
        live: bool = False,
        heartbeat_s: float = 30.0,
        snapshot_s: float = 10.0,
    ):
        self.lp, self.workdir, self.shown_workdir = lp, workdir, shown_workdir
        self.dir = workdir / "logs" / lp.launch
        self.log = EventLog(self.dir / EVENTS_FILE)
        self.actor, self.tracking, self.run_id = actor, tracking, run_id
        self.lines = Lines(lp, verbosity, heartbeat_s)
        self.board = live and console.is_terminal and verbosity > QUIET
        self.snapshot_s = snapshot_s
        self._snapshot_at = -float("inf")
        self._changed = True
        self._live: Live | None = None

    def rel(self, path: Path) -> str:
        """``path`` relative to the workdir (what files and MLflow record)."""
        return path.relative_to(self.workdir).as_posix()

    def shown(self, rel: str) -> str:
        """A workdir-relative path as the user names it (``gdwm-work/logs/...``)."""
        return f"{self.shown_workdir.rstrip('/')}/{rel}"

    @property
    def events_path(self) -> str:
        return self.rel(self.dir / EVENTS_FILE)

    # ---- lifecycle -----------------------------------------------------------------------------------------------
    def __enter__(self) -> Monitor:
        if self.board:
            self._live = Live(board(self.lp), console=console, refresh_per_second=4, transient=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        try:
            if self._live is not None:
                self._live.update(board(self.lp))
                self._live.__exit__(*exc)
                self._live = None
            self.snapshot(force=True)
        finally:
            self.log.close()

    # ---- events --------------------------------------------------------------------------------------------------
    def emit(self, ev: Event) -> Execution | None:
        ev.launch = ev.launch or self.lp.launch
        ex = self.lp.feed(ev)
        self.log.write(ev)
        self._changed = True
        line = self.lines.line(ev, ex)
        if line is not None:
            self.say(line, error=ev.state == "failed")
        return ex

    def say(self, line: str, error: bool = False) -> None:
        """A line of the log (above the board in a terminal); failures show even with ``--quiet``."""
        if self.lines.verbosity == QUIET and not error:
            return
        if self._live is not None:
            self._live.console.print(line, markup=False, highlight=False, soft_wrap=True)
        else:
            console.print(line, markup=False, highlight=False, soft_wrap=True)

    def poll(self) -> None:
        """Drain the workers' events, print heartbeats, redraw, snapshot when due."""
        if self.actor is not None:
            for d in ray.get(self.actor.drain.remote()):
                self.emit(Event.from_dict(d))
        now = time.time()
        if not self.board:
            for line in self.lines.heartbeats(now):
                self.say(line)
        if self._live is not None:
            self._live.update(board(self.lp))
        self.snapshot()

    def traceback(self, stage: str, key: str, text: str) -> str:
        """Write a failure's full traceback into the launch's folder; returns its path relative to the workdir."""
        path = self.dir / TRACEBACKS_DIR / f"{stage}-{key[:12]}.txt"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(_ANSI.sub("", text), encoding="utf-8")
        return self.rel(path)

    def snapshot(self, force: bool = False) -> None:
        """The launch's state onto its MLflow run (tags and ``progress/snapshot.json``), at most every
        ``snapshot_s`` unless ``force``; when unchanged, only every ``KEEPALIVE_S``."""
        if self.tracking is None or self.run_id is None:
            return
        now = time.monotonic()
        if not force and now - self._snapshot_at < (self.snapshot_s if self._changed else KEEPALIVE_S):
            return
        self._snapshot_at, self._changed = now, False
        snap = self.lp.snapshot(self.events_path)
        c = snap["counts"]
        tags = {
            "gdwm.state": snap["state"], "gdwm.progress": snap["summary"], "gdwm.events": self.events_path,
            "gdwm.trials_done": str(c["trials_done"]), "gdwm.trials_failed": str(c["trials_failed"]),
            "gdwm.trials_total": str(c["trials"]),
        }  # fmt: skip
        self.tracking.write([RunWrite(self.run_id, tags=tags, texts={SNAPSHOT_ARTIFACT: json.dumps(snap, indent=1)})])
