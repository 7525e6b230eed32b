"""What each dashboard page shows, read from the store (``Store``) and kept where it cannot change.

- launches (home): sweeps, ``gdwm run`` launches and regressions, newest first, with state (stale when the driver
  is gone), trials done / total, best row and key metric, started, duration;
- a sweep: its run, rows, trials and stage runs (one search of the runs tagged with the sweep's name), its
  ``sweep.yaml`` (layout, baseline), its live state (``live``) and the fingerprint its table is kept under;
- a trial: its tags, params, stages (key, how it was produced, the stage run) and the row it is compared with;
- regressions: each benchmark's runs with their checks (``regression.json``, else ``regression.md``), commit and code
  digest;
- the zoo: every registered version with the sweep row that trained it and the table's key metric.
"""

from __future__ import annotations

import hashlib
import json
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gdwm.progress import duration
from gdwm.tracking.params import full_params, inherited_params
from gdwm.ui.live import Live, grid_from_runs, launch_live, stale_reason, trial_label
from gdwm.ui.store import TERMINAL, Store

KINDS = ("sweep", "run", "regression")
STATES = ("running", "stale", "done", "failed", "killed")
_STATUS = {"RUNNING": "running", "FINISHED": "done", "FAILED": "failed", "KILLED": "killed"}


def when(ms: int | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(ms / 1000)) if ms else ""


def took(run: dict, now: float | None = None) -> str:
    if not run.get("start_time"):
        return ""
    end = run.get("end_time") or (now or time.time()) * 1000
    return duration((end - run["start_time"]) / 1000)


def state_of(run: dict, now: float | None = None) -> tuple[str, str]:
    """(state, why stale): the snapshot's state while it runs (``stale`` when its driver is gone), else its status."""
    if run["status"] == "RUNNING":
        why = stale_reason(run, None, now or time.time())
        return ("stale", why) if why else (run["tags"].get("gdwm.state", "running"), "")
    return _STATUS.get(run["status"], run["status"].lower()), ""


@dataclass
class Launch:
    """One line of the home page."""

    kind: str
    run: dict
    name: str
    state: str
    stale: str
    trials: str
    best: str
    started: str
    took: str
    href: str


class Cache:
    """Values kept per key until the key changes (a finished run's data), with a lock per computation."""

    def __init__(self) -> None:
        self._data: dict[Any, tuple[Any, Any]] = {}
        self._lock = threading.Lock()

    def get(self, name: Any, key: Any, make):
        hit = self._data.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        value = make()
        with self._lock:
            self._data[name] = (key, value)
        return value


@dataclass
class Context:
    """What every page reads: the store, where local files are, where MLflow's UI is, the kept tables."""

    store: Store
    workdirs: list[Path]
    mlflow_url: str | None
    tables: Any
    whys: Any = None
    poll_s: float = 2.0
    overrides: list[str] = field(default_factory=list)
    cache: Cache = field(default_factory=Cache)
    _home: tuple[float, dict] | None = None

    def mlflow_run(self, run: dict) -> str | None:
        if not self.mlflow_url:
            return None
        return f"{self.mlflow_url.rstrip('/')}/#/experiments/{run['experiment_id']}/runs/{run['run_id']}"

    def mlflow_model(self, name: str, version: int) -> str | None:
        return f"{self.mlflow_url.rstrip('/')}/#/models/{name}/versions/{version}" if self.mlflow_url else None


# ---- home ------------------------------------------------------------------------------------------------------
def _trial_counts(ctx: Context, sweep: dict) -> tuple[int, int, int]:
    """(done, failed, total) of a sweep: its snapshot's counts, else its trial runs' statuses."""
    tags = sweep["tags"]
    if "gdwm.trials_total" in tags:
        return (
            int(tags.get("gdwm.trials_done", 0)),
            int(tags.get("gdwm.trials_failed", 0)),
            int(tags["gdwm.trials_total"]),
        )
    name = tags.get("gdwm.sweep", "")

    def count() -> tuple[int, int, int]:
        found = ctx.store.search(f"tags.`gdwm.kind` = 'trial' and tags.`gdwm.sweep` = '{_q(name)}'", 10000)
        rows = {r["run_id"] for r in ctx.store.search(f"tags.`mlflow.parentRunId` = '{sweep['run_id']}'", 10000)}
        mine = [t for t in found if t["tags"].get("mlflow.parentRunId") in rows | {sweep["run_id"]}]
        done = sum(t["status"] == "FINISHED" for t in mine)
        failed = sum(t["status"] == "FAILED" for t in mine)
        return done, failed, len(mine)

    return ctx.cache.get(("counts", sweep["run_id"]), (sweep["status"], sweep["end_time"]), count)


