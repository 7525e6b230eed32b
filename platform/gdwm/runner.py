"""The one driver of every launch: ``gdwm run`` (one row), ``gdwm sweep`` (rows x grid), ``gdwm regress``.

Trials come planned (``gdwm.plan``): one per (row, seed), each with its config and every stage key. The driver
submits each distinct stage key once as a Ray task chained to its upstream ObjectRefs -- a stage several trials
share (seed-free stages across the seeds of a row, common upstream across rows) runs once and feeds them all --
polls until every trial has an outcome, finds the root cause of each failure, and records it all in MLflow:

- ``gdwm sweep``: the sweep's run (``gdwm.kind=sweep``) holds a run per row (``row``: the row's aggregate, mean,
  ``std/<metric>`` and ``n/<metric>`` over its finished seeds), which holds a run per seed (``trial``: that seed's
  evaluation metrics, ``gdwm.seed``, links to the stage runs it used, its per-sample tables);
- ``gdwm run``: its run (``gdwm.kind=run``) is the row; with one seed it is the trial too, with several it holds a
  ``trial`` run per seed.

Stage runs nest under the launch's run, one per cache key (``gdwm.executor``). Every run ends FINISHED, FAILED or
KILLED; a killed driver's leftovers are reconciled by the next one.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import itertools
import json
import math
import os
import signal
import socket
import statistics
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import ray
from omegaconf import DictConfig, OmegaConf
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
from rich.live import Live
from rich.table import Table

from gdwm.cache import CACHE_KEYS, Cache
from gdwm.config import SweepConfig
from gdwm.dag import Pipeline
from gdwm.determinism import worker_env
from gdwm.environment.runs import log_launch
from gdwm.errors import one_line
from gdwm.executor import (
    REUSED_SAME,
    StageFailed,
    StageResult,
    run_scene_stage,
    run_stage,
    stage_config,
    task_options,
    verified,
)
from gdwm.keylock import KeyLock
from gdwm.plan import (
    PlanError,
    PlanRow,
    Row,
    RunError,
    Trial,
    check_seed_overrides,
    compose,
    print_reasons,
    resolve_seeds,
)
from gdwm.progress import ProgressActor, render
from gdwm.simcluster import SimCluster, SimConfig
from gdwm.term import console, err_console
from gdwm.tracking import AliveExcept, RunGuard, Sink, TrackingClient, open_tracking, process_owner
from gdwm.zoo.registry import metric_tags

__all__ = ["PlanError", "RunError", "launch", "run_pipeline"]

TRIAL_KEY, ROW_KEY, LAUNCH = "gdwm.trial_key", "gdwm.row_key", "gdwm.launch"

Outcome = StageResult | str | None
"""A stage's outcome for a trial: its result, an error message (it failed), or None (an upstream failed)."""


@dataclass
class TrialResult:
    trial: Trial
    results: dict[str, StageResult] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    """Stage -> error message of the stages that failed."""
    blocked: list[str] = field(default_factory=list)
    """Stages that never ran because an upstream failed."""
    metrics: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.failed and not self.blocked


@dataclass
class LaunchSummary:
    trials: list[TrialResult] = field(default_factory=list)
    executions: int = 0
    """Stage executions this invocation ran (distinct keys not cached)."""
    naive: int = 0
    """Stage executions the trials would need as independent runs without a cache."""
    parent_run_id: str | None = None

    @property
    def ok(self) -> bool:
        return all(t.ok for t in self.trials)

    @property
    def failed(self) -> dict[str, str]:
        """Trial name -> ``stage: message`` of every failed trial."""
        return {t.trial.name: "; ".join(t.failed.values()) for t in self.trials if t.failed}

    @property
    def results(self) -> dict[str, StageResult]:
        """The stage results of the only trial (a one-seed ``gdwm run``)."""
        if len(self.trials) != 1:
            raise ValueError(f"{len(self.trials)} trials: read each one's results from .trials")
        return self.trials[0].results


