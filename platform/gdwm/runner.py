"""``gdwm run``: validate, plan, execute the DAG on Ray, track it in MLflow, summarise."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import ray
from omegaconf import DictConfig, OmegaConf
from rich.live import Live
from rich.table import Table

from gdwm.cache import Cache
from gdwm.dag import Pipeline, load_pipeline
from gdwm.datasets import build_dataset
from gdwm.executor import (
    RunEnv,
    StageFailed,
    StageResult,
    aggregate_key,
    run_scene_stage,
    run_stage,
    stage_key,
    task_options,
    upstream_keys,
)
from gdwm.progress import ProgressActor, render
from gdwm.term import console
from gdwm.tracking import AliveExcept, RunGuard, call, open_tracking, process_owner
from gdwm.zoo.registry import pin_references


class RunError(Exception):
    """A run that could not start (exit 1), e.g. a dataset that is absent and cannot be generated."""


@dataclass
class PlanRow:
    stage: str
    scene: str | None
    key: str
    status: str  # cached | to run | blocked
    resources: str


@dataclass
class RunSummary:
    results: dict[str, StageResult] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    blocked: list[str] = field(default_factory=list)
    parent_run_id: str | None = None
    wall: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.failed and not self.blocked


def subset(cfg: DictConfig, keys: tuple[str, ...]) -> dict:
    return {k: OmegaConf.to_container(OmegaConf.select(cfg, k), resolve=True) for k in keys}


def read_dataset_meta(root: Path) -> dict:
    meta = root / "dataset.json"
    if not meta.is_file():
        raise RunError(f"dataset at {root} is absent or incomplete (no dataset.json)")
    return json.loads(meta.read_text())


def ensure_data(cfg: DictConfig) -> dict:
    """The dataset's meta; a dataset that needs no source (synthetic) is generated first if absent."""
    root = Path(cfg.data.root)
    if not (root / "dataset.json").is_file():
        if cfg.source is None and not cfg.data.needs_source:
            console.print(f"generating {cfg.data.name} at {root} ...")
            build_dataset(cfg, source=None)
        else:
            raise RunError(
                f"dataset '{cfg.data.name}' not found at {root}: build it first "
                f"(gdwm data import-gaussiandwm / convert-nuscenes source=DIR data={cfg.data.name})"
            )
    return read_dataset_meta(root)


def env_settings(cfg: DictConfig, meta: dict) -> dict:
    """RunEnv fields of a composed config (all but the tracking sink, parent run and progress actor)."""
    res = {k: dict(v) for k, v in OmegaConf.to_container(cfg.cluster.resources, resolve=True).items()}
    return dict(
        cache_uri=cfg.cache.uri,
        data_root=str(Path(cfg.data.root).resolve()),
        data_fingerprint=meta["fingerprint"],
        scenes=tuple(meta["scenes"]),
        checkpoint_root=str(Path(cfg.workdir).resolve() / "checkpoints"),
        resources=res,
        on_scene_error=cfg.run.on_scene_error,
        max_retries=cfg.run.max_retries,
        seed=cfg.seed,
        train_settings={"checkpoint_every": cfg.run.checkpoint_every, "max_failures": cfg.run.max_failures},
        tracking_uri=cfg.tracking.uri,
    )


def _plan_result(sd, sub, env: RunEnv, ups: tuple[StageResult, ...], cache: Cache, rows: list[PlanRow]) -> StageResult:
    """Predict one stage's keys and cache status, assuming every upstream scene succeeds."""
    if sd.per_scene:
        keys = {s: stage_key(sd, sub, upstream_keys(ups, s), env, scene=s) for s in env.scenes}
        for s, k in keys.items():
            hit = cache.lookup(sd.name, k, verify=False) is not None
            rows.append(PlanRow(sd.name, s, k, "cached" if hit else "to run", sd.resources))
        return StageResult(
            sd.name, aggregate_key(sd, sub, keys, env), False, None, scenes={s: (k, "") for s, k in keys.items()}
        )
    key = stage_key(sd, sub, upstream_keys(ups, None), env)
    hit = cache.lookup(sd.name, key, verify=False) is not None
    rows.append(PlanRow(sd.name, None, key, "cached" if hit else "to run", sd.resources))
    return StageResult(sd.name, key, hit, None)


