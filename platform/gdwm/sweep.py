"""``gdwm sweep sweep=NAME``: an ablation table as trials over one union DAG (DESIGN §4, §6).

A sweep (``conf/sweep/NAME.yaml``) lists ``rows`` (label, the factor values the table shows, the overrides they
mean) and a ``grid`` (override key -> values, crossed with every row). Every trial's config is composed and its
stage keys planned on the driver before anything runs, so a bad row is rejected before launch and a stage whose
key several trials share is submitted once — its Ray ObjectRef feeds every trial that needs it. Independent
trials run concurrently within the cluster's resources.

MLflow: one parent run per sweep name (re-running continues it), a child run per trial (found again by its
trial key, so a resumed or extended sweep never duplicates one) holding the evaluation metrics, factor tags and
links to the stage runs it used; stage runs nest under the sweep. The comparison report closes the sweep.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import statistics
from dataclasses import dataclass, field
from typing import Any

import ray
from omegaconf import DictConfig, OmegaConf
from rich.table import Table

from gdwm.config import ConfigError, SweepConfig, SweepRow, load_config
from gdwm.dag import DagError, Pipeline, load_pipeline
from gdwm.executor import RunEnv, StageFailed, StageResult, run_scene_stage, run_stage, task_options
from gdwm.runner import (
    _TERMINATED,
    PlanRow,
    _root_cause,
    driver_session,
    ensure_data,
    env_settings,
    plan_keys,
    report_evaluation,
    subset,
)
from gdwm.term import console
from gdwm.tracking import RunGuard, call
from gdwm.zoo.refs import ZooError
from gdwm.zoo.registry import metric_tags, pin_references

TRIAL_KEY = "gdwm.trial_key"


class SweepError(Exception):
    """A sweep that cannot launch (exit 2): the message names the sweep, the row and the key."""


@dataclass
class Trial:
    index: int
    label: str
    factors: dict[str, str]
    overrides: list[str]
    cfg: DictConfig | None = None
    pipe: Pipeline | None = None
    order: list[str] = field(default_factory=list)
    keys: dict[str, str] = field(default_factory=dict)
    """Stage -> cache key (per-scene stages: the aggregate key)."""
    rows: list[PlanRow] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    run_id: str | None = None

    @property
    def key(self) -> str:
        """Identity across re-runs: label and overrides, not the config's values (a code change keeps the run)."""
        return hashlib.sha256(json.dumps([self.label, self.overrides]).encode()).hexdigest()[:16]


def expand(sweep: SweepConfig) -> list[Trial]:
    """Rows x grid, in row order then grid order; labels must be unique."""
    rows = sweep.rows or [SweepRow(label=sweep.name, factors={}, overrides=[])]
    keys = list(sweep.grid)
    trials = []
    for row in rows:
        for combo in itertools.product(*(sweep.grid[k] for k in keys)):
            grid = [f"{k}={v}" for k, v in zip(keys, combo, strict=True)]
            label = ", ".join([row.label, *grid]) if grid and sweep.rows else ", ".join(grid) or row.label
            factors = {**row.factors, **{k: str(v) for k, v in zip(keys, combo, strict=True)}}
            trials.append(Trial(len(trials), label, factors, [*row.overrides, *grid]))
    seen: dict[str, int] = {}
    for t in trials:
        if t.label in seen:
            raise SweepError(f"sweep '{sweep.name}': rows {seen[t.label]} and {t.index} share the label '{t.label}'")
        seen[t.label] = t.index
    return trials