# ---- Ray and tracking ------------------------------------------------------------------------------------------
def init_ray(cfg: DictConfig) -> SimCluster | bool:
    """Start (or join) Ray as the cluster config says: truthy if this call started it (the ``SimCluster`` it
    started for ``cluster=sim``, to stop after ``ray.shutdown``)."""
    if ray.is_initialized():
        return False
    c = cfg.cluster
    kwargs = {"include_dashboard": False, "log_to_driver": cfg.run.worker_logs}
    env_vars = worker_env(cfg.run.deterministic)
    started: SimCluster | bool = True
    if c.address:
        check_address(str(c.address), float(c.get("connect_timeout_s", 10.0)))
        # A cluster's workers run the installed wheel (k8s/Dockerfile); the driver's paths mean nothing there.
        ray.init(address=c.address, runtime_env={"env_vars": env_vars}, **kwargs)
    else:
        # Local workers import the stage modules from wherever the driver does.
        env_vars["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        if c.get("sim") is not None:
            started = SimCluster(SimConfig(**c.sim), Path(cfg.workdir).resolve() / "sim-cluster").start()
            # Ray's own helpers that look for "the" cluster (Ray Train's placement group cleaner) must find this one
            env_vars["RAY_ADDRESS"] = started.address
            try:
                ray.init(address=started.address, runtime_env={"env_vars": env_vars}, **kwargs)
            except BaseException:
                started.stop()
                raise
            console.print(started.describe(), markup=False)
        else:
            # address="local": a new Ray of its own, never a cluster some other process started on this machine
            ray.init(
                address="local", num_cpus=c.num_cpus, num_gpus=c.num_gpus, runtime_env={"env_vars": env_vars}, **kwargs
            )
    if threading.current_thread() is threading.main_thread():
        # ray.init's own SIGTERM handler exits 1; exit 143 as a terminated process should (finally shuts Ray).
        signal.signal(signal.SIGTERM, _sigterm)
    return started


def check_address(address: str, timeout_s: float) -> None:
    """A RunError naming ``address`` unless its host and port accept a connection within ``timeout_s`` (ray.init
    itself retries an address that does not answer for a minute and more); ``auto`` is Ray's to resolve."""
    hostport = address.removeprefix("ray://").rsplit("/", 1)[0]
    host, sep, port = hostport.rpartition(":")
    if address == "auto" or not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as e:
        why = "no answer" if isinstance(e, TimeoutError) else e.strerror or type(e).__name__
        raise RunError(
            f"cluster.address={address}: no Ray cluster answers there ({why} within {timeout_s:g} s); "
            "is the head up and the address right?"
        ) from None


_TERMINATED: list[int] = []


def _sigterm(signum: int, _frame) -> None:
    # Raising here would surface inside ray.wait, which turns any exception into SystemExit(1): record it and
    # let the poll loop exit 143 between waits.
    _TERMINATED.append(signum)


@contextlib.contextmanager
def driver_session(cfg: DictConfig) -> Iterator[TrackingClient]:
    """Ray (started here unless already up) and the tracking client of one driver invocation; runs that dead drivers
    left RUNNING are reconciled first. Whatever escapes (Ctrl-C, SIGTERM, an error) ends the runs this driver owns
    KILLED now, not at the next reconcile."""
    started = init_ray(cfg)
    try:
        sink, close = open_tracking(cfg.tracking)
    except BaseException:
        _stop_ray(started)
        raise
    tracking = TrackingClient(sink)
    try:
        tracking.reconcile()
        yield tracking
    except BaseException as exc:
        try:
            tracking.reconcile(AliveExcept(process_owner()))
        except Exception as e:  # the store can't be written (a full disk): the error that got us here matters more
            hint = "its runs stay RUNNING until the next gdwm run or sweep on this store ends them"
            if isinstance(exc, Exception):
                exc.gdwm_hint = hint  # the CLI's one line carries it
            else:
                err_console.print(f"gdwm: could not end this driver's runs ({one_line(e)}); {hint}", markup=False)
        raise
    finally:
        close()
        _stop_ray(started)


def _stop_ray(started: SimCluster | bool) -> None:
    if isinstance(started, SimCluster):
        console.print(started.describe_placement(), markup=False)
    if started:
        ray.shutdown()
    if isinstance(started, SimCluster):
        started.stop()


# ---- MLflow layout ---------------------------------------------------------------------------------------------
@dataclass
class Layout:
    """Where one launch's runs go (module docstring): a sweep's run with a run per row, or a ``gdwm run``'s run."""

    sweep: SweepConfig | None
    """The sweep, or None for ``gdwm run``."""
    launch_id: str
    """Finds this launch's row and trial runs again on a re-run: ``sweep:<name>`` or ``run:<run key>``."""
    pipeline: str

    @property
    def stage_tags(self) -> dict[str, str]:
        return {"gdwm.sweep": self.sweep.name} if self.sweep else {}

    def open(self, tracking: TrackingClient, cfg: DictConfig, rows: list[Row], trials: list[Trial]) -> str:
        """The launch's run (found again or created), and every row's and trial's run under it."""
        parent = self._parent(tracking, cfg)
        if self.sweep is None:  # the run is the row (and, with one seed, the trial)
            seeds = rows[0].seeds
            tracking.set_tags(parent, {"gdwm.seeds": ",".join(map(str, seeds))} | (
                {"gdwm.seed": str(seeds[0])} if len(seeds) == 1 else {}))  # fmt: skip
        for row in rows:
            mine = [t for t in trials if t.row is row]
            row.run_id = parent if self.sweep is None else self._row_run(tracking, parent, row, mine[0].cfg)
            for t in mine:
                t.run_id = row.run_id if len(mine) == 1 and self.sweep is None else self._trial_run(tracking, row, t)
        return parent

    def _find(self, tracking: TrackingClient, tags: dict[str, str]) -> str | None:
        found = tracking.search_runs(" and ".join(f"tags.`{k}` = '{v}'" for k, v in tags.items()))
        if not found:
            return None
        tracking.reopen_run(found[0]["run_id"])
        return found[0]["run_id"]

    def _parent(self, tracking: TrackingClient, cfg: DictConfig) -> str:
        """A re-run (a resume after a crash, an added row) continues the same run."""
        if self.sweep is not None:
            tags = {"gdwm.kind": "sweep", "gdwm.sweep": self.sweep.name}
            run_id = self._find(tracking, tags) or tracking.create_run(f"sweep-{self.sweep.name}", tags)
            text = OmegaConf.to_yaml(OmegaConf.structured(self.sweep))
            tracking.log_text(run_id, text, "sweep.yaml")
            return run_id
        tags = {"gdwm.kind": "run", "gdwm.run_key": self.launch_id.removeprefix("run:")}
        run_id = self._find(tracking, tags)
        if run_id is None:
            tags |= {"gdwm.pipeline": self.pipeline}
            run_id = tracking.create_run(f"run-{self.pipeline}-{tags['gdwm.run_key'][:8]}", tags, None)
            tracking.log_params(run_id, OmegaConf.to_container(cfg, resolve=True))
        return run_id

    def _row_tags(self, row: Row) -> dict[str, str]:
        tags = {"gdwm.row": row.label, "gdwm.trial_index": str(row.index), "gdwm.seeds": ",".join(map(str, row.seeds))}
        tags |= {f"gdwm.factor.{k}": v for k, v in row.factors.items()}
        return tags | ({"gdwm.sweep": self.sweep.name, "gdwm.overrides": " ".join(row.overrides)} if self.sweep else {})

    def _row_run(self, tracking: TrackingClient, parent: str, row: Row, cfg: DictConfig) -> str:
        tags = {"gdwm.kind": "row", ROW_KEY: row.key, LAUNCH: self.launch_id, **self._row_tags(row)}
        run_id = self._find(tracking, {ROW_KEY: row.key, LAUNCH: self.launch_id})
        if run_id is not None:
            tracking.set_tags(run_id, tags)  # an edited row keeps its run; its index may move
            return run_id
        run_id = tracking.create_run(f"{self.sweep.name}/{row.label}", tags, parent)
        tracking.log_params(run_id, OmegaConf.to_container(cfg, resolve=True))
        return run_id

    def _trial_run(self, tracking: TrackingClient, row: Row, t: Trial) -> str:
        tags = {"gdwm.kind": "trial", TRIAL_KEY: t.key, LAUNCH: self.launch_id, "gdwm.seed": str(t.seed)}
        tags |= self._row_tags(row) if self.sweep else {}
        run_id = self._find(tracking, {TRIAL_KEY: t.key, LAUNCH: self.launch_id})
        if run_id is not None:
            tracking.set_tags(run_id, tags)
            return run_id
        name = f"{self.sweep.name}/{t.name}" if self.sweep else f"seed-{t.seed}"
        run_id = tracking.create_run(name, tags, row.run_id)
        tracking.log_params(run_id, OmegaConf.to_container(t.cfg, resolve=True))
        return run_id


def launch_key(pipe_name: str, trials: list[Trial]) -> str:
    """Identity of a ``gdwm run``: the pipeline, the stages and every trial's keys (re-running continues it)."""
    payload = [pipe_name, trials[0].order, [[r.key for r in t.plan] for t in trials]]
    if len(trials) == 1:  # the layout a one-seed run had before seeds existed
        payload = [pipe_name, trials[0].order, [r.key for r in trials[0].plan]]
    return hashlib.sha256(json.dumps(payload).encode()).hexdigest()


# ---- evaluation onto the trial's run ---------------------------------------------------------------------------
def evaluation_metrics(pipe: Pipeline, results: dict[str, StageResult]) -> dict[str, float]:
    """The numeric values evaluation stages returned (cached or not): the metrics of the trial's run."""
    out: dict[str, float] = {}
    for name, r in results.items():
        if pipe.stages[name].evaluation:
            out |= {k: float(v) for k, v in r.extra.items() if isinstance(v, int | float) and not isinstance(v, bool)}
    return out


@dataclass(frozen=True)
class Samples:
    """An evaluation stage's per-sample table and how to rescore it (``StageDef.samples``, ``score``, ``strata``)."""

    path: Path
    scorer: str
    """``module:function``."""
    strata: str | None = None

    def tags(self, stage: str, artifact: str) -> dict[str, str]:
        """What a run carries so ``gdwm compare`` and ``gdwm regress`` can resample it (``artifact``: where it is)."""
        out = {f"gdwm.samples.{stage}": artifact, f"gdwm.scorer.{stage}": self.scorer}
        return out | ({f"gdwm.strata.{stage}": self.strata} if self.strata else {})


def evaluation_samples(pipe: Pipeline, results: dict[str, StageResult]) -> dict[str, Samples]:
    """Stage -> its per-sample table and scorer, for the evaluation stages that keep one."""
    out = {}
    for name, r in results.items():
        sd = pipe.stages[name]
        if sd.evaluation and sd.samples and r.path and (Path(r.path) / sd.samples).is_file():
            out[name] = Samples(Path(r.path) / sd.samples, f"{sd.score.__module__}:{sd.score.__qualname__}", sd.strata)
    return out


def report_evaluation(
    tracking: TrackingClient, run_id: str, pipe: Pipeline, results: dict[str, StageResult]
) -> dict[str, float]:
    """The evaluation stages' metrics, per-sample tables (``<stage>/*.parquet``) and how to rescore them (tags
    ``gdwm.samples.<stage>``, ``gdwm.scorer.<stage>``, ``gdwm.strata.<stage>``: what ``gdwm compare`` resamples)
    onto the trial's run."""
    metrics = evaluation_metrics(pipe, results)
    if metrics:
        tracking.log_metrics(run_id, metrics)
    for name, r in results.items():
        if pipe.stages[name].evaluation and r.path:
            for table in sorted(Path(r.path).glob("*.parquet")):
                tracking.log_artifact(run_id, str(table), name)
    tags = {
        k: v for n, s in evaluation_samples(pipe, results).items() for k, v in s.tags(n, f"{n}/{s.path.name}").items()
    }
    if tags:
        tracking.set_tags(run_id, tags)
    return metrics


def aggregate(per_seed: list[dict[str, float]]) -> dict[str, float]:
    """A row's aggregate over its finished seeds: ``<metric>`` the mean, ``std/<metric>`` (n >= 2), ``n/<metric>``."""
    out: dict[str, float] = {}
    for m in sorted({m for d in per_seed for m in d if not m.startswith("count/")}):
        values = [d[m] for d in per_seed if m in d and not math.isnan(d[m])]
        if not values:
            continue
        out[m] = statistics.fmean(values)
        out[f"n/{m}"] = float(len(values))
        if len(values) > 1:
            out[f"std/{m}"] = statistics.stdev(values)
    return out


def entry_keys(results: Mapping[str, StageResult]) -> dict[str, list[str]]:
    return {n: sorted({k for k, _ in r.scenes.values()}) if r.scenes else [r.key] for n, r in results.items()}


# ---- the driver loop -------------------------------------------------------------------------------------------
def _root_cause(e: BaseException) -> BaseException:
    while isinstance(e, ray.exceptions.RayTaskError) and e.cause is not None and e.cause is not e:
        e = e.cause
    return e


def _outcome(ref: ray.ObjectRef, stage: str) -> Outcome:
    try:
        return ray.get(ref)
    except Exception as e:  # Ray re-raises a task's error as a subclass of both RayTaskError and it
        root = _root_cause(e)
        if isinstance(root, StageFailed) and root.stage != stage:
            return None
        return StageFailed.__str__(root) if isinstance(root, StageFailed) else f"stage '{stage}' failed: {root!r}"


def _print_stage(k: tuple[str, str], r: Outcome, users: list[str]) -> None:
    what = "failed" if isinstance(r, str) else "blocked" if r is None else "cached" if r.cached else "done"
    shared = f" (shared by {len(users)} trials)" if len(users) > 1 else ""
    console.print(f"  {k[0]:<14} {k[1][:12]}  {what}{shared}", markup=False)


def execute(
    trials: list[Trial],
    sink: Sink,
    parent: str,
    on_trial: Callable[[Trial, dict[str, Outcome]], None],
    *,
    stage_tags: dict[str, str] | None = None,
    progress=None,
    live: bool = False,
    print_stages: bool = True,
) -> int:
    """Submit every distinct stage key once, poll until every trial has an outcome per stage, hand each finished
    trial to ``on_trial``; returns how many stage executions ran (not cached)."""
    submitted: dict[tuple[str, str], ray.ObjectRef] = {}
    for t in trials:
        # the cluster profile a stage ran on: `gdwm sweep --dry-run` estimates durations from that cluster's runs
        env = t.env(sink, parent, progress, run_tags={"gdwm.cluster": str(t.cfg.cluster.name), **(stage_tags or {})})
        refs: dict[str, ray.ObjectRef] = {}
        for name in t.order:
            sd = t.pipe.stages[name]
            k = (name, t.keys[name])
            if k not in submitted:
                fn = run_scene_stage if sd.per_scene else run_stage
                ups = [refs[u] for u in sd.upstream]
                submitted[k] = fn.options(**task_options(sd, env)).remote(sd, stage_config(sd, t.cfg), env, *ups)
            refs[name] = submitted[k]
    users = {k: [t.name for t in trials if t.keys.get(k[0]) == k[1]] for k in submitted}
    outcome: dict[tuple[str, str], Outcome] = {}
    pending = {ref: k for k, ref in submitted.items()}
    waiting = list(trials)
    executions = 0

    def poll() -> None:
        nonlocal executions
        if _TERMINATED:
            raise SystemExit(128 + _TERMINATED[0])
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.5)
        for ref in ready:
            k = pending.pop(ref)
            outcome[k] = _outcome(ref, k[0])
            if print_stages:
                _print_stage(k, outcome[k], users[k])
            if isinstance(outcome[k], StageResult) and not outcome[k].cached:
                executions += 1
            if progress is not None and outcome[k] is None:
                progress.status.remote(k[0], None, "blocked", message="an upstream stage failed")
        for t in [t for t in waiting if all((n, t.keys[n]) in outcome for n in t.order)]:
            waiting.remove(t)
            on_trial(t, {n: outcome[(n, t.keys[n])] for n in t.order})

    order = list(dict.fromkeys(n for t in trials for n in t.order))
    if live and progress is not None and console.is_terminal:
        with Live(render([], order), console=console, refresh_per_second=4) as view:
            while pending or waiting:
                poll()
                view.update(render(ray.get(progress.snapshot.remote()), order))
    else:
        while pending or waiting:
            poll()
    return executions


