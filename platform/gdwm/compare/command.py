"""``gdwm compare``: select runs, print the table, write the chosen formats, log them to the sweep's parent run."""

from __future__ import annotations

import tempfile
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gdwm.compare.layout import CompareArgs, Format, LayoutConfig
from gdwm.compare.render import to_csv, to_latex, to_markdown, to_rich
from gdwm.compare.runs import SelectionError, select, training_curves
from gdwm.compare.samples import load_samples
from gdwm.compare.stats import Settings
from gdwm.compare.table import build_table
from gdwm.config import sqlite_path, ui_url
from gdwm.environment.runs import environment_note
from gdwm.errors import CommandError
from gdwm.term import console, err_console
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
    return Settings(args.alpha, args.confidence, args.resamples, args.stats_seed, args.bootstrap_method)


def compare(cfg: DictConfig) -> int:
    """Exit 0 with the outputs written; 1 (with a message naming the selector) when nothing matches."""

    args: CompareArgs = OmegaConf.to_object(cfg.args)
    layout: LayoutConfig = OmegaConf.to_object(cfg.compare)
    try:
        stats = settings(args)
    except ValueError as e:
        raise CommandError(str(e)) from e
    db = sqlite_path(cfg.tracking.uri)
    if db is not None and not Path(db).is_file():
        raise CommandError(f"no MLflow store at {db} (tracking.uri); run `gdwm run` first or set workdir=...")
    backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    try:
        sel = select(backend, args.sweep, args.runs, args.filter, args.factors)
    except SelectionError as e:
        raise CommandError(str(e)) from e
    with tempfile.TemporaryDirectory(prefix="gdwm-compare-") as tmp:  # the tables are read into memory
        for problem in load_samples(backend, sel.rows, Path(tmp)):
            err_console.print(f"gdwm compare: warning: no per-sample statistics for {problem}", markup=False)
    table = build_table(sel.rows, layout, stats)
    if note := environment_note(backend, sel.rows):  # rows computed in different environments (gdwm.environment)
        table.notes.append(note)
    if not any(table.value(i, c.metric) is not None for i in range(len(table.rows)) for c in table.columns):
        logged = sorted({m for r in sel.rows for t in r.trials for m in t.metrics})
        err_console.print(
            f"gdwm compare: warning: the rows logged no metric of layout '{layout.name}' (pick one with "
            f"compare=NAME); they logged: {', '.join(logged) or 'nothing'}",
            markup=False,
        )
    if args.baseline:
        try:
            base = table.index_of(args.baseline)
        except KeyError:
            labels = ", ".join(r.label for r in table.rows)
            raise CommandError(f"args.baseline={args.baseline}: no such row (rows: {labels})") from None
    else:
        base = next((i for i, r in enumerate(table.rows) if not r.failed), 0)

    if Format.terminal in args.formats:
        console.print(to_rich(table))
    out = Path(args.out or Path(cfg.workdir) / "reports" / sel.name).resolve()
    for fmt in (f for f in args.formats if f in SUFFIX):
        path = out / f"{layout.name}.{SUFFIX[fmt]}"
        out.mkdir(parents=True, exist_ok=True)
        path.write_text(_render(fmt, table, base, backend, cfg, sel.selector), encoding="utf-8")
        console.print(f"wrote {path}")
        if sel.sweep_run_id:  # this process is the only writer of the store while it runs
            backend.log_artifact(sel.sweep_run_id, str(path), f"compare/{layout.name}")
            console.print(f"  logged to sweep run {sel.sweep_run_id} as compare/{layout.name}/{path.name}")
    return 0


def _render(fmt: Format, table, base: int, backend: TrackingBackend, cfg: DictConfig, selector: str) -> str:
    if fmt is Format.markdown:
        return to_markdown(table)
    if fmt is Format.latex:
        return to_latex(table)
    if fmt is Format.csv:
        return to_csv(table)
    from gdwm.compare.report import html_report  # matplotlib only when a report is asked for

    curves = {r.run_id: training_curves(backend, r) for r in table.rows}
    return html_report(table, base, curves, ui_url(cfg), selector, cfg.tracking.uri)
