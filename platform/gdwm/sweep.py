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
from gdwm.term import console

SweepError = PlanError
"""A sweep that cannot launch (exit 2): the message names the sweep, the row and the key."""


def user_overrides(argv: list[str]) -> list[str]:
    """The command line's overrides that apply to every trial (not the sweep choice, not flags)."""
    return [a for a in argv if not a.startswith("--") and a.split("=", 1)[0].lstrip("+~") != "sweep"]


def load_sweep(cfg: DictConfig) -> SweepConfig:
    if cfg.get("sweep") is None:
        from gdwm.config import group_options

        raise SweepError(f"no sweep selected: pass sweep=NAME (one of {', '.join(group_options('sweep'))})")
    return OmegaConf.to_object(cfg.sweep)


def plan_sweep(cfg: DictConfig, argv: list[str], dry_run: bool = False) -> tuple[SweepConfig, list, list[Trial]]:
    """The sweep's rows and trials, composed and planned; a bad row, key or seed raises ``SweepError``."""
    sweep = load_sweep(cfg)
    seeds = resolve_seeds(cfg, sweep.seeds, "sweep.seeds")
    given = cfg.get("seeds") is not None or sweep.seeds is not None
    where = f"sweep '{sweep.name}'"
    check_grid_seeds(sweep, given)
    check_seed_overrides(given, where, user_overrides(argv), "command-line override")
    check_seed_overrides(given, where, sweep.overrides, "sweep override")
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
        print_sweep_plan(sweep, trials, _durations(cfg))
        return LaunchSummary(naive=sum(len(t.order) for t in trials))
    layout = Layout(sweep, f"sweep:{sweep.name}", trials[0].pipe.name)
    return launch(cfg, rows, trials, layout)


def _durations(cfg: DictConfig) -> dict[str, float]:
    """Median wall seconds of finished stage runs per stage in the store (the dry run's estimate); {} if none."""
    uri = cfg.tracking.uri
    if (db := sqlite_path(uri)) is not None and not Path(db).is_file():
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

    extra = [a for a in user_overrides(argv) if a.split("=", 1)[0].split(".")[0] in ("workdir", "tracking", "ui")]
    base = ["args=compare", f"compare={sweep.layout}", f"args.sweep={sweep.name}"]
    if sweep.baseline:
        base.append(f"args.baseline={sweep.baseline}")
    return compare(load_config([*base, *extra]))
