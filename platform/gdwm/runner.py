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
import importlib
import itertools
import json
import logging
import math
import os
import signal
import socket
import statistics
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import ray
from omegaconf import DictConfig, OmegaConf
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
from rich.table import Table

from gdwm import workerlogs
from gdwm.cache import CACHE_KEYS, Cache
from gdwm.config import SweepConfig
from gdwm.dag import Pipeline
from gdwm.determinism import worker_env
from gdwm.environment.runs import DIGEST_TAG, launch_record, log_launch, record_tags
from gdwm.errors import one_line, oom_line
from gdwm.events import Event, launch_id
from gdwm.executor import (
    REUSED_SAME,
    StageFailed,
    StageResult,
    code_artifact,
    run_scene_stage,
    run_stage,
    stage_config,
    task_options,
    verified,
)
from gdwm.fromenv import recorded
from gdwm.keylock import KeyLock
from gdwm.monitor import Monitor
from gdwm.phases import phase
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
from gdwm.preflight import check_ray_temp
from gdwm.progress import Execution, LaunchProgress, ProgressActor, Reporter
from gdwm.simcluster import SimCluster, SimConfig, stop_monitor
from gdwm.term import NORMAL, QUIET, console, err_console
from gdwm.tracking import (
    AliveExcept,
    NewRun,
    RunGuard,
    RunWrite,
    Sink,
    TrackingClient,
    WriteQueue,
    open_tracking,
    process_owner,
)
from gdwm.tracking.params import PARAMS_BASE_TAG, flatten_params, own_params, relative_paths
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
    monitor: Monitor | None = None
    """The launch's progress (its state, events file and folder); None when nothing launched."""

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
    # Ray's INFO banner ("Started a local Ray instance") is noise in gdwm's output; its warnings still show.
    kwargs = {"include_dashboard": False, "log_to_driver": cfg.run.worker_logs, "logging_level": logging.WARNING}
    env_vars = worker_env(cfg.run.deterministic)
    started: SimCluster | bool = True
    if not c.address:
        own_ray_auth()
    if c.address:
        check_address(str(c.address), float(c.get("connect_timeout_s", 10.0)))
        # A cluster's workers run the installed wheel (k8s/Dockerfile); the driver's paths mean nothing there.
        ray.init(address=c.address, runtime_env={"env_vars": env_vars}, **kwargs)
    else:
        if why := check_ray_temp():  # Ray's own symptom is a timeout a minute later
            raise RunError(why)
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
            # address="local": a new Ray of its own, never a cluster some other process started on this machine.
            # A worker Ray's OOM killer ended is not retried (Ray's default retries it 15 times, minutes of the same
            # end): the stage fails at once naming itself (and its scene). The workers' variables go into the
            # environment Ray's processes start with, not into a job runtime_env: workers of a runtime_env are
            # started for it, so the workers Ray prestarts (one per CPU) would sit idle while every task and actor
            # waited for a new process. An idle worker lives a minute (Ray's default: one second once more than
            # num_cpus exist): a task that blocks on the tracking actor lets Ray start another worker, and a sweep's
            # next stage reuses that one (gdwm, MLflow and the stage's libraries imported) instead of a new process.
            system = {"task_oom_retries": 0, "idle_worker_killing_time_threshold_ms": IDLE_WORKER_MS}
            with _environ(env_vars):
                ray.init(address="local", num_cpus=c.num_cpus, num_gpus=c.num_gpus, _system_config=system, **kwargs)
    if threading.current_thread() is threading.main_thread():
        # ray.init's own SIGTERM handler exits 1; exit 143 as a terminated process should (finally shuts Ray).
        signal.signal(signal.SIGTERM, _sigterm)
    return started


@contextlib.contextmanager
def _environ(values: Mapping[str, str]) -> Iterator[None]:
    """``os.environ`` with ``values`` set for the block (what processes started in it inherit), then as it was."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


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


IDLE_WORKER_MS = 60_000
"""How long a local Ray keeps an idle worker process beyond its CPU count (see ``init_ray``)."""

AUTH_MODE_ENV = "RAY_AUTH_MODE"
"""Ray sets it to ``token`` in the driver when it turns token authentication on (by default for a local Ray)."""


class _TokenAuthNotice(logging.Filter):
    """Drops Ray's warning that token authentication is on, which it logs on every local start: on is what gdwm
    wants (and what Ray does by default), so a launch's log need not say it each time. Ray's warning that it is
    *off* still shows."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Token authentication is enabled for this Ray cluster")


def own_ray_auth() -> None:
    """Install the filter above on Ray's token-setup logger (once per process)."""
    logger = logging.getLogger("ray._private.authentication.authentication_token_setup")
    if not any(isinstance(f, _TokenAuthNotice) for f in logger.filters):
        logger.addFilter(_TokenAuthNotice())