def _q(s: str) -> str:
    return s.replace("'", "\\'")


def _best(ctx: Context, sweep: dict) -> str:
    tags = sweep["tags"]
    entry = ctx.tables.get(sweep["run_id"]) if ctx.tables is not None else None
    if entry is not None and entry.table and entry.table.get("best_row"):
        t = entry.table
        return f"{t['best_row']} ({t.get('key_label') or t['key_metric']} {t['best_value']:.2f})"
    if "gdwm.best_row" in tags:
        value = float(tags.get("gdwm.best_value", "nan"))
        return f"{tags['gdwm.best_row']} ({tags.get('gdwm.key_metric', '')} {value:.2f})"
    return ""


def launches(ctx: Context, name: str = "", state: str = "", limit: int = 200) -> dict[str, list[Launch]]:
    """Sweeps, runs and regressions, newest first, filtered by a name substring and a state."""
    now = time.time()
    out: dict[str, list[Launch]] = {}
    for kind in KINDS:
        found = ctx.store.search(f"tags.`gdwm.kind` = '{kind}'", limit, ["attributes.start_time DESC"])
        rows = []
        for r in found:
            tags = r["tags"]
            label = tags.get("gdwm.sweep") or tags.get("gdwm.benchmark") or r["name"] or r["run_id"][:8]
            if name and name.lower() not in label.lower():
                continue
            st, stale = state_of(r, now)
            if kind == "regression" and r["status"] == "FINISHED":
                st = {"pass": "done", "fail": "failed"}.get(tags.get("gdwm.verdict", ""), st)
            if state and st != state:
                continue
            if kind == "sweep":
                done, failed, total = _trial_counts(ctx, r)
                trials = f"{done}/{total}" + (f" ({failed} failed)" if failed else "")
                href, best = f"/sweeps/{r['run_id']}", _best(ctx, r)
            elif kind == "run":
                seeds = [s for s in tags.get("gdwm.seeds", "").split(",") if s]
                trials, href, best = f"{len(seeds)} seed(s)" if seeds else "", f"/runs/{r['run_id']}", ""
            else:
                trials = tags.get("gdwm.verdict", "")
                href = f"/regressions?benchmark={tags.get('gdwm.benchmark', '')}#run-{r['run_id']}"
                best = "baseline" if tags.get("gdwm.baseline") == "true" else ""
            rows.append(Launch(kind, r, label, st, stale, trials, best, when(r["start_time"]), took(r, now), href))
        out[kind] = rows
    return out


def newest_sweep(store: Store) -> dict | None:
    found = store.search("tags.`gdwm.kind` = 'sweep'", 1, ["attributes.start_time DESC"])
    return found[0] if found else None


# ---- a sweep ---------------------------------------------------------------------------------------------------
@dataclass
class Sweep:
    run: dict
    name: str
    rows: list[dict]
    """Row runs in table order (the newest run of each label)."""
    trials: list[dict]
    """Trial runs in table order (row, then seed)."""
    stage_runs: dict[str, dict]
    config: dict
    """``sweep.yaml`` (layout, baseline, rows) as logged by the sweep; empty when absent."""

    @property
    def fingerprint(self) -> tuple:
        """The finished rows and trials: the table changes only when this does."""
        done = [(r["run_id"], r["status"]) for r in self.rows + self.trials if r["status"] in TERMINAL]
        return (self.config.get("layout"), self.config.get("baseline"), *sorted(done))

    def trial_href(self) -> dict[str, str]:
        """Trial label (as progress names it) -> its page."""
        return {trial_label(t, self.run): f"/trials/{t['run_id']}" for t in self.trials}