def launch(
    cfg: DictConfig,
    rows: list[Row],
    trials: list[Trial],
    layout: Layout,
    *,
    live: bool = False,
    print_stages: bool = True,
) -> LaunchSummary:
    """Run planned trials under one driver session and record them as ``layout`` says."""
    summary = LaunchSummary(naive=sum(len(t.order) for t in trials))
    results: dict[int, TrialResult] = {}

    with _launch_lock(cfg, layout), driver_session(cfg) as tracking:
        parent = layout.open(tracking, cfg, rows, trials)
        summary.parent_run_id = parent
        log_launch(tracking, cfg, parent, trials)  # the environment these runs ran in (gdwm.environment)
        # on the driver's node, as the tracking actor: a worker node lost mid-run must not take the board along
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        progress = ProgressActor.options(scheduling_strategy=here).remote() if layout.sweep is None else None

        def on_trial(t: Trial, outcomes: dict[str, Outcome]) -> None:
            results[id(t)] = _finish_trial(tracking, layout, t, outcomes)
            row_trials = [x for x in trials if x.row is t.row]
            if all(id(x) in results for x in row_trials):
                _finish_row(tracking, layout, t.row, [results[id(x)] for x in row_trials])

        try:
            with RunGuard(tracking.sink, parent):
                summary.executions = execute(trials, tracking.sink, parent, on_trial, stage_tags=layout.stage_tags,
                                             progress=progress, live=live, print_stages=print_stages)  # fmt: skip
                summary.trials = [results[id(t)] for t in trials]
                if layout.sweep is None:
                    tracking.log_metrics(parent, {"stages_run": summary.executions})
                    _print_run_summaries(summary, progress)
                    if not summary.ok:  # the guard ends the run FAILED; the caller reports from the summary
                        bad = next(t for t in summary.trials if not t.ok)
                        stage = next(iter(bad.failed), bad.blocked[0] if bad.blocked else "")
                        raise StageFailed(stage, {None: bad.failed.get(stage, "blocked")})
                else:
                    tracking.log_metrics(parent, {
                        "trials": len(trials), "trials_failed": sum(not t.ok for t in summary.trials),
                        "stage_executions": summary.executions, "stage_executions_naive": summary.naive,
                    })  # fmt: skip
        except StageFailed:
            pass
    return summary


