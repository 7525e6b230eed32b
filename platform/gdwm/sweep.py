"""``gdwm sweep sweep=NAME``: an ablation table as trials over one union DAG.

A sweep (``conf/sweep/NAME.yaml``) lists ``rows`` (label, the factor values the table shows, the overrides they
mean), a ``grid`` (override key -> values, crossed with every row) and ``seeds`` (``seeds=[...]`` on the command line
overrides them): one trial per (row, grid point, seed). Every trial is composed and planned before anything runs
(``gdwm.plan``), then the one driver (``gdwm.runner``) runs each distinct stage key once; the comparison report
(``gdwm compare``) closes the sweep.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from rich.table import Table

from gdwm.config import SweepConfig, load_config, sqlite_path
from gdwm.names import check_name
from gdwm.plan import (
    PlanError,
    Trial,
    check_grid_seeds,
    check_seed_overrides,
    compose,
    expand,
    print_reasons,
    resolve_seeds,
)
from gdwm.runner import LaunchSummary, Layout, launch
from gdwm.term import console, verbosity

SweepError = PlanError
"""A sweep that cannot launch (exit 2): the message names the sweep, the row and the key."""


def user_overrides(argv: list[str]) -> list[str]:
    """The command line's overrides that apply to every trial (not the sweep choice or its keys, not flags)."""
    keys = (a.split("=", 1)[0].lstrip("+~") for a in argv)
    return [a for a, k in zip(argv, keys, strict=True) if not a.startswith("--") and k.split(".")[0] != "sweep"]


def load_sweep(cfg: DictConfig) -> SweepConfig:
    if cfg.get("sweep") is None:
        from gdwm.config import group_options

        raise SweepError(f"no sweep selected: pass sweep=NAME (one of {', '.join(group_options('sweep'))})")
    return OmegaConf.to_object(cfg.sweep)


def plan_sweep(cfg: DictConfig, argv: list[str], dry_run: bool = False) -> tuple[SweepConfig, list, list[Trial]]:
    """The sweep's rows and trials, composed and planned; a bad row, key or seed raises ``SweepError``."""
    sweep = load_sweep(cfg)
    try:  # they become paths (the report's folder) and run names: a shared sweep file must not point elsewhere
        check_name(sweep.name, "sweep.name")
        for i, row in enumerate(sweep.rows):
            check_name(row.label, f"sweep.rows[{i}].label")
    except ValueError as e:
        raise SweepError(str(e)) from None
    seeds = resolve_seeds(cfg, sweep.seeds, "sweep.seeds")
    given = cfg.get("seeds") is not None or sweep.seeds is not None
    where = f"sweep '{sweep.name}'"
    check_grid_seeds(sweep, given)
    check_seed_overrides(given, where, user_overrides(argv), "command-line override")
    check_seed_overrides(given, where, sweep.overrides, "sweep override")
    if sweep.only:
        labels = [r.label for r in sweep.rows]
        if unknown := [x for x in sweep.only if x not in labels]:
            raise SweepError(f"{where}: sweep.only names no row {unknown} (rows: {labels})")
        sweep.rows = [r for r in sweep.rows if r.label in sweep.only]
    for row in sweep.rows:
        check_seed_overrides(given, f"{where} row '{row.label}'", row.overrides)
    rows = expand(sweep, seeds)
    trials = [Trial(r, s) for r in rows for s in r.seeds]
    base = ([f"targets=[{','.join(sweep.targets)}]"] if sweep.targets else []) + list(sweep.overrides)
    compose(trials, [*base, *user_overrides(argv)], where, name_rows=True, dry_run=dry_run)
    check_distinct_rows(where, trials)
    return sweep, rows, trials


def check_distinct_rows(where: str, trials: list[Trial]) -> None:
    """Two rows whose trials resolve to the same stage keys are one model under two labels (a copy-paste row):
    its numbers would be printed twice, as if they were two results."""
    seen: dict[tuple, Trial] = {}
    for t in trials:
        first = seen.setdefault((t.seed, tuple(sorted(t.keys.items()))), t)
        if first.row is not t.row:
            raise SweepError(f"{where}: rows '{first.label}' and '{t.label}' resolve to the same stage keys (one "
                             "model under two labels); make their overrides differ or drop one")  # fmt: skip


def run_sweep(cfg: DictConfig, argv: list[str], dry_run: bool = False) -> LaunchSummary:
    sweep, rows, trials = plan_sweep(cfg, argv, dry_run)
    if dry_run:
        runs = _stage_runs(cfg)
        print_sweep_plan(sweep, trials, _durations(runs))
        print_capacity_plan(cfg, trials, runs, durations_file(argv))
        return LaunchSummary(naive=sum(len(t.order) for t in trials))
    layout = Layout(sweep, f"sweep:{sweep.name}", trials[0].pipe.name)
    return launch(cfg, rows, trials, layout, live=bool(cfg.run.live), verbosity=verbosity(argv))


