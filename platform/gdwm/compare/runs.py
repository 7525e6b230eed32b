"""Rows of a comparison, read from MLflow.

Tag conventions (set by ``gdwm run`` and the sweep):

- a comparable row is a run tagged ``gdwm.kind`` = ``trial`` or ``run``; its metrics are its evaluation metrics;
- its label is the tag ``gdwm.row`` (else the run name); its factors are the tags ``gdwm.factor.<Name>``;
- a sweep is a run tagged ``gdwm.kind=sweep``, ``gdwm.sweep=<name>``; its trials are its child runs
  (``mlflow.parentRunId``), ordered by the tag ``gdwm.trial_index`` when set, else by start time;
- a failed trial ends FAILED with tags ``gdwm.failed_stage`` and ``gdwm.error``;
- the stage runs a row used (for training curves) are runs tagged ``gdwm.stage`` that are its children, carry
  ``gdwm.trial=<row run id>``, or that the row links with a tag ``gdwm.stage_run.<stage>=<run id>``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mlflow.exceptions import MlflowException
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID

from gdwm.tracking import STAGE_TAG, TrackingBackend
from gdwm.tracking.backend import _run_dict

ROW_KINDS = ("trial", "run")
FACTOR_PREFIX = "gdwm.factor."
STAGE_LINK_PREFIX = "gdwm.stage_run."


class SelectionError(Exception):
    """A selector that matches nothing or names an unknown run; the message names the selector."""


@dataclass
class Row:
    run_id: str
    label: str
    status: str
    experiment_id: str
    metrics: dict[str, float]
    factors: dict[str, str] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)

    @property
    def failed(self) -> bool:
        return self.status == "FAILED" or "gdwm.failed_stage" in self.tags

    @property
    def note(self) -> str:
        """``failed at <stage>: <error>`` for a failed row, else empty."""
        if not self.failed:
            return ""
        stage = self.tags.get("gdwm.failed_stage")
        error = self.tags.get("gdwm.error", "").strip().splitlines()
        return f"failed{f' at {stage}' if stage else ''}{f': {error[0]}' if error else ''}"


@dataclass
class Selection:
    name: str
    """Report name: the sweep's name, ``runs``, ``filter`` or ``all``."""
    selector: str
    """What selected the rows, as the user wrote it (for messages)."""
    rows: list[Row]
    sweep_run_id: str | None = None


def _row(r: dict, experiment_id: str, factor_params: list[str]) -> Row:
    tags = r["tags"]
    factors = {k[len(FACTOR_PREFIX) :]: v for k, v in tags.items() if k.startswith(FACTOR_PREFIX)}
    factors |= {k: r["params"][k] for k in factor_params if k in r["params"] and k not in factors}
    label = tags.get("gdwm.row") or r["name"] or r["run_id"][:8]
    return Row(r["run_id"], label, r["status"], experiment_id, dict(r["metrics"]), factors, dict(tags))


def _order(runs: list[dict]) -> list[dict]:
    def key(r: dict) -> tuple:
        idx = r["tags"].get("gdwm.trial_index", "")
        return (0, int(idx)) if idx.lstrip("-").isdigit() else (1, r["start_time"] or 0)

    return sorted(runs, key=key)


def _search(backend: TrackingBackend, filter_string: str, selector: str, **kw) -> list[dict]:
    try:
        return backend.search_runs(filter_string, **kw)
    except MlflowException as e:
        raise SelectionError(f"{selector}: {e.message}") from e


def select(
    backend: TrackingBackend,
    sweep: str | None = None,
    runs: list[str] | None = None,
    filter_string: str | None = None,
    factor_params: list[str] | None = None,
) -> Selection:
    """The rows picked by exactly one of ``sweep``, ``runs``, ``filter_string`` (none: every comparable run)."""
    given = [k for k, v in (("args.sweep", sweep), ("args.runs", runs), ("args.filter", filter_string)) if v]
    if len(given) > 1:
        raise SelectionError(f"give one selector, not {' and '.join(given)}")
    factor_params = list(factor_params or [])
    sweep_run_id = None
    if sweep:
        selector = f"args.sweep={sweep}"
        parents = _search(
            backend,
            f"tags.`gdwm.kind` = 'sweep' and tags.`gdwm.sweep` = '{sweep}'",
            selector,
            order_by=["attributes.start_time DESC"],
        )
        if not parents:
            raise SelectionError(f"{selector}: no sweep named '{sweep}' in experiment '{backend.experiment}'")
        sweep_run_id = parents[0]["run_id"]
        found = _search(backend, f"tags.`{MLFLOW_PARENT_RUN_ID}` = '{sweep_run_id}'", selector)
        found = _order([r for r in found if r["tags"].get("gdwm.kind") == "trial"])
        name = sweep
    elif runs:
        selector = f"args.runs={list(runs)}"
        found = []
        for run_id in runs:
            try:
                found.append(_run_dict(backend.client.get_run(run_id)))
            except MlflowException as e:
                raise SelectionError(f"{selector}: no run '{run_id}' ({e.message})") from e
        name = "runs"
    else:
        selector = f"args.filter={filter_string!r}" if filter_string else "all runs"
        found = _search(backend, filter_string or "", selector, order_by=["attributes.start_time ASC"])
        found = [r for r in found if r["tags"].get("gdwm.kind") in ROW_KINDS]
        name = "filter" if filter_string else "all"
    if not found:
        raise SelectionError(
            f"{selector}: no runs tagged gdwm.kind in {list(ROW_KINDS)} in experiment '{backend.experiment}' "
            f"of {backend.uri}"
        )
    rows = [_row(r, backend.experiment_id, factor_params) for r in found]
    return Selection(name, selector, rows, sweep_run_id)


def stage_runs(backend: TrackingBackend, row: Row) -> list[dict]:
    """The stage runs ``row`` used: its children, runs tagged ``gdwm.trial=<row>``, and runs it links by tag."""
    found: dict[str, dict] = {}
    for f in (f"tags.`{MLFLOW_PARENT_RUN_ID}` = '{row.run_id}'", f"tags.`gdwm.trial` = '{row.run_id}'"):
        found |= {r["run_id"]: r for r in backend.search_runs(f)}
    for key, run_id in row.tags.items():
        if key.startswith(STAGE_LINK_PREFIX) and run_id not in found:
            try:
                found[run_id] = _run_dict(backend.client.get_run(run_id))
            except MlflowException:
                continue  # a deleted stage run: its curves are simply absent
    return [r for r in found.values() if STAGE_TAG in r["tags"]]


def training_curves(backend: TrackingBackend, row: Row) -> dict[str, list[tuple[int, float]]]:
    """``<stage>/<metric>`` -> (step, value) of every metric a stage run logged at more than one step."""
    curves = {}
    for r in stage_runs(backend, row):
        for key in sorted(r["metrics"]):
            if key.startswith("system/"):
                continue
            history = backend.metric_history(r["run_id"], key)
            if len({step for step, _ in history}) > 1:
                curves[f"{r['tags'][STAGE_TAG]}/{key}"] = history
    return curves