_TERMINATED: list[int] = []


def _sigterm(signum: int, _frame) -> None:
    # Raising here would surface inside ray.wait, which turns any exception into SystemExit(1): record it and
    # let the poll loop exit 143 between waits.
    _TERMINATED.append(signum)


@ray.remote(num_cpus=0)
def import_modules(modules: list[str]) -> list[str]:
    """Imports ``modules`` in the worker that runs it; returns those it could (a stage that needs one it could not
    imports it again and fails naming itself)."""
    done = []
    for m in modules:
        try:
            importlib.import_module(m)
        except Exception:
            continue
        done.append(m)
    return done


def warm_modules(trials: list[Trial]) -> list[str]:
    """The modules of the stages a launch will execute, and ``gdwm.training`` (torch and Ray Train: 2-3 s) where one
    trains: a local Ray's first idle worker imports them while the driver waits for the tracking actor and the
    per-scene stages run in their actors, so the first training stage starts in a worker that has them (a toy run
    spent 3 of its 15 s in its tokenizer stage's imports). Cached stages need nothing."""
    out: dict[str, None] = {}
    for t in trials:
        for r in t.plan:
            if r.status == "to run" and t.pipe is not None and r.stage in t.pipe.stages:
                sd = t.pipe.stages[r.stage]
                out[sd.fn.__module__] = None
                if sd.resources == "train":
                    out["gdwm.training"] = None
    return list(out)


@contextlib.contextmanager
def driver_session(cfg: DictConfig, warm: list[str] | None = None) -> Iterator[TrackingClient]:
    """Ray (started here unless already up) and the tracking client of one driver invocation; runs that dead drivers
    left RUNNING are reconciled first. Whatever escapes (Ctrl-C, SIGTERM, an error) ends the runs this driver owns
    KILLED now, not at the next reconcile. ``warm``: modules a worker of a local Ray imports as soon as it is up
    (``warm_modules``)."""
    early = None
    if not cfg.tracking.single_writer:  # a store that is down fails before Ray starts
        with phase("tracking start"):
            early = open_tracking(cfg.tracking)
    try:
        with phase("ray start"):
            started = init_ray(cfg)
    except BaseException:
        if early is not None:
            early[1]()
        raise
    if warm and started is True and not cfg.cluster.address:
        import_modules.remote(warm)  # its worker goes back to Ray's pool with them, for a later task to reuse
    try:
        if early is None:
            with phase("tracking start"):
                early = open_tracking(cfg.tracking)
        sink, close = early
    except BaseException:
        _stop_ray(started)
        raise
    tracking = TrackingClient(sink)
    try:
        with phase("reconcile"):
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
        with phase("tracking stop"):
            close()
        if cfg.run.worker_logs and ray.is_initialized():
            with phase("worker logs"):
                if not workerlogs.drain():
                    err_console.print(
                        "gdwm: the workers' last output may be missing above (Ray did not forward it within "
                        f"{workerlogs.TIMEOUT_S:g} s)",
                        markup=False,
                    )
        with phase("ray stop"):
            _stop_ray(started)


