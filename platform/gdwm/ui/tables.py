"""Sweep tables, computed once per set of finished trials and kept.

A sweep's fingerprint is its finished row and trial runs (id and status): while it is unchanged the page shows the
kept table; when a trial finishes, one job of ``gdwm.ui.worker`` computes the new table (the previous one stays on
the page, marked as being updated). Jobs run one at a time in a worker process; a newer fingerprint of a sweep
replaces its queued job. The table comes first, then the factor effects, then the HTML report.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Entry:
    """One sweep's table as far as it is known."""

    fingerprint: tuple = ()
    state: str = "queued"
    """queued, computing, ready, failed."""
    progress: str = ""
    """What the worker is doing (``bootstrap <stage>: 312/1000 resamples``)."""
    table: dict[str, Any] | None = None
    """The worker's ``table`` event (html, downloads, cells, key metric, ...) of ``table_fingerprint``."""
    table_fingerprint: tuple = ()
    effects: list[dict] | None = None
    report: str | None = None
    error: str = ""
    warnings: list[str] = field(default_factory=list)
    started: float | None = None
    seconds: float | None = None
    version: int = 0
    """Grows with every new table: a page replaces its table when this changes."""

    @property
    def current(self) -> bool:
        return self.table is not None and self.table_fingerprint == self.fingerprint


@dataclass
class Job:
    sweep_id: str
    fingerprint: tuple
    payload: dict[str, Any]


class Tables:
    """The dashboard's tables, by sweep run id; ``want`` asks for one, ``get`` reads what is there."""

    def __init__(self, env: dict[str, str] | None = None, hold: threading.Event | None = None):
        self.entries: dict[str, Entry] = {}
        self.env = env
        self.hold = hold
        """Jobs start once it is set (``gdwm ui`` sets it when its first page has answered: a worker starting
        meanwhile would slow that page down)."""
        self._queue: queue.Queue[str] = queue.Queue()
        self._pending: dict[str, Job] = {}
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._thread = threading.Thread(target=self._loop, name="gdwm-ui-tables", daemon=True)
        self._thread.start()

    def get(self, sweep_id: str) -> Entry | None:
        return self.entries.get(sweep_id)

    def want(self, sweep_id: str, fingerprint: tuple, payload: dict[str, Any]) -> Entry:
        """The sweep's entry; a job for ``fingerprint`` is queued unless its table is kept or being computed."""
        with self._lock:
            e = self.entries.setdefault(sweep_id, Entry())
            if e.fingerprint == fingerprint and e.state != "failed":
                return e
            if e.fingerprint == fingerprint and e.state == "failed" and time.time() - (e.started or 0) < 60:
                return e  # a failed job is retried after a minute, not on every poll
            e.fingerprint, e.state, e.progress, e.error = fingerprint, "queued", "", ""
            first = sweep_id not in self._pending
            self._pending[sweep_id] = Job(sweep_id, fingerprint, payload)
        if first:
            self._queue.put(sweep_id)
        return e

    def _loop(self) -> None:
        while True:
            sweep_id = self._queue.get()
            if self.hold is not None:
                self.hold.wait()
            with self._lock:
                job = self._pending.pop(sweep_id, None)
            if job is not None:
                self._run(job)

    def _run(self, job: Job) -> None:
        e = self.entries[job.sweep_id]
        e.state, e.started, e.progress, e.warnings = "computing", time.time(), "starting", []
        env = dict(self.env if self.env is not None else os.environ)
        proc = subprocess.Popen(
            [sys.executable, "-m", "gdwm.ui.worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        self._proc = proc
        err: list[str] = []
        drain = threading.Thread(target=lambda: err.extend(proc.stderr), daemon=True)
        drain.start()
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write(json.dumps(job.payload))
        proc.stdin.close()
        for line in proc.stdout:
            try:
                msg = json.loads(line)
            except json.JSONDecodeError:
                continue
            self._apply(e, job, msg)
        proc.wait()
        drain.join(timeout=5)
        self._proc = None
        if e.state == "computing":  # the worker died before its table
            tail = [ln.strip() for ln in err if ln.strip()]
            e.state, e.error = "failed", (tail[-1] if tail else f"the table worker exited {proc.returncode}")
        e.seconds = round(time.time() - (e.started or time.time()), 1)

    def _apply(self, e: Entry, job: Job, msg: dict[str, Any]) -> None:
        kind = msg.get("event")
        if kind == "progress":
            done = min(msg["done"], msg["total"])
            e.progress = f"bootstrap {msg['stage']}: {done}/{msg['total']} resamples"
        elif kind == "warning":
            e.warnings.append(msg["line"])
        elif kind == "table":
            e.table, e.table_fingerprint, e.state = msg, job.fingerprint, "ready"
            e.effects, e.report, e.progress = None, None, "factor effects"
            e.version += 1
        elif kind == "effects":
            e.effects, e.progress = msg["effects"], "HTML report" if job.payload.get("report") else ""
        elif kind == "report":
            e.report, e.progress = msg["html"], ""
        elif kind == "error":
            e.state, e.error = "failed", msg["line"]

    def close(self) -> None:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()


class Whys:
    """Why each stage of a trial ran (``gdwm.ui.worker``'s ``why`` job over the cache's manifests), asked once per
    trial and kept."""

    def __init__(self, cache_uri: str, env: dict[str, str] | None = None):
        self.cache_uri, self.env = cache_uri, env
        self.found: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()

    def get(self, run_id: str, stages: list[tuple[str, str]] | None = None) -> dict[str, Any]:
        """``{"ready": bool, "why": {stage: text}, "error": ...}``; ``stages`` (stage, stage run id) starts the job."""
        with self._lock:
            hit = self.found.get(run_id)
            if hit is None and stages:
                hit = self.found[run_id] = {"ready": False, "why": {}}
                threading.Thread(target=self._run, args=(run_id, stages), daemon=True).start()
        return hit or {"ready": False, "why": {}}

    def _run(self, run_id: str, stages: list[tuple[str, str]]) -> None:
        job = {"kind": "why", "cache": self.cache_uri, "stages": stages}
        env = dict(self.env if self.env is not None else os.environ)
        r = subprocess.run(
            [sys.executable, "-m", "gdwm.ui.worker"], input=json.dumps(job), capture_output=True, text=True, env=env
        )
        out: dict[str, Any] = {"ready": True, "why": {}}
        for line in r.stdout.splitlines():
            msg = json.loads(line)
            if msg.get("event") == "why":
                out["why"] = msg["why"]
            elif msg.get("event") == "error":
                out["error"] = msg["line"]
        if r.returncode and "error" not in out:
            tail = [ln for ln in r.stderr.splitlines() if ln.strip()]
            out["error"] = tail[-1] if tail else f"exit {r.returncode}"
        self.found[run_id] = out
