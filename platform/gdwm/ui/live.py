"""A launch's live state as the dashboard shows it: the snapshot its driver keeps on its MLflow run, brought up to
date with the launch's ``events.jsonl`` where that file is readable here (a local workdir), and judged stale when its
driver is gone.

The progress model is ``gdwm.progress.LaunchProgress`` (``gdwm.events`` documents states and fields): the snapshot
(``LaunchProgress.snapshot``'s JSON) is turned back into one, the events newer than the snapshot are fed to it, and
its ``snapshot()`` is what the pages render, so the dashboard, the terminal board and ``gdwm status`` agree.

A sweep run by an older gdwm has no snapshot: its trials x stages grid is rebuilt from the trial runs' tags (stage
runs linked, failed stage and error) with the same fields, in ``grid_from_runs``.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gdwm.events import FINISHED, SNAPSHOT_ARTIFACT, Event
from gdwm.progress import Execution, LaunchProgress, duration
from gdwm.tracking.owner import OWNER_TAG, owner_is_alive, parse_owner
from gdwm.ui.store import Store

STALE_AFTER_S = 180.0
"""A RUNNING launch whose driver runs on another host is stale once its snapshot is this old: the driver rewrites it
at least every ``gdwm.monitor.KEEPALIVE_S`` (60 s) while it lives."""


@dataclass
class Live:
    """What a launch page shows of a launch's progress."""

    snapshot: dict[str, Any]
    """``LaunchProgress.snapshot()``'s fields (``trials`` x ``stages`` cells, ``counts``, ``failures``, ``eta_s``)."""
    state: str
    """running, done, failed, killed or stale."""
    source: str
    """Where it came from: ``snapshot``, ``snapshot + events``, ``runs`` (a sweep of an older gdwm)."""
    stale: str = ""
    """Why a RUNNING launch is shown stale (its driver is gone), else empty."""


def from_snapshot(snap: dict[str, Any], clock=time.time) -> LaunchProgress:
    """The ``LaunchProgress`` a snapshot was taken of, as far as the snapshot tells (scenes as counts, estimates as
    the cells' ETAs): enough to feed it the events that came after."""
    trials = {t: [(stage, c["key"]) for stage, c in d.get("stages", {}).items()] for t, d in snap["trials"].items()}
    cells: dict[tuple[str, str], list[tuple[str, dict]]] = {}
    for t, d in snap["trials"].items():
        for stage, c in d.get("stages", {}).items():
            cells.setdefault((stage, c["key"]), []).append((t, c))
    executions = []
    for (stage, key), users in cells.items():
        users.sort(key=lambda tc: tc[1]["state"] == "shared")  # the trial that ran it first
        c = users[0][1]
        state = "done" if c["state"] == "shared" else c["state"]
        ex = Execution(stage, key, [t for t, _ in users], scenes_total=c.get("scenes_total", 0), state=state)
        ex.started = c.get("started")
        if state in FINISHED and ex.started is not None and c.get("duration_s") is not None:
            ex.ended = ex.started + c["duration_s"]
        ex.scenes = {f"#{k}": "done" for k in range(c.get("scenes_done", 0))}
        for name in ("step", "steps", "loss", "done", "total", "cause", "traceback"):
            setattr(ex, name, c.get(name))
        eta = c.get("eta_s")
        ex.estimate_s = (
            0.0
            if state == "cached"
            else (eta if state == "pending" else (c.get("duration_s", 0.0) + eta if eta is not None else None))
        )
        executions.append(ex)
    lp = LaunchProgress(
        snap.get("kind", "sweep"), snap.get("name", ""), snap.get("launch", ""), trials, executions, clock
    )
    lp.started = snap.get("started", lp.started)
    if snap.get("state") != "running":
        lp.ended = lp.started + snap.get("elapsed_s", 0.0)
    lp.trial_done = {t: d["state"] for t, d in snap["trials"].items() if d.get("state") in ("done", "failed")}
    return lp


class EventsTail:
    """A launch's ``events.jsonl``, read incrementally (its driver appends while the dashboard polls)."""

    def __init__(self, path: Path):
        self.path, self.offset, self.events = path, 0, []

    def read(self) -> list[Event]:
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            chunk = f.read()
        end = chunk.rfind(b"\n") + 1  # a partial last line waits for its newline
        for line in chunk[:end].decode("utf-8", errors="replace").splitlines():
            if line.strip():
                try:
                    import json

                    self.events.append(Event.from_dict(json.loads(line)))
                except (ValueError, TypeError):
                    continue  # a line of a newer format
        self.offset += end
        return self.events


_TAILS: dict[Path, EventsTail] = {}


def events_after(path: Path, t: float) -> list[Event]:
    tail = _TAILS.get(path)
    if tail is None:
        tail = _TAILS[path] = EventsTail(path)
    return [e for e in tail.read() if e.t > t]