def _stop_ray(started: SimCluster | bool) -> None:
    if isinstance(started, SimCluster):
        console.print(started.describe_placement(), markup=False)
    if started:
        if (node := getattr(ray._private.worker, "_global_node", None)) is not None:  # the Ray this process runs
            stop_monitor(node)
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
    recorded: set[str] = field(default_factory=set, init=False)
    """Row and trial runs an earlier launch of this one recorded an environment on (``gdwm.environment``)."""
    created: set[str] = field(default_factory=set, init=False)
    """Row and trial runs ``open`` created, with the tags its ``run_tags`` gave (the environment record's)."""
    _parent_params: dict[str, str] | None = field(default=None, init=False)
    """The params of the ``gdwm run`` run ``open`` created (None: found again, or a sweep)."""
    _sweep_params: dict[str, str] | None = field(default=None, init=False)
    """The params a sweep's run holds, found again (None: a sweep run ``open`` creates, or a ``gdwm run``)."""

    @property
    def stage_tags(self) -> dict[str, str]:
        return {"gdwm.sweep": self.sweep.name} if self.sweep else {}

    def open(
        self,
        tracking: TrackingClient,
        cfg: DictConfig,
        rows: list[Row],
        trials: list[Trial],
        run_tags: Callable[[str], Mapping[str, str]] | None = None,
    ) -> str:
        """The launch's run (found again or created), and every row's and trial's run under it: one search finds the
        runs an earlier launch of it made (reopened, re-tagged), one call creates the rest per level, with the tags
        ``run_tags(launch run)`` gives (a write less per run than tagging them after)."""
        parent = self._parent(tracking, cfg)
        born = dict(run_tags(parent)) if run_tags else {}
        if self.sweep is None:  # the run is the row (and, with one seed, the trial)
            seeds = rows[0].seeds
            tracking.set_tags(parent, {"gdwm.seeds": ",".join(map(str, seeds))} | (
                {"gdwm.seed": str(seeds[0])} if len(seeds) == 1 else {}))  # fmt: skip
        found = self._earlier(tracking)
        # a row's run holds its config as params (its first trial's; its seeds differ in the seed alone), a trial's
        # run what differs from it (gdwm.tracking.own_params), where the row's run is created now (one an earlier
        # launch made holds that launch's config); a gdwm run's trials are under the launch's run
        inherited: dict[int, dict[str, str]] = {}
        if self.sweep is None and self._parent_params is not None:
            inherited[id(rows[0])] = self._parent_params
        reopened: list[RunWrite] = []
        new_rows: list[tuple[Row, NewRun]] = []
        for row in rows:
            if self.sweep is None:
                row.run_id = parent
                continue
            tags = {"gdwm.kind": "row", ROW_KEY: row.key, LAUNCH: self.launch_id, **self._row_tags(row)}
            if (run_id := found.get((ROW_KEY, row.key))) is not None:  # an edited row keeps its run; its index may move
                row.run_id = run_id
                reopened.append(RunWrite(run_id, tags=tags, reopen=True))
                continue
            cfg0 = next(t for t in trials if t.row is row).cfg
            inherited[id(row)] = config_params(cfg0) | factor_params(row)
            new_rows.append((row, NewRun(f"{self.sweep.name}/{row.label}", tags | born, parent, inherited[id(row)])))
        if new_rows:
            self._trim_rows(tracking, parent, new_rows)
        for (row, _), run_id in zip(new_rows, tracking.create_runs([n for _, n in new_rows]), strict=True):
            row.run_id = run_id
            self.created.add(run_id)
        new_trials: list[tuple[Trial, NewRun]] = []
        for t in trials:
            if self.sweep is None and len(t.row.seeds) == 1:
                t.run_id = t.row.run_id
                continue
            tags = {"gdwm.kind": "trial", TRIAL_KEY: t.key, LAUNCH: self.launch_id, "gdwm.seed": str(t.seed)}
            tags |= self._row_tags(t.row) if self.sweep else {}
            if (run_id := found.get((TRIAL_KEY, t.key))) is not None:
                t.run_id = run_id
                reopened.append(RunWrite(run_id, tags=tags, reopen=True))
                continue
            name = f"{self.sweep.name}/{t.name}" if self.sweep else f"seed-{t.seed}"
            factors = factor_params(t.row) if self.sweep else {}
            params = config_params(t.cfg) | factors
            if (row_params := inherited.get(id(t.row))) is not None:
                params = own_params(params, row_params, keep=factors)
            new_trials.append((t, NewRun(name, tags | born, t.row.run_id, params)))
        for (t, _), run_id in zip(new_trials, tracking.create_runs([n for _, n in new_trials]), strict=True):
            t.run_id = run_id
            self.created.add(run_id)
        tracking.write(reopened)
        return parent

    def _earlier(self, tracking: TrackingClient) -> dict[tuple[str, str], str]:
        """``(ROW_KEY or TRIAL_KEY, key) -> run id`` of the runs earlier launches of this one made (the newest)."""
        out: dict[tuple[str, str], str] = {}
        for r in tracking.search_runs(f"tags.`{LAUNCH}` = '{self.launch_id}'", 10**9, ["attributes.start_time DESC"]):
            for tag in (ROW_KEY, TRIAL_KEY):
                if tag in r["tags"]:
                    out.setdefault((tag, r["tags"][tag]), r["run_id"])
            if r["tags"].get(DIGEST_TAG):
                self.recorded.add(r["run_id"])
        return out

    def _trim_rows(self, tracking: TrackingClient, parent: str, new_rows: list[tuple[Row, NewRun]]) -> None:
        """New rows' runs record what differs from the sweep's run (``PARAMS_BASE_TAG``; their factors always): a
        sweep run made now gets, once, the params every new row shares; one found again keeps its own (none: a sweep
        of gdwm before 2026-12-06, under which rows record their whole config). A row lacking one of the sweep run's
        keys records its whole config (an overlay can't remove a key). Three requests less a row to a team's server.
        """
        base = self._sweep_params
        if base is None:  # the sweep's run is new: what all its new rows share, on it
            first, *others = (n.params for _, n in new_rows)
            base = {k: v for k, v in first.items()
                    if not k.startswith(FACTOR_PARAM) and all(o.get(k) == v for o in others)}  # fmt: skip
            tracking.log_params(parent, base)
        if not base:
            return
        for row, new in new_rows:
            if base.keys() <= new.params.keys():
                new.params = own_params(new.params, base, keep=factor_params(row))
                new.tags = {**new.tags, PARAMS_BASE_TAG: parent}

    def _find(self, tracking: TrackingClient, tags: dict[str, str]) -> dict | None:
        found = tracking.search_runs(" and ".join(f"tags.`{k}` = '{v}'" for k, v in tags.items()))
        if not found:
            return None
        tracking.reopen_run(found[0]["run_id"])
        if found[0]["tags"].get(DIGEST_TAG):
            self.recorded.add(found[0]["run_id"])
        return found[0]

    def _parent(self, tracking: TrackingClient, cfg: DictConfig) -> str:
        """A re-run (a resume after a crash, an added row) continues the same run."""
        if self.sweep is not None:
            tags = {"gdwm.kind": "sweep", "gdwm.sweep": self.sweep.name}
            if (run := self._find(tracking, tags)) is not None:
                run_id, self._sweep_params = run["run_id"], dict(run["params"])
            else:
                run_id = tracking.create_run(f"sweep-{self.sweep.name}", tags)
            text = OmegaConf.to_yaml(OmegaConf.structured(self.sweep))
            tracking.log_text(run_id, text, "sweep.yaml")
            return run_id
        tags = {"gdwm.kind": "run", "gdwm.run_key": self.launch_id.removeprefix("run:")}
        if (run := self._find(tracking, tags)) is not None:
            return run["run_id"]
        tags |= {"gdwm.pipeline": self.pipeline}
        run_id = tracking.create_run(f"run-{self.pipeline}-{tags['gdwm.run_key'][:8]}", tags, None)
        self._parent_params = config_params(cfg)
        tracking.log_params(run_id, self._parent_params)
        return run_id

    def _row_tags(self, row: Row) -> dict[str, str]:
        tags = {"gdwm.row": row.label, "gdwm.trial_index": str(row.index), "gdwm.seeds": ",".join(map(str, row.seeds))}
        tags |= {f"gdwm.factor.{k}": v for k, v in row.factors.items()}
        return tags | ({"gdwm.sweep": self.sweep.name, "gdwm.overrides": " ".join(row.overrides)} if self.sweep else {})