def plan(pipe: Pipeline, order: list[str], cfg: DictConfig, env: RunEnv) -> list[PlanRow]:
    """Keys depend on upstream keys, not outputs, so the whole DAG's keys are known before anything runs."""
    return plan_keys(pipe, order, cfg, env)[0]


def plan_keys(pipe: Pipeline, order: list[str], cfg: DictConfig, env: RunEnv) -> tuple[list[PlanRow], dict[str, str]]:
    """``plan``'s rows, and each stage's key as its downstream sees it (per-scene stages: the aggregate key)."""
    cache = Cache(env.cache_uri)
    rows: list[PlanRow] = []
    predicted: dict[str, StageResult] = {}
    for name in order:
        sd = pipe.stages[name]
        ups = tuple(predicted[u] for u in sd.upstream)
        predicted[name] = _plan_result(sd, subset(cfg, sd.config), env, ups, cache, rows)
    return rows, {name: r.key for name, r in predicted.items()}


def print_plan(rows: list[PlanRow], env: RunEnv) -> None:
    t = Table(title="plan", header_style="bold")
    for col in ("stage", "scene", "status", "key", "resources"):
        t.add_column(col)
    for r in rows:
        res = env.resources.get(r.resources, {})
        cpus, gpus, n = res.get("num_cpus", 0), res.get("num_gpus", 0), res.get("num_workers", 1)
        desc = f"{r.resources}: {cpus:g} CPU, {gpus:g} GPU, " + (f"x{n}" if n else "in-process")
        t.add_row(r.stage, r.scene or "-", r.status, r.key[:12], desc)
    console.print(t)
    counts = {s: sum(1 for r in rows if r.status == s) for s in ("cached", "to run")}
    console.print(", ".join(f"{n} {s}" for s, n in counts.items()))


def _verify_all(rows: list[PlanRow], env_cache: Cache) -> bool:
    return all(env_cache.lookup(r.stage, r.key, verify=True) is not None for r in rows)