def _row_order(r: dict) -> tuple:
    idx = r["tags"].get("gdwm.trial_index", "")
    seed = r["tags"].get("gdwm.seed", "")
    return (0, int(idx)) if idx.lstrip("-").isdigit() else (1, r["start_time"] or 0), int(seed) if seed.isdigit() else 0


def load_sweep(ctx: Context, run: dict) -> Sweep:
    """The sweep's runs, re-read only when its run changed (status, end, snapshot tags): one search by its name."""
    tags = run["tags"]
    key = (
        run["status"],
        run["end_time"],
        tags.get("gdwm.trials_done"),
        tags.get("gdwm.trials_failed"),
        tags.get("gdwm.progress"),
    )

    def make() -> Sweep:
        name = tags.get("gdwm.sweep", run["name"])
        found = ctx.store.search(f"tags.`gdwm.sweep` = '{_q(name)}'", 100000)
        kids = [r for r in found if r["tags"].get("mlflow.parentRunId") == run["run_id"]]
        rows = sorted((r for r in kids if r["tags"].get("gdwm.kind") == "row"), key=_row_order)
        newest: dict[str, dict] = {}
        for r in rows:  # a row launched again after its config changed: the table shows the newest
            label = r["tags"].get("gdwm.row", r["run_id"])
            if label not in newest or (r["start_time"] or 0) > (newest[label]["start_time"] or 0):
                newest[label] = r
        rows = [r for r in rows if newest.get(r["tags"].get("gdwm.row", r["run_id"])) is r]
        parents = {r["run_id"] for r in rows} | {run["run_id"]}
        trials = [
            r for r in found if r["tags"].get("gdwm.kind") == "trial" and r["tags"].get("mlflow.parentRunId") in parents
        ]
        row_at = {r["run_id"]: i for i, r in enumerate(rows)}
        trials.sort(key=lambda t: (row_at.get(t["tags"].get("mlflow.parentRunId"), -1), _row_order(t)))
        stages = {r["run_id"]: r for r in found if "gdwm.stage" in r["tags"]}
        config = {}
        text = ctx.store.text(run["run_id"], "sweep.yaml")
        if text:
            import yaml

            try:
                config = yaml.safe_load(text) or {}
            except yaml.YAMLError:
                config = {}
        return Sweep(run, name, rows, trials, stages, config)

    return ctx.cache.get(("sweep", run["run_id"]), key, make)


def sweep_live(ctx: Context, sweep: Sweep) -> Live:
    """The launch's progress: its snapshot (and events), else a grid rebuilt from its runs."""
    live = launch_live(ctx.store, sweep.run, ctx.workdirs)
    if live is not None:
        return live
    grid = grid_from_runs(sweep.run, sweep.trials, sweep.stage_runs)
    state, stale = state_of(sweep.run)
    return Live(grid, state, "runs", stale)


def table_job(ctx: Context, sweep: Sweep) -> dict[str, Any]:
    return {
        "sweep": sweep.name,
        "layout": sweep.config.get("layout"),
        "baseline": sweep.config.get("baseline"),
        "overrides": ctx.overrides,
        "mlflow_url": ctx.mlflow_url,
        "links": {r["run_id"]: _row_href(sweep, r) for r in sweep.rows + sweep.trials},
        "report": True,
    }


def _row_href(sweep: Sweep, row: dict) -> str:
    """A row's label links to its first trial's page (a row of one trial is that trial)."""
    if row["tags"].get("gdwm.kind") == "trial":
        return f"/trials/{row['run_id']}"
    mine = [t for t in sweep.trials if t["tags"].get("mlflow.parentRunId") == row["run_id"]]
    return f"/trials/{mine[0]['run_id']}" if mine else f"/runs/{row['run_id']}"


def want_table(ctx: Context, sweep: Sweep):
    """The sweep's kept table entry, a job queued when its finished trials changed (the newest sweep of a name
    only: ``gdwm compare args.sweep=NAME`` compares that one)."""
    if not any(t["status"] in TERMINAL for t in sweep.trials):
        return ctx.tables.get(sweep.run["run_id"])
    return ctx.tables.want(sweep.run["run_id"], sweep.fingerprint, table_job(ctx, sweep))