def compose(sweep: SweepConfig, trials: list[Trial], user_overrides: list[str]) -> None:
    """Compose, validate and plan every trial; the first bad row stops the sweep before launch."""
    base = ([f"targets=[{','.join(sweep.targets)}]"] if sweep.targets else []) + list(sweep.overrides)
    for t in trials:
        where = f"sweep '{sweep.name}' row '{t.label}'"
        try:
            t.cfg = load_config([*base, *user_overrides, *t.overrides])
            t.pipe = load_pipeline(t.cfg, list(t.cfg.targets) or None)
        except (ConfigError, DagError) as e:
            raise SweepError(f"{where}: {e}") from e
        t.order = t.pipe.ancestors(list(t.cfg.targets)) if t.cfg.targets else list(t.pipe.order)
        try:  # zoo:NAME@ALIAS -> zoo:NAME/VERSION: the trial's keys name exact versions
            t.cfg = pin_references(t.cfg, t.cfg.tracking.uri, [k for n in t.order for k in t.pipe.stages[n].config])
        except ZooError as e:
            raise SweepError(f"{where}: {e}") from e
        t.settings = env_settings(t.cfg, ensure_data(t.cfg))
        t.rows, t.keys = plan_keys(t.pipe, t.order, t.cfg, RunEnv(sink=None, parent_run_id=None, progress=None,
                                                                  **t.settings))  # fmt: skip


def user_overrides(argv: list[str]) -> list[str]:
    """The command line's overrides that apply to every trial (not the sweep choice, not flags)."""
    return [a for a in argv if not a.startswith("--") and a.split("=", 1)[0].lstrip("+~") != "sweep"]


@dataclass
class SweepSummary:
    trials: list[Trial]
    executions: int = 0
    """Stage executions this invocation submitted (distinct keys not cached)."""
    naive: int = 0
    """Stage executions the trials would need as independent runs without a cache."""
    failed: dict[str, str] = field(default_factory=dict)
    """Trial label -> 'stage: error'."""
    parent_run_id: str | None = None


def load_sweep(cfg: DictConfig) -> SweepConfig:
    if cfg.get("sweep") is None:
        from gdwm.config import group_options

        raise SweepError(f"no sweep selected: pass sweep=NAME (one of {', '.join(group_options('sweep'))})")
    return OmegaConf.to_object(cfg.sweep)


def run_sweep(cfg: DictConfig, argv: list[str], dry_run: bool = False) -> SweepSummary:
    sweep = load_sweep(cfg)
    trials = expand(sweep)
    compose(sweep, trials, user_overrides(argv))
    summary = SweepSummary(trials, naive=sum(len(t.order) for t in trials))
    if dry_run:
        print_sweep_plan(sweep, trials, _durations(cfg))
        return summary
    with driver_session(cfg) as sink:
        parent = _parent_run(sink, sweep, cfg)
        summary.parent_run_id = parent
        with RunGuard(sink, parent):
            _execute(sweep, trials, sink, parent, summary)
            call(sink, "log_metrics", parent, {
                "trials": len(trials), "trials_failed": len(summary.failed),
                "stage_executions": summary.executions, "stage_executions_naive": summary.naive,
            })  # fmt: skip
    return summary


def _parent_run(sink, sweep: SweepConfig, cfg: DictConfig) -> str:
    """One parent per sweep name: a re-run, a resume after a crash, an added row all continue it."""
    found = call(sink, "search_runs", f"tags.`gdwm.kind` = 'sweep' and tags.`gdwm.sweep` = '{sweep.name}'")
    if found:
        call(sink, "reopen_run", found[0]["run_id"])
        run_id = found[0]["run_id"]
    else:
        run_id = call(sink, "create_run", f"sweep-{sweep.name}", {"gdwm.kind": "sweep", "gdwm.sweep": sweep.name})
    call(sink, "log_text", run_id, OmegaConf.to_yaml(OmegaConf.structured(sweep)), "sweep.yaml")
    return run_id