def stale_reason(run: dict, updated: float | None, now: float) -> str:
    """Why a RUNNING run is stale: its driver's process is gone (same host), or no snapshot came for
    ``STALE_AFTER_S`` (another host); empty while it may be alive."""
    if run["status"] != "RUNNING":
        return ""
    owner = run["tags"].get(OWNER_TAG, "")
    parsed = parse_owner(owner) if owner else None
    if parsed is not None and parsed[0] == socket.gethostname():
        return "" if owner_is_alive(owner) else f"its driver (pid {parsed[1]} on this host) is gone"
    if updated is not None and now - updated > STALE_AFTER_S:
        host = f" on {parsed[0]}" if parsed else ""
        return f"no news from its driver{host} for {duration(now - updated)}"
    return ""


def _status_state(run: dict) -> str:
    return {"RUNNING": "running", "FINISHED": "done", "FAILED": "failed", "KILLED": "killed"}.get(
        run["status"], run["status"].lower()
    )


def launch_live(store: Store, run: dict, workdirs: list[Path], now: float | None = None) -> Live | None:
    """The launch's progress from its snapshot (and local events file); None when it has no snapshot."""
    now = time.time() if now is None else now
    snap = store.json(run["run_id"], SNAPSHOT_ARTIFACT)
    if not snap or "trials" not in snap:
        return None
    source = "snapshot"
    rel = run["tags"].get("gdwm.events") or snap.get("events")
    path = next((w / rel for w in workdirs if rel and (w / rel).is_file()), None)
    updated = snap.get("updated")
    if path is not None and run["status"] == "RUNNING":
        newer = events_after(path, snap.get("updated", 0.0))
        if newer:
            lp = from_snapshot(snap)
            for ev in newer:
                lp.feed(ev)
            snap = lp.snapshot(rel) | {"events": rel}
            source = "snapshot + events"
        updated = max(updated or 0.0, path.stat().st_mtime)
    stale = stale_reason(run, updated, now)
    if run["status"] == "RUNNING":
        state = "stale" if stale else snap.get("state", "running")
    else:
        state = _status_state(run)
    return Live(snap, state, source, stale)


def grid_from_runs(sweep: dict, trials: list[dict], stage_runs: dict[str, dict]) -> dict[str, Any]:
    """A snapshot-shaped grid of a sweep without a snapshot: per trial (in table order) each stage it linked
    (``done`` for the first trial that used a stage run made by this sweep, ``shared`` for the others, ``cached``
    for one made before it), ``failed`` with the trial's error, and ``blocked`` for the stages after the failure."""
    order: dict[str, float] = {}
    for t in trials:
        for k, rid in t["tags"].items():
            if k.startswith("gdwm.stage_run."):
                start = stage_runs.get(rid, {}).get("start_time") or 0
                stage = k.removeprefix("gdwm.stage_run.")
                order[stage] = min(order.get(stage, start), start)
    for t in trials:
        failed = t["tags"].get("gdwm.failed_stage")
        if failed and failed not in order:
            order[failed] = max(order.values(), default=0) + 1
    stages = sorted(order, key=order.__getitem__)
    seen: set[str] = set()
    out: dict[str, Any] = {}
    failures = []
    for t in trials:
        tags = t["tags"]
        cells: dict[str, dict] = {}
        failed = tags.get("gdwm.failed_stage")
        for stage in stages:
            key = tags.get(f"gdwm.stage_key.{stage}", "")
            rid = tags.get(f"gdwm.stage_run.{stage}")
            if stage == failed:
                cause = tags.get("gdwm.error", "").strip().splitlines()
                cells[stage] = {"state": "failed", "key": key, "cause": cause[0] if cause else ""}
                failures.append(
                    {
                        "stage": stage,
                        "key": key,
                        "trials": [trial_label(t, sweep)],
                        "cause": cells[stage]["cause"],
                        "traceback": None,
                    }
                )
            elif rid:
                sr = stage_runs.get(rid, {})
                before = (sr.get("start_time") or 0) < (sweep.get("start_time") or 0)
                state = "cached" if before else ("shared" if rid in seen else "done")
                seen.add(rid)
                started, ended = sr.get("start_time"), sr.get("end_time")
                cells[stage] = {"state": state, "key": key or sr.get("tags", {}).get("gdwm.cache_key", "")}
                if state == "done" and started and ended:
                    cells[stage]["duration_s"] = round((ended - started) / 1000, 1)
            elif failed and order.get(stage, 0) > order.get(failed, 0):
                cells[stage] = {"state": "blocked", "key": key}
        state = "failed" if failed or t["status"] == "FAILED" else _status_state(t)
        out[trial_label(t, sweep)] = {"state": state, "stages": cells}
    done = sum(d["state"] == "done" for d in out.values())
    fails = sum(d["state"] == "failed" for d in out.values())
    return {
        "trials": out,
        "stages": stages,
        "failures": failures,
        "eta_s": None,
        "state": _status_state(sweep),
        "counts": {"trials": len(out), "trials_done": done, "trials_failed": fails},
    }


def trial_label(trial: dict, sweep: dict) -> str:
    """A trial as progress names it: its run name without the ``<sweep>/`` prefix."""
    name = trial["name"] or trial["run_id"][:8]
    prefix = f"{sweep['tags'].get('gdwm.sweep', '')}/"
    return name.removeprefix(prefix)