# ---- a trial ---------------------------------------------------------------------------------------------------
@dataclass
class StageLine:
    stage: str
    key: str
    state: str
    run: dict | None
    seconds: str
    cause: str = ""
    log: list[str] = field(default_factory=list)


def _flat_diff(a: dict[str, str], b: dict[str, str]) -> list[tuple[str, str, str]]:
    return [(k, a.get(k, "–"), b.get(k, "–")) for k in sorted(a.keys() | b.keys()) if a.get(k) != b.get(k)]


def _config(trial: dict, runs: dict[str, dict]) -> dict[str, str]:
    """A trial's config as params: its row's run's (over its sweep's run's, where the row says so) overlaid with its
    own (``gdwm.tracking.full_params``); ``runs``: run id -> run."""
    row = runs.get(trial["tags"].get("mlflow.parentRunId", ""))
    if row is None:
        return dict(trial["params"])
    return full_params(trial["params"], row["params"], inherited_params(row["tags"], runs))


def trial_page(ctx: Context, run_id: str) -> dict[str, Any]:
    """A trial's (or a ``gdwm run``'s) page data: its sweep, the row compared with and the config diff, stages."""
    run = ctx.store.run(run_id)
    tags = run["tags"]
    parent = ctx.store.run(tags["mlflow.parentRunId"]) if tags.get("mlflow.parentRunId") else None
    sweep_run = None
    if parent is not None and parent["tags"].get("gdwm.kind") == "sweep":
        sweep_run = parent
    elif parent is not None and parent["tags"].get("mlflow.parentRunId"):
        grand = ctx.store.run(parent["tags"]["mlflow.parentRunId"])
        sweep_run = grand if grand["tags"].get("gdwm.kind") == "sweep" else None
    sweep = load_sweep(ctx, sweep_run) if sweep_run is not None else None
    live = sweep_live(ctx, sweep) if sweep is not None else launch_live(ctx.store, run, ctx.workdirs)
    label = trial_label(run, sweep_run) if sweep_run is not None else f"seed {tags.get('gdwm.seed', '0')}"
    cells = (live.snapshot["trials"].get(label) or {}).get("stages", {}) if live is not None else {}
    if not cells and live is not None and len(live.snapshot.get("trials", {})) == 1:
        cells = next(iter(live.snapshot["trials"].values())).get("stages", {})

    compared, diff = None, []
    if sweep is not None and sweep.trials:
        base_label = sweep.config.get("baseline")
        base_rows = [r for r in sweep.rows if r["tags"].get("gdwm.row") == base_label] if base_label else []
        base_row = (base_rows or sweep.rows or [None])[0]
        candidates = [
            t for t in sweep.trials if base_row and t["tags"].get("mlflow.parentRunId") == base_row["run_id"]
        ] or sweep.trials
        same_seed = [t for t in candidates if t["tags"].get("gdwm.seed") == tags.get("gdwm.seed")]
        compared = (same_seed or candidates)[0]
        if compared["run_id"] == run_id and len(sweep.trials) > 1:  # the baseline itself: against the next row
            others = [
                t
                for t in sweep.trials
                if t["tags"].get("mlflow.parentRunId") != compared["tags"].get("mlflow.parentRunId")
            ]
            compared = others[0] if others else None
        if compared is not None:
            runs = {r["run_id"]: r for r in [sweep_run, *sweep.rows, *([parent] if parent is not None else [])]}
            diff = _flat_diff(_config(compared, runs), _config(run, runs))

    stages = []
    names = list(cells) or sorted({k.removeprefix("gdwm.stage_key.") for k in tags if k.startswith("gdwm.stage_key.")})
    events = _stage_events(ctx, sweep_run or run)
    for stage in names:
        c = cells.get(stage, {})
        key = c.get("key") or tags.get(f"gdwm.stage_key.{stage}", "")
        rid = tags.get(f"gdwm.stage_run.{stage}")
        srun = sweep.stage_runs.get(rid) if sweep is not None and rid else None
        if srun is None and rid:
            try:
                srun = ctx.store.run(rid)
            except Exception:
                srun = None
        if srun is None and sweep is not None and key:
            srun = next((r for r in sweep.stage_runs.values() if r["tags"].get("gdwm.cache_key") == key), None)
        secs = c.get("duration_s")
        if secs is None and srun is not None and srun.get("end_time") and c.get("state", "done") == "done":
            secs = (srun["end_time"] - srun["start_time"]) / 1000
        lines = events.get((stage, key), [])
        if srun is not None and srun["status"] == "FAILED":
            err = ctx.store.text(srun["run_id"], "error.txt")
            lines += [f"error.txt: {ln}" for ln in (err or "").strip().splitlines()[-12:]]
        tb = c.get("traceback")
        for w in ctx.workdirs:
            if tb and (w / tb).is_file():
                lines += [f"{tb}: {ln}" for ln in (w / tb).read_text(errors="replace").strip().splitlines()[-12:]]
                break
        stages.append(
            StageLine(
                stage,
                key,
                c.get("state", "done" if srun else ""),
                srun,
                duration(secs) if secs is not None else "",
                c.get("cause", ""),
                lines[-20:],
            )
        )
    if not cells and tags.get("gdwm.failed_stage"):
        for s in stages:
            if s.stage == tags["gdwm.failed_stage"]:
                s.state, s.cause = (
                    "failed",
                    tags.get("gdwm.error", "").splitlines()[0] if tags.get("gdwm.error") else "",
                )
    artifacts = ctx.store.artifacts(run_id)
    return {
        "run": run,
        "sweep": sweep,
        "label": label,
        "compared": compared,
        "diff": diff,
        "stages": stages,
        "artifacts": artifacts,
        "live": live,
    }