def _launch_lock(cfg: DictConfig, layout: Layout) -> KeyLock:
    """One driver at a time per launch (the same ``gdwm run`` or sweep on one tracking store): a second one waits,
    then finds every stage cached and continues the same runs. Different launches run side by side; the stages
    they share are computed once (the per-key lock in the executor)."""
    key = hashlib.sha256(f"{cfg.tracking.uri}\n{layout.launch_id}".encode()).hexdigest()

    def waiting(owner: str) -> None:
        console.print(f"another driver ({owner}) is running this {layout.launch_id.split(':')[0]} on this store; "
                      "waiting for it to finish")  # fmt: skip

    return KeyLock(Cache(cfg.cache.uri), "launch", key, on_wait=waiting)


def _finish_trial(tracking: TrackingClient, layout: Layout, t: Trial, outcomes: dict[str, Outcome]) -> TrialResult:
    """Record one trial's outcome on its run: a failure (stage, error), or its evaluation and stage links."""
    res = TrialResult(t)
    for n, r in outcomes.items():
        if isinstance(r, StageResult):
            res.results[n] = r
        elif isinstance(r, str):
            res.failed[n] = r
        else:
            res.blocked.append(n)
    own_run = t.run_id != t.row.run_id  # else it is the launch's run, which its guard ends
    if res.failed:
        stage, msg = next(iter(res.failed.items()))
        tracking.set_tags(t.run_id, {"gdwm.failed_stage": stage, "gdwm.error": msg})
        tracking.log_text(t.run_id, msg, "error.txt")
        if own_run:
            tracking.end_run(t.run_id, "FAILED")
        if layout.sweep is not None:
            console.print(f"[red]trial '{t.name}' failed at {stage}[/red]")
        return res
    links = {f"gdwm.stage_run.{n}": r.run_id for n, r in res.results.items() if r.run_id}
    tracking.set_tags(t.run_id, links | {f"gdwm.stage_key.{n}": r.key for n, r in res.results.items()})
    tracking.log_text(t.run_id, json.dumps(entry_keys(res.results), indent=1), CACHE_KEYS)
    res.metrics = report_evaluation(tracking, t.run_id, t.pipe, res.results)
    if layout.sweep is not None:
        # the zoo versions this trial's stages registered carry its sweep, trial and key metrics
        lineage = {"gdwm.sweep": layout.sweep.name, "gdwm.trial": t.run_id, "gdwm.row": t.label}
        lineage |= metric_tags({k: v for k, v in res.metrics.items() if not k.startswith("count/")})
        tracking.tag_versions([r.key for r in res.results.values()], lineage)
        console.print(f"[green]trial '{t.name}' finished[/green] ({len(res.metrics)} metrics)")
    if own_run and not res.blocked:
        tracking.end_run(t.run_id, "FINISHED")
    return res


