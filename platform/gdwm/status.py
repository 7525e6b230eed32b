"""``gdwm status``: what the store holds, launches first -- sweeps (trials done / total, state, duration, best row on
the table's key metric, the last regression verdict), then ``gdwm run`` launches and regression runs.

``args.sweep=NAME`` shows one sweep with its rows, ``args.state=running|done|failed|killed`` keeps launches in that
state, ``args.limit=N`` caps each list (newest first). Progress of a running launch comes from the snapshot its
driver keeps on its run (``gdwm.events``); a run whose driver died shows ``killed`` once reconciled.
"""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from rich.table import Table

from gdwm.config import StatusArgs, sqlite_path
from gdwm.errors import CommandError
from gdwm.progress import duration
from gdwm.redact import redact
from gdwm.term import console

STATES = ("running", "done", "failed", "killed")
_STATE = {"RUNNING": "running", "FINISHED": "done", "FAILED": "failed", "KILLED": "killed"}


def _when(ms: int | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(ms / 1000)) if ms else ""


def _took(r: dict) -> str:
    if not r["start_time"]:
        return ""
    end = r["end_time"] or time.time() * 1000
    return duration((end - r["start_time"]) / 1000)


def state_of(r: dict) -> str:
    """A launch's state: its snapshot's while it runs, else its MLflow status."""
    if r["status"] == "RUNNING":
        return r["tags"].get("gdwm.state", "running")
    return _STATE.get(r["status"], r["status"].lower())


def _trials(r: dict, rows: list[dict]) -> str:
    tags = r["tags"]
    if "gdwm.trials_total" in tags:
        failed = int(tags.get("gdwm.trials_failed", "0"))
        return f"{tags.get('gdwm.trials_done', '0')}/{tags['gdwm.trials_total']}" + (f" ({failed} failed)" if failed
                                                                                    else "")  # fmt: skip
    mine = [x for x in rows if x["tags"].get("mlflow.parentRunId") == r["run_id"]]
    done = sum(x["status"] == "FINISHED" for x in mine)
    return f"{done}/{len(mine)}" if mine else ""


def _best(r: dict) -> str:
    tags = r["tags"]
    if "gdwm.best_row" not in tags:
        return ""
    value = float(tags.get("gdwm.best_value", "nan"))
    return f"{tags['gdwm.best_row']} ({tags.get('gdwm.key_metric', '')} {value:.2f})"


def status(cfg: DictConfig) -> int:
    from gdwm.tracking import TrackingBackend

    args: StatusArgs = OmegaConf.to_object(cfg.args)
    if args.state is not None and args.state not in STATES:
        raise CommandError(f"args.state={args.state}: one of {', '.join(STATES)}")
    uri = cfg.tracking.uri
    if (db := sqlite_path(uri)) is not None and not Path(db).is_file():
        # reading must not create a workdir and an empty store where nothing has run
        raise CommandError(f"no MLflow store at {db}: nothing has run in workdir {cfg.workdir} (or tracking.uri points "
                           "elsewhere)")  # fmt: skip
    backend = TrackingBackend(uri, cfg.tracking.experiment, cfg.tracking.artifact_location,
                              lock_timeout_s=cfg.tracking.lock_timeout_s)  # fmt: skip
    newest = ["attributes.start_time DESC"]

    def launches(kind: str, extra: str = "") -> list[dict]:
        found = backend.search_runs(f"tags.`gdwm.kind` = '{kind}'{extra}", 1000, newest)
        return [r for r in found if args.state is None or state_of(r) == args.state][: args.limit]

    where = f" and tags.`gdwm.sweep` = '{args.sweep}'" if args.sweep else ""
    sweeps = launches("sweep", where)
    if args.sweep and not sweeps:
        raise CommandError(f"args.sweep={args.sweep}: no sweep of that name in {redact(uri)}")
    rows = backend.search_runs("tags.`gdwm.kind` = 'row'", 5000) if sweeps else []
    regressions = launches("regression")
    verdicts = {}
    for r in regressions:
        verdicts.setdefault(r["tags"].get("gdwm.benchmark", ""), r)

    t = Table(title=f"sweeps in {redact(uri)}", header_style="bold")
    for col in ("sweep", "state", "trials", "started", "duration", "best row (key metric)", "run id"):
        t.add_column(col)
    for r in sweeps:
        t.add_row(r["tags"].get("gdwm.sweep", r["name"]), state_of(r), _trials(r, rows), _when(r["start_time"]),
                  _took(r), _best(r), r["run_id"])  # fmt: skip
    console.print(t if sweeps else f"no sweeps in {redact(uri)}" + (f" in state {args.state}" if args.state else ""))
    if args.sweep and sweeps:
        _sweep_rows(sweeps[0], rows)
        return 0
    runs = launches("run")
    if runs:
        t = Table(title="gdwm run launches", header_style="bold")
        for col in ("run", "state", "seeds", "stages run", "started", "duration", "run id"):
            t.add_column(col)
        for r in runs:
            tags = r["tags"]
            t.add_row(r["name"] or "", state_of(r), tags.get("gdwm.seeds", ""), tags.get("gdwm.stages_run", ""),
                      _when(r["start_time"]), _took(r), r["run_id"])  # fmt: skip
        console.print(t)
    if regressions:
        t = Table(title="regressions (the last verdict per benchmark first)", header_style="bold")
        for col in ("benchmark", "verdict", "baseline", "started", "duration", "run id"):
            t.add_column(col)
        for r in regressions:
            tags = r["tags"]
            t.add_row(tags.get("gdwm.benchmark", ""), tags.get("gdwm.verdict", state_of(r)),
                      "yes" if tags.get("gdwm.baseline") == "true" else tags.get("gdwm.baseline_run", "")[:12],
                      _when(r["start_time"]), _took(r), r["run_id"])  # fmt: skip
        console.print(t)
    return 0


def _sweep_rows(sweep: dict, rows: list[dict]) -> None:
    key = sweep["tags"].get("gdwm.key_metric")
    mine = [r for r in rows if r["tags"].get("mlflow.parentRunId") == sweep["run_id"]]
    t = Table(title=f"rows of sweep {sweep['tags'].get('gdwm.sweep', '')}", header_style="bold")
    for col in ("row", "state", "seeds", key or "key metric", "run id"):
        t.add_column(col)
    for r in sorted(mine, key=lambda r: int(r["tags"].get("gdwm.trial_index", "0"))):
        value = r["metrics"].get(key) if key else None
        t.add_row(r["tags"].get("gdwm.row", r["name"] or ""), state_of(r), r["tags"].get("gdwm.seeds", ""),
                  "" if value is None else f"{value:.2f}", r["run_id"])  # fmt: skip
    console.print(t)