def _stage_events(ctx: Context, launch_run: dict) -> dict[tuple[str, str], list[str]]:
    """(stage, key) -> its lines of the launch's events file (what a piped launch prints), where it is local."""
    rel = launch_run["tags"].get("gdwm.events")
    path = next((w / rel for w in ctx.workdirs if rel and (w / rel).is_file()), None)
    if path is None:
        return {}
    from gdwm.events import read_events

    out: dict[tuple[str, str], list[str]] = {}
    for ev in read_events(path):
        if ev.stage is None or ev.key is None or ev.kind not in ("stage", "scene", "step", "progress"):
            continue
        parts = [time.strftime("%H:%M:%S", time.localtime(ev.t)), ev.kind]
        if ev.scene:
            parts.append(ev.scene)
        if ev.state:
            parts.append(ev.state)
        if ev.step is not None:
            parts.append(f"step {ev.step}/{ev.steps or '?'}" + (f" loss {ev.loss:.4g}" if ev.loss is not None else ""))
        if ev.done is not None and ev.total:
            parts.append(f"{ev.done}/{ev.total}")
        if ev.duration_s is not None:
            parts.append(f"in {duration(ev.duration_s)}")
        for text in (ev.message, ev.cause):
            if text:
                parts.append(text)
        out.setdefault((ev.stage, ev.key), []).append(" ".join(parts))
    return out


# ---- regressions -----------------------------------------------------------------------------------------------
_MD_ROW = re.compile(
    r"^\|\s*(?P<metric>[^|]+?)\s*\|\s*(?P<base>[^|]*?)\s*\|\s*(?P<now>[^|]*?)\s*\|[^|]*\|"
    r"\s*(?P<tol>[^|]*?)\s*\|\s*(?P<verdict>[^|]*?)\s*\|$"
)


def _num(s: str | None) -> float | None:
    try:
        return None if s in (None, "", "–") else float(s)
    except ValueError:
        return None