FACTOR_PARAM = "factor."
"""A row's factors are params ``factor.<name>`` (MLflow's compare view plots params) and tags ``gdwm.factor.<name>``."""


def factor_params(row: Row) -> dict[str, str]:
    return {f"{FACTOR_PARAM}{k}": str(v) for k, v in row.factors.items()}


def config_params(cfg: DictConfig) -> dict[str, str]:
    """A config as a run's params: flattened, paths relative to the workdir (``gdwm.tracking.relative_paths``)."""
    return relative_paths(flatten_params(recorded(cfg)), cfg.workdir)


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


def evaluation_write(run_id: str, pipe: Pipeline, results: dict[str, StageResult]) -> RunWrite:
    """The evaluation stages' metrics, per-sample tables (``<stage>/*.parquet``) and how to rescore them (tags
    ``gdwm.samples.<stage>``, ``gdwm.scorer.<stage>``, ``gdwm.strata.<stage>``: what ``gdwm compare`` resamples)
    as one write to the trial's run; counts (``count/*``) are tags ``gdwm.count/<name>``, not metrics."""
    metrics = evaluation_metrics(pipe, results)
    w = RunWrite(run_id, metrics={k: v for k, v in metrics.items() if not k.startswith(COUNT)})
    # how many samples were answered or skipped: a fact about the run, not a score to sort or plot
    tags = {f"gdwm.{k}": f"{v:g}" for k, v in metrics.items() if k.startswith(COUNT)}
    for n, samples in evaluation_samples(pipe, results).items():
        tags |= samples.tags(n, f"{n}/{samples.path.name}")
    w.tags = tags
    w.files = [(str(table), name) for name, r in results.items() if pipe.stages[name].evaluation and r.path
               for table in sorted(Path(r.path).glob("*.parquet"))]  # fmt: skip
    return w


COUNT = "count/"
"""Evaluation values that are counts (``count/answered``): tags ``gdwm.count/<name>`` of the trial run, not metrics."""


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