def _finish_row(tracking: TrackingClient, layout: Layout, row: Row, results: list[TrialResult]) -> None:
    """A row's aggregate over its finished seeds, on the row's run (when it is not its only trial's run)."""
    if all(r.trial.run_id == row.run_id for r in results):
        return
    agg = aggregate([r.metrics for r in results if r.ok])
    if agg:
        tracking.log_metrics(row.run_id, agg)
    if layout.sweep is not None:
        tracking.end_run(row.run_id, "FINISHED" if any(r.ok for r in results) else "FAILED")


# ---- gdwm run ----------------------------------------------------------------------------------------------------
def run_pipeline(
    cfg: DictConfig,
    overrides: list[str] | None = None,
    *,
    seeds: list[int] | None = None,
    seeds_key: str = "seeds",
    dry_run: bool = False,
    live: bool | None = None,
) -> LaunchSummary:
    """``gdwm run``: one row of trials, one per seed (``seeds=[...]``, else ``seeds``, else ``[seed]``).

    ``overrides`` (what ``cfg`` was composed from) let each seed compose its own config; without them ``cfg`` is
    the only trial."""
    trial_seeds = resolve_seeds(cfg, seeds, seeds_key)
    check_seed_overrides(cfg.get("seeds") is not None or seeds is not None, "gdwm run", overrides or [])
    row = Row(0, "", {}, [], trial_seeds)
    trials = [Trial(row, s) for s in trial_seeds]
    one = trial_seeds == [int(cfg.seed)]
    plan_only = dry_run or cfg.run.plan
    compose(trials, None if one else [o for o in overrides or [] if not o.startswith("--")], "gdwm run", cfg,
            dry_run=plan_only)  # fmt: skip
    if plan_only:
        print_plan(trials)
        return LaunchSummary(naive=sum(len(t.order) for t in trials))
    cache = Cache(cfg.cache.uri)
    if all(r.status == "cached" and r.reused == REUSED_SAME for t in trials for r in t.plan) and all(
        verified(cache, t.settings["checkpoint_root"], r.stage, r.key, t.settings["verify"])
        for t in trials
        for r in t.plan
    ):
        # Nothing to run: no Ray, no tracking; a no-op re-run costs only the hash checks.
        n = len({(r.stage, r.key) for t in trials for r in t.plan})
        console.print(f"all {n} stage outputs cached and verified; nothing to run")
        return LaunchSummary([TrialResult(t, _cached_results(t.plan, cache)) for t in trials])
    pipe = trials[0].pipe
    layout = Layout(None, f"run:{launch_key(pipe.name, trials)}", pipe.name)
    show = cfg.run.live if live is None else live
    return launch(cfg, [row], trials, layout, live=show, print_stages=False)


