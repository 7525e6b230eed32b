"""Rows of a comparison and their trials (one per seed), read from MLflow.

Tag conventions (set by ``gdwm run`` and the sweep):

- a sweep is a run tagged ``gdwm.kind=sweep``, ``gdwm.sweep=<name>``; its rows are its child runs
  (``mlflow.parentRunId``) tagged ``gdwm.kind=row``, ordered by the tag ``gdwm.trial_index`` (else start time);
- a row's trials are its child runs tagged ``gdwm.kind=trial``, one per seed (``gdwm.seed``); its planned seeds are
  the tag ``gdwm.seeds`` (``0,1,2``); the trials' metrics are the source of truth (the row's own are aggregates);
- a plain ``gdwm run`` (``gdwm.kind=run``) is a row: with several seeds its children are its trials, with one it is
  its own trial; a trial selected by id, or one directly under a sweep (stores from before seeds), is a row alone;
- a row's label is the tag ``gdwm.row`` (else the run name); its factors are the tags ``gdwm.factor.<Name>``;
- a failed trial ends FAILED with tags ``gdwm.failed_stage`` and ``gdwm.error``; a row fails when all its trials do;
- the stage runs a trial used (for training curves) are runs tagged ``gdwm.stage`` that are its children, carry
  ``gdwm.trial=<run id>``, or that it links with a tag ``gdwm.stage_run.<stage>=<run id>``;
- an evaluation stage run a trial links may label its metrics with params ``protocol/<metric>`` (``official`` or
  ``approximate``) and ``proxy/<metric>`` (what stands in for the benchmark's data): the table's notes print them;
- the trial's (and row's) params are its resolved config, flattened: the table's notes print the encoders from them;
- a reported row (numbers copied from a paper, ``gdwm compare args.log_references=true`` logs a references file's
  rows so) is a run tagged ``gdwm.kind=reference``, ``gdwm.row``, ``gdwm.source.paper``, ``gdwm.source.table``,
  ``gdwm.source.year``, whose metrics are the published values; under a sweep run it is one of the sweep's rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mlflow.exceptions import MlflowException
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID

from gdwm.compare.stats import SampleSet
from gdwm.tracking import STAGE_TAG, TrackingBackend
from gdwm.tracking.backend import run_dict
from gdwm.tracking.params import PARAMS_BASE_TAG, full_params, inherited_params

REFERENCE_KIND = "reference"
ROW_KINDS = ("row", "run", REFERENCE_KIND)
TRIAL_KIND = "trial"
SOURCE_PREFIX = "gdwm.source."
FACTOR_PREFIX = "gdwm.factor."
STAGE_LINK_PREFIX = "gdwm.stage_run."
PROTOCOL_PARAM = "protocol/"
PROXY_PARAM = "proxy/"


_ALL = 1_000_000
"""``max_results`` of a search that must return every match (a sweep's rows and trials; the default stops at 1000)."""


class SelectionError(Exception):
    """A selector that matches nothing or names an unknown run; the message names the selector."""


def _failed(status: str, tags: dict[str, str]) -> bool:
    return status == "FAILED" or "gdwm.failed_stage" in tags


def _note(tags: dict[str, str]) -> str:
    stage = tags.get("gdwm.failed_stage")
    error = tags.get("gdwm.error", "").strip().splitlines()
    return f"failed{f' at {stage}' if stage else ''}{f': {error[0]}' if error else ''}"


@dataclass(frozen=True)
class Source:
    """Where a reported row's numbers were published."""

    paper: str
    """The paper (a citation key or title)."""
    table: str = ""
    """The table in it (e.g. ``Tab. 3``)."""
    year: str = ""

    def __str__(self) -> str:
        """``DriveMonkey (2025)``: what the table's source column shows (the notes name the tables)."""
        return f"{self.paper} ({self.year})" if self.year else self.paper

    def tags(self) -> dict[str, str]:
        fields = {"paper": self.paper, "table": self.table, "year": self.year}
        return {f"{SOURCE_PREFIX}{k}": v for k, v in fields.items()}


@dataclass
class Trial:
    """One seed of a row: a ``gdwm.kind=trial`` run, or a single-seed run that is its own trial."""

    run_id: str
    seed: int | None
    status: str
    metrics: dict[str, float]
    tags: dict[str, str] = field(default_factory=dict)
    samples: dict[str, SampleSet] = field(default_factory=dict)
    """Evaluation stage -> its per-sample predictions (``samples.load_samples`` fills it)."""
    params: dict[str, str] = field(default_factory=dict)
    """The trial run's params (its resolved config, flattened)."""
    labels: dict[str, str] = field(default_factory=dict)
    """Metric -> ``official`` | ``approximate``, as its evaluation stage run labelled it (``read_labels``)."""
    proxy: dict[str, str] = field(default_factory=dict)
    """Metric -> what stood in for the benchmark's data, where its evaluation said it was a proxy."""

    @property
    def failed(self) -> bool:
        return _failed(self.status, self.tags)


@dataclass
class Row:
    run_id: str
    label: str
    status: str
    experiment_id: str
    metrics: dict[str, float]
    """The row run's own metrics (aggregates for a row run); the table recomputes from ``trials``."""
    factors: dict[str, str] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)
    trials: list[Trial] = field(default_factory=list)
    """One per seed, in seed order."""
    planned: int = 1
    """Seeds the row was meant to have (``gdwm.seeds``)."""
    params: dict[str, str] = field(default_factory=dict)
    """The row run's params (a row run logs its first trial's config)."""
    source: Source | None = None
    """Where a reported row's values were published; None for the rows of runs (the table's own)."""

    @property
    def reported(self) -> bool:
        """Values copied from a paper: one number per cell, no seeds, no samples; marked by value only."""
        return self.source is not None

    def param(self, key: str) -> str | None:
        """``key`` from the row's params, else from its first counted trial that has it."""
        if key in self.params:
            return self.params[key]
        return next((t.params[key] for t in self.counted if key in t.params), None)

    @property
    def failed(self) -> bool:
        """Every trial failed (a multi-seed ``gdwm run`` may end FAILED with seeds that finished); a row that is its
        own trial, by its own status."""
        children = [t for t in self.trials if t.run_id != self.run_id]
        return all(t.failed for t in children) if children else _failed(self.status, self.tags)

    @property
    def counted(self) -> list[Trial]:
        """The trials the cells come from: the finished ones; all of them when the row failed (shown, dimmed)."""
        return self.trials if self.failed else [t for t in self.trials if not t.failed]

    @property
    def note(self) -> str:
        """``failed at <stage>: <error>`` for a failed row (from its own tags, else its first trial's), else empty."""
        if not self.failed:
            return ""
        if "gdwm.failed_stage" in self.tags:
            return _note(self.tags)
        return _note(next((t.tags for t in self.trials if "gdwm.failed_stage" in t.tags), self.tags))