def row_metrics(agg: Mapping[str, float]) -> dict[str, float]:
    """A row's aggregate as its run's metrics: the mean as ``<metric>``, the spread over seeds as ``<metric>/std``
    (beside ``<metric>/ci_low`` and ``<metric>/ci_high``, which ``gdwm compare`` logs); the count of seeds is a tag
    ``gdwm.n.<metric>``, not a metric."""
    out = {}
    for m, v in agg.items():
        if m.startswith("std/"):
            out[f"{m.removeprefix('std/')}/std"] = v
        elif not m.startswith("n/"):
            out[m] = v
    return out


def entry_keys(results: Mapping[str, StageResult]) -> dict[str, list[str]]:
    return {n: sorted({k for k, _ in r.scenes.values()}) if r.scenes else [r.key] for n, r in results.items()}


def planned_keys(t: Trial) -> dict[str, list[str]]:
    """Every entry a trial is about to read or publish (per scene where a stage fans out), from its plan."""
    out: dict[str, set[str]] = {}
    for r in t.plan:
        out.setdefault(r.stage, set()).add(r.key)
    return {n: sorted(keys) for n, keys in out.items()}


def code_records(trials: list[Trial]) -> dict[str, Mapping[str, Any]]:
    """Digest -> code fingerprint of each stage the trials' plans run (cached stages open no run)."""
    out: dict[str, Mapping[str, Any]] = {}
    for t in trials:
        code = t.settings.get("code", {})
        for r in t.plan:
            if r.status != "cached" and (fp := code.get(r.stage)) is not None:
                out[fp["digest"]] = fp
    return out


# ---- the driver loop -------------------------------------------------------------------------------------------
def _root_cause(e: BaseException) -> BaseException:
    while isinstance(e, ray.exceptions.RayTaskError) and e.cause is not None and e.cause is not e:
        e = e.cause
    return e


def _label(t: Trial) -> str:
    """A trial as progress names it: its row label (and seed), ``seed N`` for ``gdwm run``."""
    return t.name or f"seed {t.seed}"


def _trial_map(trials: list[Trial]) -> dict[str, list[tuple[str, str]]]:
    return {_label(t): [(n, t.keys[n]) for n in t.order] for t in trials}


def _executions(trials: list[Trial], priors: Mapping[str, Any]) -> list[Execution]:
    """Every distinct stage key of the launch with the trials it serves, its scenes and its expected duration."""
    out: dict[tuple[str, str], Execution] = {}
    for t in trials:
        for name in t.order:
            k = (name, t.keys[name])
            if k in out:
                out[k].trials.append(_label(t))
                continue
            sd = t.pipe.stages[name]
            rows = [r for r in t.plan if r.stage == name]
            todo = sum(r.status == "to run" for r in rows)
            per_task = priors.get(name)
            if not todo:
                estimate = 0.0
            elif per_task is None:
                estimate = None
            elif sd.per_scene:
                pool = int(t.env().resources.get(sd.resources, {}).get("num_workers", 1)) or 1
                estimate = math.ceil(todo / pool) * per_task.seconds
            else:
                estimate = per_task.seconds
            out[k] = Execution(name, k[1], [_label(t)], len(rows) if sd.per_scene else 0, estimate)
    return list(out.values())


def _priors(tracking: TrackingClient, trials: list[Trial]) -> dict[str, Any]:
    """Seconds per task of each stage from the store's finished stage runs (``gdwm.capacity.stage_durations``)."""
    from gdwm.capacity import stage_durations

    try:
        runs = tracking.search_runs("tags.`gdwm.kind` = 'stage' and attributes.status = 'FINISHED'", 5000)
    except Exception:  # an ETA is a nicety: a store that can't answer this must not stop the launch
        return {}
    t = trials[0]
    res = t.env().resources
    asks_gpu = {n: float(res.get(t.pipe.stages[n].resources, {}).get("num_gpus", 0)) > 0 for n in t.order}
    return stage_durations(runs, str(t.cfg.cluster.name), asks_gpu)


def _failure(root: BaseException, stage: str, running: list[str]) -> tuple[str, str]:
    """(one line naming stage, scene and error; the full traceback) of a stage task's error. ``running``: the scenes
    the stage had running, named when Ray's OOM killer ended the stage's coordinating task (it may pick that task
    over the actor that filled the node, one of those scenes)."""
    if isinstance(root, ray.exceptions.OutOfMemoryError):  # Ray's report is many lines; the cause fits in one
        where = f" scene(s) {running}" if running else ""
        return f"stage '{stage}'{where} failed: {oom_line(root)}", "".join(traceback.format_exception(root))
    if isinstance(root, StageFailed):
        text = "\n\n".join(f"== {s} ==\n{tb}" if s else tb for s, tb in root.errors.items())
        return str(root), text
    return f"stage '{stage}' failed: {one_line(root)}", "".join(traceback.format_exception(root))