def _stage_runs(cfg: DictConfig) -> list[dict]:
    """Finished stage runs of the store (their times and tags); [] when there is no store yet."""
    uri = cfg.tracking.uri
    if (db := sqlite_path(uri)) is not None and not Path(db).is_file():
        return []
    from gdwm.tracking import TrackingBackend

    backend = TrackingBackend(uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    return backend.search_runs("tags.`gdwm.kind` = 'stage' and attributes.status = 'FINISHED'", 5000)


def durations_file(argv: list[str]) -> Path | None:
    """``--durations=FILE`` (JSON: stage -> wall seconds of one task, measured elsewhere)."""
    given = [a.split("=", 1)[1] for a in argv if a.startswith("--durations=")]
    return Path(given[-1]) if given else None


def print_capacity_plan(cfg: DictConfig, trials: list[Trial], runs: list[dict], durations: Path | None) -> None:
    """Per stage: resource shape, tasks (scenes or executions) to run, how many at once on the cluster, estimated
    wall time and GPU-hours (``gdwm.capacity``), then the model the estimate rests on."""
    import json

    from gdwm.capacity import GPU_SPEEDUP, Duration, cluster_nodes, describe, plan_capacity, stage_durations

    resources = OmegaConf.to_container(cfg.cluster.resources, resolve=True)
    cluster, nodes = str(cfg.cluster.name), cluster_nodes(cfg.cluster)
    stages: dict[str, tuple[str, bool, int]] = {}
    todo: dict[str, set] = {}
    for t in trials:
        for name in t.order:
            sd = t.pipe.stages[name]
            rows = [r for r in t.plan if r.stage == name and r.status == "to run"]
            todo.setdefault(name, set()).update((t.keys[name], r.scene) for r in rows)
            stages[name] = (sd.resources, sd.per_scene, 0)
    stages = {n: (c, ps, len(todo[n])) for n, (c, ps, _) in stages.items()}
    asks_gpu = {n: float(resources.get(c, {}).get("num_gpus", 0)) > 0 for n, (c, _, _) in stages.items()}
    if durations is not None:
        try:
            measured = {str(k): Duration(float(v), f"file {durations.name}") for k, v in
                        json.loads(durations.read_text()).items()}  # fmt: skip
        except (OSError, ValueError, AttributeError) as e:
            raise SweepError(f"--durations={durations}: not a JSON object of stage -> seconds per task ({e})") from e
    else:
        measured = stage_durations(runs, cluster, asks_gpu)
    plans = plan_capacity(stages, resources, nodes, measured)
    table = Table(title=f"capacity plan on cluster '{cluster}' ({describe(nodes) or 'nodes unknown'})",
                  header_style="bold")  # fmt: skip
    for col in ("stage", "shape", "tasks", "at once", "est. wall", "GPU-h", "duration from"):
        table.add_column(col, justify="left" if col in ("stage", "shape", "duration from") else "right")
    for p in plans:
        wall = "?" if p.seconds is None else f"{p.seconds:.0f} s" if p.seconds < 120 else f"{p.seconds / 60:.1f} min"
        gpu_h = "?" if p.gpu_hours is None else f"{p.gpu_hours:.2f}"
        table.add_row(p.stage, p.shape, str(p.tasks), str(p.at_once), wall, gpu_h, p.source)
    console.print(table)
    known = [p for p in plans if p.seconds is not None]
    total = sum(p.seconds for p in known) / 3600
    gpu_h = sum(p.gpu_hours for p in known)
    unknown = [p.stage for p in plans if p.seconds is None]
    console.print(
        f"estimate: {total:.2f} h of wall time if the stages ran one after another (an upper bound: independent "
        f"stages overlap), {gpu_h:.2f} GPU-hours" + (f"; no duration for {', '.join(unknown)}" if unknown else ""),
        markup=False,
    )
    console.print(
        f"model: a task's seconds are the median of earlier finished runs of the stage on '{cluster}' (tag "
        "gdwm.cluster); without any, of runs on other clusters, per scene for per-scene stages, divided by "
        f"{GPU_SPEEDUP:g} (gdwm.capacity.GPU_SPEEDUP, an assumption) where the stage asks for a GPU here; "
        "--durations=FILE replaces both. Tasks run in waves of 'at once'; GPU-hours = tasks x seconds x workers x "
        "GPUs per worker.",
        markup=False,
    )


def _durations(runs: list[dict]) -> dict[str, float]:
    """Median wall seconds of finished stage runs per stage in the store (the dry run's estimate); {} if none."""
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
            rows = [r for r in t.plan if r.stage == s]
            cached = all(r.status == "cached" for r in rows)
            state = "cached" if cached else "shared" if k in claimed else "to run"
            old = cached and any(r.shown != "cached" for r in rows)  # reused from other or unknown code
            if state == "to run":
                seconds += durations.get(s, float("nan"))
            claimed.add(k)
            counts[state] += 1
            shown = {"cached": "[dim]cached[/dim]", "shared": "[cyan]shared[/cyan]", "to run": "run"}[state]
            cells.append("[yellow]cached (old code)[/yellow]" if old else shown)
        table.add_row(t.name, *cells)
    for note in dict.fromkeys(t.pending_data for t in trials if t.pending_data):
        console.print(f"{note}: nothing is generated by a dry run, so every stage is to run", markup=False)
    console.print(table)
    est = f"~{seconds / 60:.0f} min of stage time (medians of earlier runs)" if seconds == seconds else (
        "no duration estimate (no earlier runs of some stages in this store)")  # fmt: skip
    console.print(f"{counts['to run']} stage executions to run, {counts['shared']} shared, {counts['cached']} "
                  f"cached; {est}")  # fmt: skip
    print_reasons(trials)
    return counts


def report(cfg: DictConfig, sweep: SweepConfig, argv: list[str]) -> int:
    """The comparison report of the sweep (``gdwm compare``) into workdir/reports/<name> and the sweep run."""
    from gdwm.compare.command import compare

    extra = [
        a for a in user_overrides(argv) if a.split("=", 1)[0].split(".")[0] in ("workdir", "tracking", "ui", "compare")
    ]
    # a layout on the command line (the same sweep on another benchmark's data) wins over the sweep's own
    given = any(a.split("=", 1)[0] == "compare" for a in extra)
    layout = [f"compare={sweep.layout}"] if sweep.layout and not given else []
    base = ["args=compare", *layout, f"args.sweep={sweep.name}"]
    if sweep.baseline:
        base.append(f"args.baseline={sweep.baseline}")
    return compare(load_config([*base, *extra]))