@dataclass
class Selection:
    name: str
    """Report name: the sweep's name, ``runs``, ``filter`` or ``all``."""
    selector: str
    """What selected the rows, as the user wrote it (for messages)."""
    rows: list[Row]
    sweep_run_id: str | None = None
    linked: dict[str, dict] | None = None
    """:func:`linked_runs` of ``rows``, read once by :func:`select` (None: not read)."""


def _trial(r: dict) -> Trial:
    seed = r["tags"].get("gdwm.seed", "")
    number = int(seed) if seed.lstrip("-").isdigit() else None
    return Trial(r["run_id"], number, r["status"], dict(r["metrics"]), dict(r["tags"]), params=dict(r["params"]))


def _row(
    backend: TrackingBackend, r: dict, factor_params: list[str], selector: str, known: list[dict] | None = None
) -> Row:
    """The row of run ``r`` with its trials: ``known`` (found by one search for a whole sweep), else its children."""
    tags = r["tags"]
    factors = {k[len(FACTOR_PREFIX) :]: v for k, v in tags.items() if k.startswith(FACTOR_PREFIX)}
    factors |= {k: r["params"][k] for k in factor_params if k in r["params"] and k not in factors}
    label = tags.get("gdwm.row") or r["name"] or r["run_id"][:8]
    children = []
    if known:
        children = known
    elif tags.get("gdwm.kind") in ROW_KINDS:
        children = _search(backend, f"tags.`{MLFLOW_PARENT_RUN_ID}` = '{r['run_id']}'", selector, max_results=_ALL)
        children = [c for c in children if c["tags"].get("gdwm.kind") == TRIAL_KIND]
    trials = sorted(map(_trial, children), key=lambda t: (t.seed is None, t.seed or 0)) or [_trial(r)]
    seeds = [s for s in tags.get("gdwm.seeds", "").split(",") if s.strip()] if children else []
    row = Row(r["run_id"], label, r["status"], backend.experiment_id, dict(r["metrics"]), factors, dict(tags), trials)
    row.planned = max(len(seeds), len(trials))
    row.params = dict(r["params"])
    if tags.get("gdwm.kind") == REFERENCE_KIND:
        row.source = Source(*(tags.get(f"{SOURCE_PREFIX}{k}", "") for k in ("paper", "table", "year")))
    return row