def execute(
    trials: list[Trial],
    sink: Sink,
    parent: str,
    on_trial: Callable[[Trial, dict[str, Outcome]], Event | None],
    monitor: Monitor,
    *,
    stage_tags: dict[str, str] | None = None,
    code_recorded: frozenset[str] = frozenset(),
) -> int:
    """Submit every distinct stage key once, poll until every trial has an outcome per stage, hand each finished
    trial to ``on_trial``; returns how many stage executions ran (not cached). Every state change goes through
    ``monitor`` (the board, the log lines, the events file, the MLflow snapshot). ``code_recorded``: the code
    fingerprints ``parent`` holds (``code_records``), which stage runs point to instead of holding them."""
    submitted: dict[tuple[str, str], ray.ObjectRef] = {}
    upstream: dict[tuple[str, str], set[tuple[str, str]]] = {}
    for t in trials:
        # the cluster profile a stage ran on: `gdwm sweep --dry-run` estimates durations from that cluster's runs
        env = t.env(sink, parent, None, run_tags={"gdwm.cluster": str(t.cfg.cluster.name), **(stage_tags or {})},
                    code_recorded=code_recorded)  # fmt: skip
        refs: dict[str, ray.ObjectRef] = {}
        for name in t.order:
            sd = t.pipe.stages[name]
            k = (name, t.keys[name])
            upstream.setdefault(k, set()).update((u, t.keys[u]) for u in sd.upstream)
            if k not in submitted:
                fn = run_scene_stage if sd.per_scene else run_stage
                ups = [refs[u] for u in sd.upstream]
                mine = replace(env, progress=Reporter(monitor.actor, *k) if monitor.actor is not None else None)
                submitted[k] = fn.options(**task_options(sd, mine)).remote(sd, stage_config(sd, t.cfg), mine, *ups)
            refs[name] = submitted[k]
    order = {ref: i for i, ref in enumerate(submitted.values())}
    outcome: dict[tuple[str, str], Outcome] = {}
    pending = {ref: k for k, ref in submitted.items()}
    waiting = list(trials)
    executions = 0

    def finish(k: tuple[str, str], ref: ray.ObjectRef) -> None:
        nonlocal executions
        ex = monitor.lp.executions[k]
        try:
            res: StageResult | BaseException = ray.get(ref)
        except Exception as e:  # Ray re-raises a task's error as a subclass of both RayTaskError and it
            res = _root_cause(e)
        bad_up = [u for u in upstream[k] if u in outcome and not isinstance(outcome[u], StageResult)]
        if isinstance(res, StageResult):
            outcome[k] = res
            executions += not res.cached
            skipped = f"{len(res.failed)} scene(s) skipped" if res.failed else None
            took = ex.elapsed(time.time()) if not res.cached else None
            monitor.emit(Event("stage", "cached" if res.cached else "done", *k, trials=ex.trials, duration_s=took,
                               message=skipped))  # fmt: skip
        elif bad_up or (isinstance(res, StageFailed) and res.stage != k[0]):
            outcome[k] = None
            monitor.emit(Event("stage", "blocked", *k, trials=ex.trials, message=f"{bad_up[0][0] if bad_up else ''}"))
        else:
            running = sorted(sc for sc, state in ex.scenes.items() if state == "running")
            line, text = _failure(res, k[0], running)
            rel = monitor.traceback(*k, text)
            outcome[k] = f"{line}; traceback: {monitor.shown(rel)}"
            monitor.emit(Event("stage", "failed", *k, trials=ex.trials, duration_s=ex.elapsed(time.time()),
                               cause=outcome[k], traceback=rel))  # fmt: skip
            block_below(k)

    def block_below(k: tuple[str, str]) -> None:
        """Everything downstream of a failed execution is blocked now: Ray would fail each of them with the
        failure's own error as their results arrive, one by one."""
        todo = [d for d, ups in upstream.items() if k in ups]
        while todo:
            d = todo.pop(0)
            if d in outcome:
                continue
            outcome[d] = None
            monitor.emit(Event("stage", "blocked", *d, trials=monitor.lp.executions[d].trials, message=k[0]))
            todo += [x for x, ups in upstream.items() if d in ups]

    def poll() -> None:
        if _TERMINATED:
            raise SystemExit(128 + _TERMINATED[0])
        # Back as soon as one result is in (waiting for all, the last stage's end waited out the timeout), then
        # every result in by now: their events are handled upstream first.
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
        if ready and len(pending) > 1:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0)
        monitor.poll()  # the workers' events before the outcomes they precede
        blocked_before = {k for k, v in outcome.items() if v is None}
        for ref in sorted(ready, key=order.__getitem__):  # upstream first: a failure blocks what follows it
            k = pending.pop(ref)
            if k not in outcome:  # else already blocked by an upstream failure
                finish(k, ref)
        blocked = [monitor.lp.executions[k] for k, v in outcome.items() if v is None and k not in blocked_before]
        if blocked:
            failed = [e.stage for e in monitor.lp.executions.values() if e.state == "failed"]
            because = f"{', '.join(dict.fromkeys(failed)) or 'an upstream stage'} failed"
            if (line := monitor.lines.blocked(time.time(), blocked, because)) is not None:
                monitor.say(line)
        for t in [t for t in waiting if all((n, t.keys[n]) in outcome for n in t.order)]:
            waiting.remove(t)
            ev = on_trial(t, {n: outcome[(n, t.keys[n])] for n in t.order})
            if ev is not None:
                monitor.emit(ev)

    while pending or waiting:
        poll()
    monitor.poll()
    return executions