def _cached_results(rows: list[PlanRow], cache: Cache) -> dict[str, StageResult]:
    """Every stage's entry (local directory, per scene where it fans out) when the whole plan is cached."""
    out: dict[str, StageResult] = {}
    for r in rows:
        m = cache.lookup(r.stage, r.key, verify=False, use=False)  # verified (and used) just before
        path = str(cache.materialize(m))
        if r.scene is None:
            out[r.stage] = StageResult(r.stage, r.key, True, m.run_id, path=path, extra=dict(m.extra))
        else:
            res = out.setdefault(r.stage, StageResult(r.stage, "", True, None, scenes={}))
            res.scenes[r.scene] = (r.key, path)  # type: ignore[index]
    return out


_PLAN_SCENES = 12
"""A stage with more scenes than this shows as one line of the plan."""


def print_plan(trials: list[Trial]) -> None:
    """Stage x scene: cached / to run (``shared`` where an earlier seed's row already runs the same key)."""
    several = len(trials) > 1
    t = Table(title="plan", header_style="bold")
    for col in ("seed",) * several + ("stage", "scene", "status", "key", "resources"):
        t.add_column(col)
    seen: set[tuple[str, str]] = set()
    counts = {"cached": 0, "to run": 0, "shared": 0}
    for trial in trials:
        env = trial.env()
        for stage, rows in itertools.groupby(trial.plan, key=lambda r: r.stage):
            rows = list(rows)
            res = env.resources.get(rows[0].resources, {})
            cpus, gpus, n = res.get("num_cpus", 0), res.get("num_gpus", 0), res.get("num_workers", 1)
            desc = f"{rows[0].resources}: {cpus:g} CPU, {gpus:g} GPU, " + (f"x{n}" if n else "in-process")
            shown_rows = []
            for r in rows:
                status = "shared" if r.status == "to run" and (r.stage, r.key) in seen else r.status
                seen.add((r.stage, r.key))
                counts[status] += 1
                shown_rows.append((r.scene or "-", r.shown if status == r.status else status, r.key[:12]))
            if len(shown_rows) > _PLAN_SCENES:  # a real dataset's hundreds of scenes: one line per stage
                tally = collections.Counter(s for _, s, _ in shown_rows)
                shown_rows = [(f"{len(shown_rows)} scenes", ", ".join(f"{k} {v}" for k, v in tally.items()), "")]
            for scene, status, key in shown_rows:
                t.add_row(*(str(trial.seed),) * several, stage, scene, status, key, desc)
    for note in dict.fromkeys(trial.pending_data for trial in trials if trial.pending_data):
        console.print(f"{note}: nothing is generated by a dry run, so every stage is to run", markup=False)
    console.print(t)
    console.print(", ".join(f"{n} {s}" for s, n in counts.items() if n or s != "shared"))
    print_reasons(trials)


def _print_run_summaries(summary: LaunchSummary, progress) -> None:
    items = ray.get(progress.snapshot.remote()) if progress is not None else []
    heads = {i.stage: i for i in items if i.scene is None}
    for res in summary.trials:
        title = "run summary" + (f" (seed {res.trial.seed})" if len(summary.trials) > 1 else "")
        t = Table(title=title, header_style="bold")
        for col in ("stage", "status", "wall s", "cache key", "MLflow run"):
            t.add_column(col)
        for name in res.trial.order:
            r = res.results.get(name)
            if r is not None:
                status = "done" if not r.cached else "cached" if r.reused == REUSED_SAME else f"cached ({r.reused})"
                if r.failed:
                    status += f" ({len(r.failed)} scene(s) skipped)"
            else:
                status = "failed" if name in res.failed else "blocked"
            head = heads.get(name)
            wall = head.wall if head is not None else None
            key = r.key[:12] if r else res.trial.keys.get(name, "")[:12]
            run_id = (r.run_id or "") if r else (head.run_id if head is not None else "")
            t.add_row(name, status, f"{wall:.1f}" if wall is not None else "", key, run_id)
        console.print(t)
        for msg in res.failed.values():
            console.print(f"[red]{msg}[/red]", markup=True)