def _order(runs: list[dict]) -> list[dict]:
    def key(r: dict) -> tuple:
        idx = r["tags"].get("gdwm.trial_index", "")
        return (0, int(idx)) if idx.lstrip("-").isdigit() else (1, r["start_time"] or 0)

    return sorted(runs, key=key)


def _inherit_params(backend: TrackingBackend, rows: list[Row], selector: str, known: dict[str, dict]) -> None:
    """Rows that record what differs from their sweep's run (``PARAMS_BASE_TAG``) get its params under their own
    (``gdwm.tracking.full_params``); ``known``: runs already read, the rest in one search."""
    bases = {r.tags[PARAMS_BASE_TAG] for r in rows if PARAMS_BASE_TAG in r.tags}
    if missing := sorted(bases - known.keys()):
        ids = ", ".join(f"'{x}'" for x in missing)
        known = known | {r["run_id"]: r for r in _search(backend, f"attributes.run_id IN ({ids})", selector)}
    for r in rows:
        r.params = full_params(r.params, inherited_params(r.tags, known))


def newest_per_row(runs: list[dict]) -> list[dict]:
    """The newest run of each row label (``gdwm.row``), in ``runs``' order: a sweep launched again after a row's
    config or code changed holds that row twice under its parent, and the table reports what the row is now."""
    newest: dict[tuple, dict] = {}
    for r in runs:
        label = (r["tags"].get("gdwm.kind"), r["tags"].get("gdwm.row") or r["run_id"])
        if label not in newest or (r["start_time"] or 0) > (newest[label]["start_time"] or 0):
            newest[label] = r
    keep = {r["run_id"] for r in newest.values()}
    return [r for r in runs if r["run_id"] in keep]


def _search(backend: TrackingBackend, filter_string: str, selector: str, **kw) -> list[dict]:
    try:
        return backend.search_runs(filter_string, **kw)
    except MlflowException as e:
        raise SelectionError(f"{selector}: {e.message}") from e


def _sweep_ids(backend: TrackingBackend, selector: str) -> set[str]:
    return {r["run_id"] for r in _search(backend, "tags.`gdwm.kind` = 'sweep'", selector)}


def select(
    backend: TrackingBackend,
    sweep: str | None = None,
    runs: list[str] | None = None,
    filter_string: str | None = None,
    factor_params: list[str] | None = None,
) -> Selection:
    """The rows picked by exactly one of ``sweep``, ``runs``, ``filter_string`` (none: every row and plain run),
    each with its trials."""
    given = [k for k, v in (("args.sweep", sweep), ("args.runs", runs), ("args.filter", filter_string)) if v]
    if len(given) > 1:
        raise SelectionError(f"give one selector, not {' and '.join(given)}")
    factor_params = list(factor_params or [])
    sweep_run_id = None
    known: dict[str, list[dict]] = {}
    parents: list[dict] = []
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
        found = _search(backend, f"tags.`{MLFLOW_PARENT_RUN_ID}` = '{sweep_run_id}'", selector, max_results=_ALL)
        kinds = ("row", TRIAL_KIND, REFERENCE_KIND)
        found = _order(newest_per_row([r for r in found if r["tags"].get("gdwm.kind") in kinds]))
        # every row's trials in one search (MLflow filters tags by =, not IN): the trials of this sweep's name, by
        # parent; a row none of them names (a trial without the tag) searches its own children
        trials = _search(backend, f"tags.`gdwm.kind` = '{TRIAL_KIND}' and tags.`gdwm.sweep` = '{sweep}'", selector,
                         max_results=_ALL)  # fmt: skip
        for t in trials:
            known.setdefault(t["tags"].get(MLFLOW_PARENT_RUN_ID, ""), []).append(t)
        name = sweep
    elif runs:
        selector = f"args.runs={list(runs)}"
        found = []
        for run_id in runs:
            try:
                found.append(run_dict(backend.client.get_run(run_id)))
            except MlflowException as e:
                raise SelectionError(f"{selector}: no run '{run_id}' ({e.message})") from e
        name = "runs"
    else:
        selector = f"args.filter={filter_string!r}" if filter_string else "all runs"
        found = _search(backend, filter_string or "", selector, order_by=["attributes.start_time ASC"])
        if any(r["tags"].get("gdwm.kind") == TRIAL_KIND for r in found):
            sweeps = _sweep_ids(backend, selector)  # a trial right under a sweep is an old store's row
        else:
            sweeps = set()
        found = [
            r
            for r in found
            if r["tags"].get("gdwm.kind") in ROW_KINDS
            or (r["tags"].get("gdwm.kind") == TRIAL_KIND and r["tags"].get(MLFLOW_PARENT_RUN_ID) in sweeps)
        ]
        name = "filter" if filter_string else "all"
    if not found:
        raise SelectionError(
            f"{selector}: no runs tagged gdwm.kind in {list(ROW_KINDS)} in experiment '{backend.experiment}' "
            f"of {backend.uri}"
        )
    rows = [_row(backend, r, factor_params, selector, known.get(r["run_id"])) for r in found]
    _inherit_params(backend, rows, selector, {p["run_id"]: p for p in parents})
    linked = read_labels(backend, rows, selector)
    return Selection(name, selector, rows, sweep_run_id, linked)