def _trial_run(sink, sweep: SweepConfig, parent: str, t: Trial) -> str:
    found = call(sink, "search_runs", f"tags.`{TRIAL_KEY}` = '{t.key}' and tags.`gdwm.sweep` = '{sweep.name}'")
    tags = {
        "gdwm.kind": "trial",
        "gdwm.sweep": sweep.name,
        "gdwm.row": t.label,
        "gdwm.trial_index": str(t.index),
        TRIAL_KEY: t.key,
        "gdwm.overrides": " ".join(t.overrides),
        **{f"gdwm.factor.{k}": v for k, v in t.factors.items()},
    }
    if found:
        run_id = found[0]["run_id"]
        call(sink, "reopen_run", run_id)
        call(sink, "set_tags", run_id, tags)  # an edited row keeps its run; the index may move
        return run_id
    run_id = call(sink, "create_run", f"{sweep.name}/{t.label}", tags, parent)
    call(sink, "log_params", run_id, OmegaConf.to_container(t.cfg, resolve=True))
    return run_id


def _execute(sweep: SweepConfig, trials: list[Trial], sink, parent: str, summary: SweepSummary) -> None:
    submitted: dict[tuple[str, str], ray.ObjectRef] = {}
    for t in trials:
        env = RunEnv(sink=sink, parent_run_id=parent, progress=None, run_tags={"gdwm.sweep": sweep.name},
                     **t.settings)  # fmt: skip
        refs: dict[str, ray.ObjectRef] = {}
        for name in t.order:
            sd = t.pipe.stages[name]
            k = (name, t.keys[name])
            if k not in submitted:
                fn = run_scene_stage if sd.per_scene else run_stage
                ups = [refs[u] for u in sd.upstream]
                submitted[k] = fn.options(**task_options(sd, env)).remote(sd, subset(t.cfg, sd.config), env, *ups)
            refs[name] = submitted[k]
        t.run_id = _trial_run(sink, sweep, parent, t)
    users = {k: [t.label for t in trials if t.keys.get(k[0]) == k[1]] for k in submitted}
    outcome: dict[tuple[str, str], StageResult | str | None] = {}
    pending = {ref: k for k, ref in submitted.items()}
    open_trials = list(trials)
    while pending:
        if _TERMINATED:
            raise SystemExit(128 + _TERMINATED[0])
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
        for ref in ready:
            k = pending.pop(ref)
            outcome[k] = _outcome(ref, k[0])
            _print_stage(k, outcome[k], users[k])
            if isinstance(outcome[k], StageResult) and not outcome[k].cached:
                summary.executions += 1
        for t in [t for t in open_trials if all((n, t.keys[n]) in outcome for n in t.order)]:
            open_trials.remove(t)
            _finish_trial(sink, sweep, t, {n: outcome[(n, t.keys[n])] for n in t.order}, summary)


def _outcome(ref: ray.ObjectRef, stage: str) -> StageResult | str | None:
    """The result, an error message (this stage failed), or None (blocked by a failed upstream)."""
    try:
        return ray.get(ref)
    except Exception as e:  # Ray re-raises a task's error as a subclass of both RayTaskError and it
        root = _root_cause(e)
        if isinstance(root, StageFailed) and root.stage != stage:
            return None
        return StageFailed.__str__(root) if isinstance(root, StageFailed) else f"stage '{stage}' failed: {root!r}"


def _print_stage(k: tuple[str, str], r, users: list[str]) -> None:
    what = "failed" if isinstance(r, str) else "blocked" if r is None else "cached" if r.cached else "done"
    shared = f" (shared by {len(users)} trials)" if len(users) > 1 else ""
    console.print(f"  {k[0]:<14} {k[1][:12]}  {what}{shared}", markup=False)