def launch(
    cfg: DictConfig,
    rows: list[Row],
    trials: list[Trial],
    layout: Layout,
    *,
    live: bool = False,
    verbosity: int = NORMAL,
) -> LaunchSummary:
    """Run planned trials under one driver session and record them as ``layout`` says."""
    summary = LaunchSummary(naive=sum(len(t.order) for t in trials))
    results: dict[int, TrialResult] = {}

    with _launch_lock(cfg, layout), driver_session(cfg, warm_modules(trials)) as tracking:
        with phase("environment record"):
            rec = launch_record(cfg)
        with phase("launch runs"):
            # new row and trial runs are created tagged with the environment they run in (gdwm.environment)
            parent = layout.open(tracking, cfg, rows, trials, lambda launch_run: record_tags(rec, launch_run))
            summary.parent_run_id = parent
        with phase("environment record"):
            # what `gdwm cache gc` keeps while each trial runs (its end replaces it with what it used, where that
            # differs), and the record on the launch's run, the runs found again tagged with it: one write
            planned = [RunWrite(t.run_id, texts={CACHE_KEYS: json.dumps(planned_keys(t), indent=1)}) for t in trials]
            # each code fingerprint a stage run is about to need, once on the launch's run (not on every stage run)
            code = code_records(trials)
            if code:
                planned.append(RunWrite(parent, texts={code_artifact(d): json.dumps(fp, indent=1, sort_keys=True)
                                                       for d, fp in code.items()}))  # fmt: skip
            log_launch(tracking, cfg, parent, trials, layout.recorded, planned, rec=rec, tagged=layout.created)
        # on the driver's node, as the tracking actor: a worker node lost mid-run must not take the board along
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        actor = ProgressActor.options(scheduling_strategy=here).remote()
        kind, name = ("sweep", layout.sweep.name) if layout.sweep else ("run", layout.pipeline)
        lp = LaunchProgress(kind, name, launch_id(kind, name), _trial_map(trials),
                            _executions(trials, _priors(tracking, trials)))  # fmt: skip
        monitor = Monitor(lp, Path(cfg.workdir).resolve(), str(cfg.workdir), actor=actor, tracking=tracking,
                          run_id=parent, verbosity=verbosity, live=live, heartbeat_s=float(cfg.run.heartbeat_s),
                          snapshot_s=float(cfg.run.snapshot_s))  # fmt: skip
        summary.monitor = monitor

        # a trial's and row's outcomes are written while the launch goes on; the launch waits for them at its end
        writes = WriteQueue(tracking.sink)
        row_trials: dict[int, list[Trial]] = {}
        for t in trials:
            row_trials.setdefault(id(t.row), []).append(t)

        def on_trial(t: Trial, outcomes: dict[str, Outcome]) -> Event:
            results[id(t)] = res = _finish_trial(writes, layout, t, outcomes)
            mine = row_trials[id(t.row)]
            if all(id(x) in results for x in mine):
                _finish_row(writes, layout, t.row, [results[id(x)] for x in mine])
            if res.ok:
                return Event("trial", "done", trials=[_label(t)], message=f"finished ({len(res.metrics)} metrics)")
            stage = next(iter(res.failed), res.blocked[0] if res.blocked else "")
            return Event("trial", "failed", trials=[_label(t)], message=f"failed at {stage}", stage=stage)

        try:
            with RunGuard(tracking.sink, parent), monitor:
                c = lp.counts()
                auth = "on" if os.environ.get(AUTH_MODE_ENV, "").lower() == "token" else "off"
                monitor.emit(Event("launch", "running", launch=lp.launch, total=c["executions"],
                                   message=f"{c['trials']} trial(s), {c['executions']} stage executions; "
                                   f"Ray token authentication {auth}"))  # fmt: skip
                tracking.set_tags(parent, {"gdwm.events": monitor.events_path})
                with phase("stages"):
                    summary.executions = execute(trials, tracking.sink, parent, on_trial, monitor,
                                                 stage_tags=layout.stage_tags,
                                                 code_recorded=frozenset(code))  # fmt: skip
                writes.flush()
                summary.trials = [results[id(t)] for t in trials]
                ok = summary.ok
                monitor.emit(Event("launch", "done" if ok else "failed", duration_s=lp.elapsed(),
                                   snapshot=lp.snapshot(monitor.events_path)))  # fmt: skip
                if layout.sweep is None:
                    tracking.set_tags(parent, {"gdwm.stages_run": str(summary.executions)})
                    if ok and verbosity > QUIET:
                        _print_run_summaries(summary, lp)
                    if not ok:  # the guard ends the run FAILED; the caller reports from the summary
                        bad = next(t for t in summary.trials if not t.ok)
                        stage = next(iter(bad.failed), bad.blocked[0] if bad.blocked else "")
                        raise StageFailed(stage, {None: bad.failed.get(stage, "blocked")})
                else:
                    tracking.set_tags(parent, {
                        "gdwm.trials": str(len(trials)),
                        "gdwm.trials_failed": str(sum(not t.ok for t in summary.trials)),
                        "gdwm.stage_executions": str(summary.executions),
                        "gdwm.stage_executions_naive": str(summary.naive),
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


def _finish_trial(writes: WriteQueue, layout: Layout, t: Trial, outcomes: dict[str, Outcome]) -> TrialResult:
    """Record one trial's outcome on its run, in one write: a failure (stage, error), or its evaluation and stage
    links; the zoo versions its stages registered get its lineage."""
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
        writes.put(RunWrite(t.run_id, tags={"gdwm.failed_stage": stage, "gdwm.error": msg}, texts={"error.txt": msg},
                            end="FAILED" if own_run else None))  # fmt: skip
        return res
    links = {f"gdwm.stage_run.{n}": r.run_id for n, r in res.results.items() if r.run_id}
    w = evaluation_write(t.run_id, t.pipe, res.results)
    w.tags = links | {f"gdwm.stage_key.{n}": r.key for n, r in res.results.items()} | dict(w.tags)
    used = entry_keys(res.results)
    if used != planned_keys(t):  # else the planned keys the launch wrote already say it
        w.texts = {CACHE_KEYS: json.dumps(used, indent=1)}
    res.metrics = evaluation_metrics(t.pipe, res.results)
    if layout.sweep is not None:
        # the zoo versions this trial's stages registered carry its sweep, trial and key metrics
        lineage = {"gdwm.sweep": layout.sweep.name, "gdwm.trial": t.run_id, "gdwm.row": t.label}
        w.version_tags = lineage | metric_tags({k: v for k, v in res.metrics.items() if not k.startswith("count/")})
        w.versions_of = sorted({r.run_id for r in res.results.values() if r.run_id and r.registered is not False})
    w.end = "FINISHED" if own_run and not res.blocked else None
    writes.put(w)
    return res


def _finish_row(writes: WriteQueue, layout: Layout, row: Row, results: list[TrialResult]) -> None:
    """A row's aggregate over its finished seeds, on the row's run (when it is not its only trial's run)."""
    if all(r.trial.run_id == row.run_id for r in results):
        return
    agg = aggregate([r.metrics for r in results if r.ok])
    w = RunWrite(row.run_id)
    if agg:
        w.metrics = row_metrics(agg)
        w.tags = {f"gdwm.n.{m.removeprefix('n/')}": f"{v:g}" for m, v in agg.items() if m.startswith("n/")}
    if layout.sweep is not None:
        w.end = "FINISHED" if any(r.ok for r in results) else "FAILED"
    writes.put(w)


# ---- gdwm run ----------------------------------------------------------------------------------------------------
def run_pipeline(
    cfg: DictConfig,
    overrides: list[str] | None = None,
    *,
    seeds: list[int] | None = None,
    seeds_key: str = "seeds",
    dry_run: bool = False,
    live: bool | None = None,
    verbosity: int = NORMAL,
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
    with phase("plan"):
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
    return launch(cfg, [row], trials, layout, live=show, verbosity=verbosity)


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


def _print_run_summaries(summary: LaunchSummary, lp: LaunchProgress) -> None:
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
            ex = lp.executions.get((name, res.trial.keys.get(name, "")))
            wall = ex.elapsed(lp.clock()) if ex is not None and not (r is not None and r.cached) else None
            key = r.key[:12] if r else res.trial.keys.get(name, "")[:12]
            t.add_row(name, status, f"{wall:.1f}" if wall is not None else "", key, (r.run_id or "") if r else "")
        console.print(t)