def checks_of(ctx: Context, run: dict) -> list[dict]:
    """A regression run's checks: ``regression.json`` (metric, direction, baseline, now, tolerance, allowed band,
    verdict), else the rows of its ``regression.md`` (no band)."""

    def read() -> list[dict]:
        data = ctx.store.json(run["run_id"], "regression.json")
        if isinstance(data, list):
            return data
        text = ctx.store.text(run["run_id"], "regression.md") or ""
        out = []
        for line in text.splitlines()[2:]:
            m = _MD_ROW.match(line.strip())
            if m:
                out.append(
                    {
                        "metric": m["metric"],
                        "baseline": _num(m["base"]),
                        "now": _num(m["now"]),
                        "tolerance": m["tol"],
                        "allowed": None,
                        "verdict": m["verdict"],
                    }
                )
        return out

    return ctx.cache.get(("checks", run["run_id"]), run["end_time"], read) if run["end_time"] else read()


def code_digest(ctx: Context, run: dict) -> str:
    """12 hex of the stages' code digests the regression ran (its ``provenance.json``), empty without one."""

    def read() -> str:
        data = ctx.store.json(run["run_id"], "provenance.json")
        if not isinstance(data, dict) or not data:
            return ""
        text = json.dumps({s: (d or {}).get("code", "") for s, d in sorted(data.items())}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]

    return ctx.cache.get(("digest", run["run_id"]), run["end_time"], read) if run["end_time"] else read()


FAILING = ("REGRESSION", "missing", "no spread", "untestable")


def regressions(ctx: Context, benchmark: str | None = None) -> dict[str, list[dict]]:
    """Benchmark -> its regression runs, oldest first, each with date, commit, code digest, verdict, checks."""
    found = ctx.store.search("tags.`gdwm.kind` = 'regression'", 2000, ["attributes.start_time ASC"])
    out: dict[str, list[dict]] = {}
    for r in found:
        name = r["tags"].get("gdwm.benchmark", "")
        if benchmark and name != benchmark:
            continue
        st, stale = state_of(r)
        out.setdefault(name, []).append(
            {
                "run": r,
                "date": when(r["start_time"]),
                "commit": r["tags"].get("gdwm.commit", "")[:10],
                "digest": code_digest(ctx, r) if r["status"] == "FINISHED" else "",
                "verdict": r["tags"].get("gdwm.verdict", st),
                "baseline": r["tags"].get("gdwm.baseline") == "true",
                "checks": checks_of(ctx, r) if r["status"] == "FINISHED" else [],
                "state": st,
                "stale": stale,
            }
        )
    return out


# ---- zoo -------------------------------------------------------------------------------------------------------
def zoo(ctx: Context) -> list[dict]:
    """Every registered version with its sweep row, key metric value, aliases and lineage tags."""
    versions = ctx.store.model_versions()
    sweeps = {r["tags"].get("gdwm.sweep"): r for r in ctx.store.search("tags.`gdwm.kind` = 'sweep'", 1000)}
    out = []
    for v in versions:
        tags = v["tags"]
        metrics = {k.removeprefix("gdwm.metric."): x for k, x in tags.items() if k.startswith("gdwm.metric.")}
        sweep = sweeps.get(tags.get("gdwm.sweep", ""))
        key = sweep["tags"].get("gdwm.key_metric") if sweep else None
        entry = ctx.tables.get(sweep["run_id"]) if sweep is not None and ctx.tables is not None else None
        if key is None and entry is not None and entry.table:
            key = entry.table.get("key_metric")
        if key not in metrics:
            key = next((k for k in sorted(metrics) if "avg" in k), next(iter(sorted(metrics)), None))
        row = tags.get("gdwm.row", "")
        out.append(
            {
                **v,
                "created_str": when(v["created"]),
                "experiment_id": ctx.store.experiment_id,
                "variant": tags.get("gdwm.variant", ""),
                "stage": tags.get("gdwm.stage", ""),
                "cache_key": tags.get("gdwm.cache_key", ""),
                "row": f"{tags['gdwm.sweep']}/{row}" if row and "gdwm.sweep" in tags else row,
                "sweep_id": sweep["run_id"] if sweep else None,
                "key": f"{key} = {float(metrics[key]):.4g}" if key else "",
                "lineage": {
                    k.removeprefix("gdwm.upstream."): x for k, x in tags.items() if k.startswith("gdwm.upstream.")
                },
            }
        )
    return out
