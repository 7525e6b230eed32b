"""``gdwm compare``: select runs (and read ``compare.references``' reported rows), print the table, write the chosen
formats, log them to the sweep's parent run. A references file alone, without a store or selector, makes a table of
reported rows. Exit 2 for a bad references file (naming file, line and field), 1 for a selection that fails."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from rich.measure import Measurement

from gdwm.board import resampling_progress
from gdwm.compare.layout import CompareArgs, Direction, Format, LayoutConfig
from gdwm.compare.references import Reference, ReferencesError, load_references, log_references, merge
from gdwm.compare.render import to_csv, to_latex, to_markdown, to_rich
from gdwm.compare.rounding import fmt as fmt_value
from gdwm.compare.runs import Selection, SelectionError, linked_runs, select, training_curves
from gdwm.compare.samples import load_samples
from gdwm.compare.stats import Settings
from gdwm.compare.table import Table, build_table
from gdwm.config import sqlite_path, ui_url
from gdwm.environment.runs import environment_note
from gdwm.errors import CommandError
from gdwm.names import check_name
from gdwm.owned import NotOurs, own_report_dir
from gdwm.term import RedactingConsole, console, err_console
from gdwm.tracking import TrackingBackend

METHODS = ("BCa", "percentile", "basic")
"""``scipy.stats.bootstrap`` methods."""
SUFFIX = {Format.markdown: "md", Format.latex: "tex", Format.csv: "csv", Format.html: "html"}


def settings(args: CompareArgs) -> Settings:
    """The statistics' settings from ``args``; a value out of range is named as the user would set it."""
    for name in ("alpha", "confidence"):
        value = getattr(args, name)
        if not 0 < value < 1:
            raise ValueError(f"args.{name}={value}: must lie strictly between 0 and 1")
    if args.resamples < 2:
        raise ValueError(f"args.resamples={args.resamples}: the bootstrap needs at least 2 resamples")
    if args.bootstrap_method not in METHODS:
        raise ValueError(f"args.bootstrap_method={args.bootstrap_method}: must be one of {', '.join(METHODS)}")
    return Settings(
        args.alpha, args.confidence, args.resamples, args.stats_seed, args.bootstrap_method, args.correction
    )


@dataclass
class Comparison:
    """What ``gdwm compare`` shows: the selection, its table, the row the deltas are taken against and the reported
    rows (``compare.references``) it holds."""

    selection: Selection
    table: Table
    base: int
    references: list[Reference]


def comparison(cfg: DictConfig, backend: TrackingBackend | None, warn: Callable[[str], None]) -> Comparison:
    """Select the rows ``cfg.args`` names, read their samples, add ``compare.references``' reported rows and build
    the table: the one way every surface gets it (this command, the dashboard's sweep page). Reads the store (None:
    there is none, and only a references file makes the table), writes nothing; ``warn`` gets each warning. A bad
    references file is a ``ReferencesError`` (exit 2)."""
    args: CompareArgs = OmegaConf.to_object(cfg.args)
    layout: LayoutConfig = OmegaConf.to_object(cfg.compare)
    try:
        stats = settings(args)
    except ValueError as e:
        raise CommandError(str(e)) from e
    refs = load_references(layout.references, layout) if layout.references else []
    selected = args.sweep or args.runs or args.filter
    only_refs = Selection("references", f"compare.references={layout.references}", [])
    if backend is None:
        if not refs or selected:
            db = sqlite_path(cfg.tracking.uri)
            raise CommandError(f"no MLflow store at {db} (tracking.uri); run `gdwm run` first or set workdir=...")
        sel = only_refs
    else:
        try:
            sel = select(backend, args.sweep, args.runs, args.filter, args.factors)
        except SelectionError as e:
            if not refs or selected:
                raise CommandError(str(e)) from e
            sel = only_refs
    rows = merge(refs, sel.rows, sel.selector)
    if backend is not None:
        with tempfile.TemporaryDirectory(prefix="gdwm-compare-") as tmp:  # the tables are read into memory
            for problem in load_samples(backend, sel.rows, Path(tmp)):
                warn(f"no per-sample statistics for {problem}")
    table = build_table(rows, layout, stats)
    if backend is not None and (note := environment_note(backend, sel.rows)):  # rows of different environments
        table.notes.append(note)
    for problem in published_averages(table, refs):
        warn(problem)
    if not any(table.value(i, c.metric) is not None for i in range(len(table.rows)) for c in table.columns):
        logged = sorted({m for r in sel.rows for t in r.trials for m in t.metrics})
        warn(f"the rows logged no metric of layout '{layout.name}' (pick one with compare=NAME); they logged: "
             f"{', '.join(logged) or 'nothing'}")  # fmt: skip
    if args.baseline:
        try:
            base = table.index_of(args.baseline)
        except KeyError:
            labels = ", ".join(r.label for r in table.rows)
            raise CommandError(f"args.baseline={args.baseline}: no such row (rows: {labels})") from None
    else:  # the first own row that did not fail (a reported row only when asked for by name)
        base = next((i for i, r in enumerate(table.rows) if not r.failed and not r.reported), 0)
    return Comparison(sel, table, base, refs)


