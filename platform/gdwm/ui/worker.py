"""``python -m gdwm.ui.worker``: the dashboard's heavy lifting, in a process of its own.

It builds a sweep's table with ``gdwm compare``'s own code (``gdwm.compare.command.comparison``: the same selection,
per-sample bootstrap, marks, legend and notes, from the same config ``gdwm compare args.sweep=NAME`` composes), and
renders what the sweep page and its downloads need; then the factor effects; then the HTML report. Each arrives as
one JSON line on stdout (``{"event": "table" | "effects" | "report" | "progress" | "warning", ...}``), so the page
shows the table before the rest is done. The job is one JSON object on stdin: ``sweep``, ``layout``, ``baseline``,
``overrides`` (the dashboard's ``workdir=`` / ``tracking=`` overrides), ``mlflow_url``, ``links`` (row run id ->
page), and ``report`` (bool).

Why a process: the bootstrap rescores every row's predictions a thousand times with the pipeline's scorers and
reads the samples into memory; the dashboard's own process stays small and answers pages meanwhile. It reads the
store and writes nothing.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

OUT = sys.stdout
"""The JSON lines go here; anything the code it calls prints goes to stderr instead."""


def emit(event: str, **fields: Any) -> None:
    OUT.write(json.dumps({"event": event, **fields}, default=str) + "\n")
    OUT.flush()


def compare_config(job: dict[str, Any]):
    """The config ``gdwm compare`` runs with for the sweep (as ``gdwm sweep`` calls it at its end)."""
    from gdwm.config import load_config

    base = ["args=compare", *([f"compare={job['layout']}"] if job.get("layout") else []), f"args.sweep={job['sweep']}"]
    if job.get("baseline"):
        base.append(f"args.baseline={job['baseline']}")
    return load_config([*base, "args.formats=[]", *job.get("overrides", [])])


def run(job: dict[str, Any]) -> None:
    from omegaconf import OmegaConf

    from gdwm.compare.command import comparison, key_metric, settings
    from gdwm.compare.render import to_csv, to_latex, to_markdown
    from gdwm.compare.stats import ON_RESAMPLE
    from gdwm.tracking import TrackingBackend
    from gdwm.ui.tablehtml import table_html

    t0 = time.perf_counter()
    cfg = compare_config(job)
    backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    last = [0.0]

    def progress(stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        if now - last[0] >= 1.0:
            last[0] = now
            emit("progress", stage=stage, done=done, total=total)

    token = ON_RESAMPLE.set(progress)
    try:
        result = comparison(cfg, backend, lambda line: emit("warning", line=line))
    finally:
        ON_RESAMPLE.reset(token)
    table = result.table
    key = key_metric(table)
    live = {i: table.value(i, key) for i, r in enumerate(table.rows) if not r.failed and key} if key else {}
    live = {i: v for i, v in live.items() if v is not None}
    col = next((c for c in table.columns if c.metric == key), None)
    best = None
    if live and col is not None:
        pick = max if col.direction.value == "higher" else min
        best = pick(live, key=live.__getitem__)
    cells = []
    for i in range(len(table.rows)):
        for c in table.columns:
            cell = table.cell(i, c.metric)
            if cell is not None:
                cells.append(
                    {
                        "row": i,
                        "metric": c.metric,
                        "mean": cell.mean,
                        "std": cell.std,
                        "n": cell.n,
                        "ci_low": cell.ci_low,
                        "ci_high": cell.ci_high,
                        "text": table.text(i, c.metric),
                        "mark": table.marks.get((i, c.metric), ""),
                    }
                )
    emit(
        "table",
        title=table.title,
        html=table_html(table, key, job.get("links", {})),
        markdown=to_markdown(table),
        latex=to_latex(table),
        csv=to_csv(table),
        key_metric=key,
        key_label=col.label if col is not None else None,
        best_row=table.rows[best].label if best is not None else None,
        best_value=live.get(best) if best is not None else None,
        base=result.base,
        rows=[
            {"label": r.label, "run_id": r.run_id, "failed": r.failed, "factors": r.factors, "note": r.note}
            for r in table.rows
        ],
        columns=[
            {"metric": c.metric, "header": c.header, "group": c.group, "direction": c.direction.value, "label": c.label}
            for c in table.columns
        ],
        factors=table.factors,
        cells=cells,
        caption=table.caption,
        seconds=round(time.perf_counter() - t0, 1),
    )
    from gdwm.ui.effects import effects

    args = OmegaConf.to_object(cfg.args)
    emit("effects", effects=effects(table, settings(args)))
    if job.get("report"):
        from gdwm.compare.report import html_report
        from gdwm.compare.runs import linked_runs, training_curves

        linked = linked_runs(backend, table.rows, result.selection.selector)
        curves = {r.run_id: training_curves(backend, r, linked) for r in table.rows}
        html = html_report(
            table, result.base, curves, job.get("mlflow_url") or "", result.selection.selector, cfg.tracking.uri
        )
        emit("report", html=html)


def why(job: dict[str, Any]) -> None:
    """For each stage a trial ran (``job["stages"]``: stage, its run id), why it ran rather than coming from the cache,
    in the dry run's words (``gdwm.plan.why``): its entries compared with the closest earlier entry of the stage."""
    from types import SimpleNamespace

    from gdwm.cache import Cache
    from gdwm.plan import why as plan_why

    cache = Cache(job["cache"])
    out: dict[str, str] = {}
    for stage, run_id in job["stages"]:
        entries = cache.entries(stage)
        mine = [m for m in entries if m.run_id == run_id]
        if not mine:
            out[stage] = "no cache entry of its run (removed, or written elsewhere)"
            continue
        reasons = []
        for m in mine:
            earlier = [e for e in entries if e.scene == m.scene and e.created_at < m.created_at and e.key != m.key]
            if not earlier:
                reasons.append(
                    "first computation (no earlier entry of the stage" + (f" for {m.scene})" if m.scene else ")")
                )
                continue
            sd = SimpleNamespace(name=stage, version=m.version)
            env = SimpleNamespace(data_fingerprint=m.data_fingerprint, code={stage: m.code} if m.code else {}, reuse={})
            reasons.append(plan_why(earlier, sd, m.config, m.upstream, m.identity, env))
        out[stage] = "; ".join(dict.fromkeys(reasons))
    emit("why", why=out)


def main() -> int:
    job = json.loads(sys.stdin.read())
    sys.stdout = sys.stderr
    try:
        why(job) if job.get("kind") == "why" else run(job)
    except Exception as e:  # the dashboard shows this line where the table would be
        from gdwm.errors import one_line
        from gdwm.redact import redact

        emit("error", line=redact(one_line(e)))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