def linked_runs(backend: TrackingBackend, rows: list[Row], selector: str, chunk: int = 100) -> dict[str, dict]:
    """run id -> run of every stage run the rows' trials link (``gdwm.stage_run.<stage>``): one search per
    ``chunk`` of them, not a request each."""
    tags = [t.tags for r in rows for t in r.trials] + [r.tags for r in rows]
    links = sorted({v for ts in tags for k, v in ts.items() if k.startswith(STAGE_LINK_PREFIX)})
    found: dict[str, dict] = {}
    for i in range(0, len(links), chunk):
        ids = ", ".join(f"'{x}'" for x in links[i : i + chunk])
        found |= {r["run_id"]: r for r in _search(backend, f"attributes.run_id IN ({ids})", selector)}
    return found


def read_labels(backend: TrackingBackend, rows: list[Row], selector: str) -> dict[str, dict]:
    """Fill ``labels`` and ``proxy`` of every trial from the ``protocol/`` and ``proxy/`` params of the stage runs
    it links; returns those runs (:func:`linked_runs`)."""
    trials = [t for r in rows for t in r.trials]
    linked = linked_runs(backend, rows, selector)
    params = {run_id: r["params"] for run_id, r in linked.items()}
    for t in trials:
        for key, run_id in t.tags.items():
            if key.startswith(STAGE_LINK_PREFIX):
                for name, value in params.get(run_id, {}).items():
                    if name.startswith(PROTOCOL_PARAM):
                        t.labels[name[len(PROTOCOL_PARAM) :]] = value
                    elif name.startswith(PROXY_PARAM):
                        t.proxy[name[len(PROXY_PARAM) :]] = value
    return linked


def stage_runs(
    backend: TrackingBackend, run_id: str, tags: dict[str, str], linked: dict[str, dict] | None = None
) -> list[dict]:
    """The stage runs a row or trial used: its children, runs tagged ``gdwm.trial=<it>``, and runs it links.

    With ``linked`` (:func:`linked_runs` of its rows), a run that links its stages (every finished trial links all
    of them, executed or cached) takes them from there, and a sweep's row run (its stage runs are its trials') has
    none: no request at all."""
    links = [v for k, v in tags.items() if k.startswith(STAGE_LINK_PREFIX)]
    if linked is not None and (links or tags.get("gdwm.kind") == "row"):
        return [linked[x] for x in dict.fromkeys(links) if x in linked and STAGE_TAG in linked[x]["tags"]]
    found: dict[str, dict] = {}
    for f in (f"tags.`{MLFLOW_PARENT_RUN_ID}` = '{run_id}'", f"tags.`gdwm.trial` = '{run_id}'"):
        found |= {r["run_id"]: r for r in backend.search_runs(f)}
    for key, linked in tags.items():
        if key.startswith(STAGE_LINK_PREFIX) and linked not in found:
            try:
                found[linked] = run_dict(backend.client.get_run(linked))
            except MlflowException:
                continue  # a deleted stage run: its curves are simply absent
    return [r for r in found.values() if STAGE_TAG in r["tags"]]


def training_curves(
    backend: TrackingBackend, row: Row, linked: dict[str, dict] | None = None
) -> dict[str, list[tuple[int, float]]]:
    """``<stage>/<metric>`` -> (step, value) of every metric a stage run logged at more than one step: those of the
    row run's stage runs, else of its first trial (lowest seed) that has any, as a row has one line per plot.
    ``linked``: :func:`linked_runs` of the rows (see :func:`stage_runs`)."""
    owners = [(row.run_id, row.tags)] + [(t.run_id, t.tags) for t in row.trials if t.run_id != row.run_id]
    for run_id, tags in owners:
        curves = {}
        for r in stage_runs(backend, run_id, tags, linked):
            for key in sorted(r["metrics"]):
                if key.startswith("system/"):
                    continue
                history = backend.metric_history(r["run_id"], key)
                if len({step for step, _ in history}) > 1:
                    curves[f"{r['tags'][STAGE_TAG]}/{key}"] = history
        if curves:
            return curves
    return {}