def compare(cfg: DictConfig) -> int:
    """Exit 0 with the outputs written; 1 (with a message naming the selector) when nothing matches; 2 for a bad
    references file."""
    args: CompareArgs = OmegaConf.to_object(cfg.args)
    layout: LayoutConfig = OmegaConf.to_object(cfg.compare)
    db = sqlite_path(cfg.tracking.uri)
    backend = None
    if db is None or Path(db).is_file():
        backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)

    def warn(line: str) -> None:
        err_console.print(f"gdwm compare: warning: {line}", markup=False)

    try:
        with resampling_progress("gdwm compare"):
            result = comparison(cfg, backend, warn)
    except ReferencesError as e:
        err_console.print(f"gdwm compare: {e}", markup=False)
        return 2
    sel, table, base = result.selection, result.table, result.base
    if backend is not None and result.references and args.log_references:
        ids = log_references(backend, result.references, sel.sweep_run_id, sel.rows)
        where = f"under sweep run {sel.sweep_run_id}" if sel.sweep_run_id else f"in experiment {backend.experiment}"
        console.print(f"logged {len(ids)} reported rows as runs tagged gdwm.kind=reference {where}")
    if backend is not None and sel.sweep_run_id:
        _log_statistics(backend, table, sel.sweep_run_id)

    if Format.terminal in args.formats:
        print_table(table)
    try:  # a sweep's name becomes the folder; gdwm writes only into a folder of its own (gdwm.owned)
        out = Path(args.out or Path(cfg.workdir) / "reports" / check_name(sel.name, "args.sweep")).resolve()
        if any(f in SUFFIX for f in args.formats):
            own_report_dir(out)
    except (ValueError, NotOurs) as e:
        raise CommandError(str(e)) from None
    for fmt in (f for f in args.formats if f in SUFFIX):
        path = out / f"{layout.name}.{SUFFIX[fmt]}"
        path.write_text(_render(fmt, table, base, backend, cfg, sel), encoding="utf-8")
        console.print(f"wrote {path}")
        if sel.sweep_run_id and backend is not None:  # this process is the only writer of the store while it runs
            backend.log_artifact(sel.sweep_run_id, str(path), f"compare/{layout.name}")
            console.print(f"  logged to sweep run {sel.sweep_run_id} as compare/{layout.name}/{path.name}")
    return 0