def init_ray(cfg: DictConfig) -> bool:
    """Start (or join) Ray as the cluster config says; True if this call started it."""
    if ray.is_initialized():
        return False
    c = cfg.cluster
    kwargs = {"include_dashboard": False, "log_to_driver": cfg.run.worker_logs}
    if c.address:
        # A cluster's workers run the installed wheel (k8s/Dockerfile); the driver's paths mean nothing there.
        ray.init(address=c.address, **kwargs)
    else:
        # Local workers import the stage modules from wherever the driver does.
        env_vars = {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        ray.init(num_cpus=c.num_cpus, num_gpus=c.num_gpus, runtime_env={"env_vars": env_vars}, **kwargs)
    if threading.current_thread() is threading.main_thread():
        # ray.init's own SIGTERM handler exits 1; exit 143 as a terminated process should (finally shuts Ray).
        signal.signal(signal.SIGTERM, _sigterm)
    return True


_TERMINATED: list[int] = []


def _sigterm(signum: int, _frame) -> None:
    # Raising here would surface inside ray.wait, which turns any exception into SystemExit(1): record it and
    # let the poll loop exit 143 between waits.
    _TERMINATED.append(signum)


def _run_key(pipe_name: str, order: list[str], rows: list[PlanRow]) -> str:
    h = hashlib.sha256(json.dumps([pipe_name, order, [r.key for r in rows]]).encode())
    return h.hexdigest()


def _cached_results(rows: list[PlanRow], cache: Cache) -> dict[str, StageResult]:
    """Every stage's entry (local directory, per scene where it fans out) when the whole plan is cached."""
    out: dict[str, StageResult] = {}
    for r in rows:
        m = cache.lookup(r.stage, r.key, verify=False)
        path = str(cache.materialize(m))
        if r.scene is None:
            out[r.stage] = StageResult(r.stage, r.key, True, m.run_id, path=path, extra=dict(m.extra))
        else:
            res = out.setdefault(r.stage, StageResult(r.stage, "", True, None, scenes={}))
            res.scenes[r.scene] = (r.key, path)  # type: ignore[index]
    return out


def run_pipeline(cfg: DictConfig, dry_run: bool = False, live: bool | None = None) -> RunSummary:
    pipe = load_pipeline(cfg, list(cfg.targets) or None)
    order = pipe.ancestors(list(cfg.targets)) if cfg.targets else list(pipe.order)
    # zoo:NAME@ALIAS -> zoo:NAME/VERSION in what the stages to run read: their keys name exact versions
    cfg = pin_references(cfg, cfg.tracking.uri, [k for name in order for k in pipe.stages[name].config])
    base_env = env_settings(cfg, ensure_data(cfg))
    rows = plan(pipe, order, cfg, RunEnv(sink=None, parent_run_id=None, progress=None, **base_env))
    if dry_run or cfg.run.plan:
        print_plan(rows, RunEnv(sink=None, parent_run_id=None, progress=None, **base_env))
        return RunSummary()
    if all(r.status == "cached" for r in rows) and _verify_all(rows, env_cache=Cache(cfg.cache.uri)):
        # Nothing to run: no Ray, no tracking; a no-op re-run costs only the hash checks.
        console.print(f"all {len(rows)} stage outputs cached and verified; nothing to run")
        return RunSummary(results=_cached_results(rows, Cache(cfg.cache.uri)))
    summary = RunSummary()
    with driver_session(cfg) as sink:
        try:
            run_key = _run_key(pipe.name, order, rows)
            parent = _parent_run(sink, cfg, pipe, run_key)
            summary.parent_run_id = parent
            progress = ProgressActor.remote()
            env = RunEnv(sink=sink, parent_run_id=parent, progress=progress, **base_env)
            with RunGuard(sink, parent):
                _execute_dag(pipe, order, cfg, env, summary, progress, live)
                n_run = sum(not r.cached for r in summary.results.values())
                call(sink, "log_metrics", parent, {"stages_run": n_run})
                report_evaluation(sink, parent, pipe, summary.results)
                if summary.failed:
                    raise StageFailed(next(iter(summary.failed)), {None: next(iter(summary.failed.values()))})
        except StageFailed:
            pass  # the parent run is FAILED by the guard; the caller reports from the summary
    return summary


@contextlib.contextmanager
def driver_session(cfg: DictConfig) -> Iterator:
    """Ray (started here unless already up) and the tracking sink of one driver invocation (``gdwm run``, ``gdwm
    sweep``); runs that dead drivers left RUNNING are reconciled first. Whatever escapes (Ctrl-C, SIGTERM, an error)
    ends the runs this driver owns KILLED now, not at the next reconcile."""
    started = init_ray(cfg)
    sink, close = open_tracking(cfg.tracking)
    try:
        call(sink, "reconcile")
        yield sink
    except BaseException:
        call(sink, "reconcile", AliveExcept(process_owner()))
        raise
    finally:
        close()
        if started:
            ray.shutdown()


def report_evaluation(sink, run_id: str, pipe: Pipeline, results: dict[str, StageResult]) -> dict[str, float]:
    """The evaluation stages' metrics and per-sample tables onto the trial's run; returns the metrics."""
    metrics = evaluation_metrics(pipe, results)
    if metrics:
        call(sink, "log_metrics", run_id, metrics)
    log_evaluation_tables(sink, run_id, pipe, results)
    return metrics


def evaluation_metrics(pipe: Pipeline, results: dict[str, StageResult]) -> dict[str, float]:
    """The numeric values evaluation stages returned (cached or not): the metrics of the trial's run."""
    out: dict[str, float] = {}
    for name, r in results.items():
        if pipe.stages[name].evaluation:
            out |= {k: float(v) for k, v in r.extra.items() if isinstance(v, int | float) and not isinstance(v, bool)}
    return out


def log_evaluation_tables(sink, run_id: str, pipe: Pipeline, results: dict[str, StageResult]) -> None:
    """The evaluation stages' per-sample tables (``*.parquet``) as artifacts of the trial's run, ``<stage>/``."""
    for name, r in results.items():
        if pipe.stages[name].evaluation and r.path:
            for table in sorted(Path(r.path).glob("*.parquet")):
                call(sink, "log_artifact", run_id, str(table), name)


def _parent_run(sink, cfg: DictConfig, pipe: Pipeline, run_key: str) -> str:
    """Re-running the same command continues the same parent run."""
    found = call(sink, "search_runs", f"tags.`gdwm.run_key` = '{run_key}'")
    if found:
        call(sink, "reopen_run", found[0]["run_id"])
        return found[0]["run_id"]
    tags = {"gdwm.kind": "run", "gdwm.run_key": run_key, "gdwm.pipeline": pipe.name}
    run_id = call(sink, "create_run", f"run-{pipe.name}-{run_key[:8]}", tags, None)
    call(sink, "log_params", run_id, OmegaConf.to_container(cfg, resolve=True))
    return run_id


def _execute_dag(pipe, order, cfg, env: RunEnv, summary: RunSummary, progress, live: bool | None) -> None:
    refs: dict[str, ray.ObjectRef] = {}
    t0 = time.time()
    for name in order:
        sd = pipe.stages[name]
        fn = run_scene_stage if sd.per_scene else run_stage
        ups = [refs[u] for u in sd.upstream]
        refs[name] = fn.options(**task_options(sd, env)).remote(sd, subset(cfg, sd.config), env, *ups)
    pending = {ref: name for name, ref in refs.items()}
    show_live = cfg.run.live if live is None else live
    show_live = show_live and console.is_terminal

    def poll() -> None:
        if _TERMINATED:
            raise SystemExit(128 + _TERMINATED[0])
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.5)
        for ref in ready:
            name = pending.pop(ref)
            summary.wall[name] = time.time() - t0
            try:
                summary.results[name] = ray.get(ref)
            except Exception as e:  # Ray re-raises a task's error as a subclass of both RayTaskError and it
                root = _root_cause(e)
                if isinstance(root, StageFailed) and root.stage != name:
                    summary.blocked.append(name)
                    env.progress.status.remote(name, None, "blocked", message=f"upstream {root.stage} failed")
                elif isinstance(root, StageFailed):
                    summary.failed[name] = StageFailed.__str__(root)
                else:
                    summary.failed[name] = f"stage '{name}' failed: {root!r}"

    if show_live:
        with Live(render([], order), console=console, refresh_per_second=4) as view:
            while pending:
                poll()
                view.update(render(ray.get(progress.snapshot.remote()), order))
    else:
        while pending:
            poll()
    print_summary(summary, order, ray.get(progress.snapshot.remote()))


def _root_cause(e: BaseException) -> BaseException:
    while isinstance(e, ray.exceptions.RayTaskError) and e.cause is not None and e.cause is not e:
        e = e.cause
    return e


def print_summary(summary: RunSummary, order: list[str], items) -> None:
    t = Table(title="run summary", header_style="bold")
    for col in ("stage", "status", "wall s", "cache key", "MLflow run"):
        t.add_column(col)
    heads = {i.stage: i for i in items if i.scene is None}
    for name in order:
        r = summary.results.get(name)
        if r is not None:
            status = "cached" if r.cached else "done"
            if r.failed:
                status += f" ({len(r.failed)} scene(s) skipped)"
        elif name in summary.failed:
            status = "failed"
        else:
            status = "blocked"
        wall = heads[name].wall if name in heads and heads[name].wall is not None else None
        key = r.key[:12] if r else (heads[name].key[:12] if name in heads else "")
        run_id = (r.run_id or "") if r else (heads[name].run_id if name in heads else "")
        t.add_row(name, status, f"{wall:.1f}" if wall is not None else "", key, run_id)
    console.print(t)
    for msg in summary.failed.values():
        console.print(f"[red]{msg}[/red]", markup=True)