def _finish_trial(sink, sweep: SweepConfig, t: Trial, results: dict, summary: SweepSummary) -> None:
    failed = next(((n, r) for n, r in results.items() if isinstance(r, str)), None)
    if failed is not None:
        stage, msg = failed
        summary.failed[t.label] = f"{stage}: {msg}"
        call(sink, "set_tags", t.run_id, {"gdwm.failed_stage": stage, "gdwm.error": msg})
        call(sink, "log_text", t.run_id, msg, "error.txt")
        call(sink, "end_run", t.run_id, "FAILED")
        console.print(f"[red]trial '{t.label}' failed at {stage}[/red]")
        return
    ok = {n: r for n, r in results.items() if isinstance(r, StageResult)}
    call(sink, "set_tags", t.run_id, {f"gdwm.stage_run.{n}": r.run_id for n, r in ok.items() if r.run_id})
    call(sink, "set_tags", t.run_id, {f"gdwm.stage_key.{n}": r.key for n, r in ok.items()})
    metrics = report_evaluation(sink, t.run_id, t.pipe, ok)
    # the zoo versions this trial's stages registered carry its sweep, trial and key metrics
    lineage = {"gdwm.sweep": sweep.name, "gdwm.trial": t.run_id, "gdwm.row": t.label}
    lineage |= metric_tags({k: v for k, v in metrics.items() if not k.startswith("count/")})
    call(sink, "tag_versions", [r.key for r in ok.values()], lineage)
    call(sink, "end_run", t.run_id, "FINISHED")
    console.print(f"[green]trial '{t.label}' finished[/green] ({len(metrics)} metrics)")


def _durations(cfg: DictConfig) -> dict[str, float]:
    """Median wall seconds of finished stage runs per stage in the store (the dry run's estimate); {} if none."""
    from pathlib import Path

    uri = cfg.tracking.uri
    if uri.startswith("sqlite:///") and not Path(uri.removeprefix("sqlite:///")).is_file():
        return {}
    from gdwm.tracking import TrackingBackend

    backend = TrackingBackend(uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    runs = backend.search_runs("tags.`gdwm.kind` = 'stage' and attributes.status = 'FINISHED'", 5000)
    per: dict[str, list[float]] = {}
    for r in runs:
        if r["end_time"] and r["start_time"]:
            per.setdefault(r["tags"]["gdwm.stage"], []).append((r["end_time"] - r["start_time"]) / 1000)
    return {s: statistics.median(v) for s, v in per.items()}


def print_sweep_plan(sweep: SweepConfig, trials: list[Trial], durations: dict[str, float]) -> dict[str, int]:
    """Trials x stages: cached, to run (first trial needing the key) or shared (an earlier trial runs it)."""
    stages = list(dict.fromkeys(n for t in trials for n in t.order))
    table = Table(title=f"sweep {sweep.name}: {len(trials)} trials", header_style="bold")
    table.add_column("trial")
    for s in stages:
        table.add_column(s)
    claimed: set[tuple[str, str]] = set()
    counts = {"cached": 0, "to run": 0, "shared": 0}
    seconds = 0.0
    for t in trials:
        cells = []
        for s in stages:
            if s not in t.keys:
                cells.append("")
                continue
            k = (s, t.keys[s])
            cached = all(r.status == "cached" for r in t.rows if r.stage == s)
            state = "cached" if cached else "shared" if k in claimed else "to run"
            if state == "to run":
                seconds += durations.get(s, float("nan"))
            claimed.add(k)
            counts[state] += 1
            cells.append({"cached": "[dim]cached[/dim]", "shared": "[cyan]shared[/cyan]", "to run": "run"}[state])
        table.add_row(t.label, *cells)
    console.print(table)
    est = f"~{seconds / 60:.0f} min of stage time (medians of earlier runs)" if seconds == seconds else (
        "no duration estimate (no earlier runs of some stages in this store)")  # fmt: skip
    console.print(f"{counts['to run']} stage executions to run, {counts['shared']} shared, {counts['cached']} "
                  f"cached; {est}")  # fmt: skip
    return counts


def report(cfg: DictConfig, sweep: SweepConfig, argv: list[str]) -> int:
    """The comparison report of the sweep (``gdwm compare``) into workdir/reports/<name> and the sweep run."""
    from gdwm.compare.command import compare

    extra = [a for a in user_overrides(argv) if a.split("=", 1)[0].split(".")[0] in ("workdir", "tracking", "ui")]
    base = ["args=compare", f"compare={sweep.layout}", f"args.sweep={sweep.name}"]
    if sweep.baseline:
        base.append(f"args.baseline={sweep.baseline}")
    return compare(load_config([*base, *extra]))