def _log_statistics(backend: TrackingBackend, table, sweep_run_id: str) -> None:
    """Each row's statistics as metrics of its run (``<metric>/std``, ``<metric>/ci_low``, ``<metric>/ci_high``:
    MLflow's compare view can plot and sort them) and the table, in Markdown, as the sweep run's description."""
    for i, row in enumerate(table.rows):
        stats = {}
        for c in table.columns:
            cell = table.cell(i, c.metric)
            if cell is None:
                continue
            for name, v in (("std", cell.std), ("ci_low", cell.ci_low), ("ci_high", cell.ci_high)):
                if v is not None and v == v:
                    stats[f"{c.metric}/{name}"] = v
        if stats and row.run_id:
            backend.log_metrics(row.run_id, stats)
    tags = {"mlflow.note.content": to_markdown(table)}
    key = key_metric(table)
    if key is not None:  # gdwm status shows the best row, gdwm zoo list each version's value
        col = next(c for c in table.columns if c.metric == key)
        live = {i: table.value(i, key) for i in range(len(table.rows)) if not table.rows[i].failed}
        live = {i: v for i, v in live.items() if v is not None}
        best = (max if col.direction is Direction.higher else min)(live, key=live.__getitem__)
        tags |= {"gdwm.key_metric": key, "gdwm.best_row": table.rows[best].label, "gdwm.best_value": f"{live[best]}"}
    backend.set_tags(sweep_run_id, tags)


def key_metric(table) -> str | None:
    """The table's key metric: its last column any live row has a value in (a paper table's last is its Avg.)."""
    for c in reversed(table.columns):
        if any(table.value(i, c.metric) is not None for i, r in enumerate(table.rows) if not r.failed):
            return c.metric
    return None


LOG_WIDTH = 400
"""Widest line a table printed to a log may take; a wider table wraps its cells (never cuts them)."""


def print_table(table: Table) -> None:
    """To a terminal: bold and underline, at the terminal's width. Elsewhere (a pipe, a log file): the marks as
    characters, at the table's natural width up to ``LOG_WIDTH``, so labels and intervals stay on one line."""
    if console.is_terminal:
        console.print(to_rich(table))
        return
    rich = to_rich(table, chars=True)
    natural = Measurement.get(console, console.options.update(width=LOG_WIDTH), rich).maximum
    wide = RedactingConsole(file=console.file, width=max(console.width, min(natural, LOG_WIDTH)), highlight=False)
    wide.print(rich)


def published_averages(table: Table, refs: list[Reference]) -> list[str]:
    """Where a references file gives an aggregate (Avg.) that is not the mean of the row's printed values: the
    table shows the mean (the one average every row gets); the file's line says where to look for a typo."""
    out = []
    by_label = {r.label: r for r in refs}
    for i, row in enumerate(table.rows):
        ref = by_label.get(row.label) if row.reported else None
        for c in (c for c in table.columns if c.mean_of and ref is not None and c.metric in ref.values):
            cell = table.cell(i, c.metric)
            given = fmt_value(ref.values[c.metric], table.precision)
            if cell is not None and table.fmt(cell.mean) != given:
                mean = table.fmt(cell.mean)
                out.append(
                    f"{ref.where(c.metric)}: {c.header} {given} is not the mean of the row's printed values "
                    f"({mean}); the table shows {mean}"
                )
    return out


def _render(fmt: Format, table, base: int, backend: TrackingBackend | None, cfg: DictConfig, sel: Selection) -> str:
    if fmt is Format.markdown:
        return to_markdown(table)
    if fmt is Format.latex:
        return to_latex(table)
    if fmt is Format.csv:
        return to_csv(table)
    from gdwm.compare.report import html_report  # matplotlib only when a report is asked for

    rows = [r for r in table.rows if r.run_id and backend is not None]
    own = {r.run_id for r in sel.rows}
    if sel.linked is not None and all(r.run_id in own for r in rows):  # select read the stage runs they link
        linked = sel.linked
    else:
        linked = linked_runs(backend, rows, sel.selector) if rows else {}
    curves = {r.run_id: training_curves(backend, r, linked) for r in rows}
    return html_report(table, base, curves, ui_url(cfg), sel.selector, cfg.tracking.uri)
