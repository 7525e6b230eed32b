"""A self-contained HTML report: the marked table (cells with their uncertainty, the legend under it) linked to MLflow,
deltas vs a baseline, and matplotlib plots (per-metric bars with error bars, the Fig. 1 radar, training curves)
inlined as base64 PNGs. Deltas and the radar use the means."""

from __future__ import annotations

import base64
import io
import math
import time
from html import escape

from matplotlib.figure import Figure  # the object API renders with Agg and leaves pyplot's global state alone

from gdwm.compare.layout import Direction
from gdwm.compare.rounding import fmt, round_half_up
from gdwm.compare.table import BEST, SECOND, Table, normalise

Curves = dict[str, list[tuple[int, float]]]
"""``<stage>/<metric>`` -> (step, value) history of one row."""

MAX_PANELS = 16
MAX_LEGEND = 10
"""Rows a plot's legend names at most: matplotlib's colour cycle has 10 colours, so beyond them a legend cannot tell
rows apart (and 200 entries outgrow the figure: its layout collapses, and drawing them took seconds)."""
MAX_TICKS = 30
"""Row labels a bar panel prints at most (every k-th bar beyond): 200 labels overlap in a panel and took a second."""

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; }
th, td { padding: 4px 10px; border-bottom: 1px solid #ddd; }
thead tr:last-child th { border-bottom: 2px solid #444; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.failed td { color: #999; }
td.note { color: #b00; }
tr.reported td { font-style: italic; } tr.block-end td { border-bottom: 2px solid #444; }
td.better { color: #070; } td.worse { color: #b00; }
img { max-width: 100%; display: block; margin: 1em 0; }
.meta, .legend { color: #666; }
"""


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return f'<img alt="plot" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _live_columns(table: Table) -> list[int]:
    """Metric columns with at least one value among rows that did not fail."""
    ok = [i for i, r in enumerate(table.rows) if not r.failed]
    return [j for j, c in enumerate(table.columns) if any(table.value(i, c.metric) is not None for i in ok)]


def _grid(n: int, size: float = 3.0):
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(size * cols, size * 0.8 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    return fig, list(axes.flat)


def error_bar(table: Table, i: int, metric: str) -> tuple[float, float]:
    """(below, above) the mean: the std over seeds, else the bootstrap interval, else none."""
    c = table.cell(i, metric)
    if c is None:
        return 0.0, 0.0
    if c.std is not None:
        return c.std, c.std
    if c.ci_low is not None and c.ci_high is not None:  # a BCa interval may sit off the mean: clip to non-negative
        return max(c.mean - c.ci_low, 0.0), max(c.ci_high - c.mean, 0.0)
    return 0.0, 0.0


def bars(table: Table) -> str | None:
    """One panel per metric: a bar per row that did not fail, with its error bar; best and second coloured.
    None: no values."""
    cols = _live_columns(table)[:MAX_PANELS]
    if not cols:
        return None
    ok = [i for i, r in enumerate(table.rows) if not r.failed]
    fig, axes = _grid(len(cols))
    colour = {BEST: "#1f6feb", SECOND: "#7aa7f0"}
    for ax, j in zip(axes, cols, strict=False):
        c = table.columns[j]
        values = [table.value(i, c.metric) for i in ok]
        err = [error_bar(table, i, c.metric) for i in ok]
        ax.bar(
            range(len(ok)),
            [v or 0.0 for v in values],
            yerr=[[lo for lo, _ in err], [hi for _, hi in err]],
            capsize=3,
            ecolor="#444",
            color=[colour.get(table.marks.get((i, c.metric)), "#bbb") for i in ok],
        )
        every = max(1, math.ceil(len(ok) / MAX_TICKS))
        ticks = range(0, len(ok), every)
        ax.set_xticks(ticks, [table.rows[ok[k]].label for k in ticks], rotation=45, ha="right", fontsize=7)
        ax.set_title(c.label, fontsize=9)
    return _png(fig)


def radar(table: Table) -> str | None:
    """Fig. 1: radius Metric_i/Metric_max (higher-better) or Metric_min/Metric_i (lower-better); None if < 3 axes."""
    cols = _live_columns(table)
    if len(cols) < 3:
        return None
    ok = [i for i, r in enumerate(table.rows) if not r.failed]
    radii = {
        j: normalise([table.value(i, table.columns[j].metric) for i in ok], table.columns[j].direction) for j in cols
    }
    angles = [2 * math.pi * k / len(cols) for k in range(len(cols))]
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="polar")
    for n, i in enumerate(ok):
        r = [radii[j][n] or 0.0 for j in cols]
        ax.plot([*angles, angles[0]], [*r, r[0]], label=table.rows[i].label)
        ax.fill([*angles, angles[0]], [*r, r[0]], alpha=0.08)
    ax.set_xticks(angles, [f"{table.columns[j].header} {table.columns[j].arrow}" for j in cols], fontsize=8)
    ax.set_ylim(0, 1.0)
    if len(ok) <= MAX_LEGEND:
        ax.legend(loc="upper right", bbox_to_anchor=(1.35, 1.1), fontsize=8)
    return _png(fig)


def curves_plot(table: Table, curves: dict[str, Curves]) -> str | None:
    """One panel per ``<stage>/<metric>`` with a line per row; None when no row has any history."""
    keys = sorted({k for c in curves.values() for k in c})[:MAX_PANELS]
    if not keys:
        return None
    fig, axes = _grid(len(keys), size=3.5)
    for ax, key in zip(axes, keys, strict=False):
        for r in table.rows:
            history = curves.get(r.run_id, {}).get(key)
            if history:
                ax.plot([s for s, _ in history], [v for _, v in history], label=r.label)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("step", fontsize=8)
    if sum(1 for r in table.rows if curves.get(r.run_id)) <= MAX_LEGEND:
        axes[0].legend(fontsize=7)
    return _png(fig)


def improvement(delta: float, base: float, direction: Direction) -> float | None:
    """Relative change vs the baseline in %, signed so that positive is better."""
    if base == 0:
        return None
    return 100.0 * delta / abs(base) * (1 if direction is Direction.higher else -1)


def delta_bars(table: Table, base: int) -> str | None:
    cols = _live_columns(table)
    others = [i for i, r in enumerate(table.rows) if i != base and not r.failed]
    if not cols or not others:
        return None
    deltas = table.deltas(base)
    width = 0.8 / len(others)
    fig = Figure(figsize=(max(6.0, 0.6 * len(cols) * len(others)), 3.5), layout="constrained")
    ax = fig.add_subplot()
    for k, i in enumerate(others):
        ys = []
        for j in cols:
            c, d = table.columns[j], deltas[i][j]
            b = table.value(base, c.metric)
            ys.append(0.0 if d is None or b is None else improvement(d, b, c.direction) or 0.0)
        ax.bar([x + k * width for x in range(len(cols))], ys, width, label=table.rows[i].label)
    ax.axhline(0, color="#444", lw=0.8)
    ax.set_xticks(
        [x + 0.4 - width / 2 for x in range(len(cols))],
        [table.columns[j].header for j in cols],
        rotation=45,
        ha="right",
        fontsize=8,
    )
    ax.set_ylabel(f"% better than {table.rows[base].label}", fontsize=8)
    if len(others) <= MAX_LEGEND:
        ax.legend(fontsize=7)
    return _png(fig)


def _run_link(table: Table, i: int, ui_url: str) -> str:
    r = table.rows[i]
    if not r.run_id:  # a reported row read from a references file: no run to open
        return escape(r.label)
    url = f"{ui_url.rstrip('/')}/#/experiments/{r.experiment_id}/runs/{r.run_id}"
    return f'<a href="{escape(url)}">{escape(r.label)}</a>'


def _thead(table: Table, extra: list[str]) -> str:
    lead = table.lead_names
    if not any(c.group for c in table.columns):
        cells = [*lead, *(f"{c.header} {c.arrow}" for c in table.columns), *extra]
        return "<thead><tr>" + "".join(f"<th>{escape(h)}</th>" for h in cells) + "</tr></thead>"
    top = "".join(f'<th rowspan="2">{escape(h)}</th>' for h in lead)
    top += "".join(f'<th colspan="{n}">{escape(g)}</th>' for g, n in table.groups())
    top += "".join(f'<th rowspan="2">{escape(h)}</th>' for h in extra)
    bottom = "".join(f"<th>{escape(c.header)} {c.arrow}</th>" for c in table.columns)
    return f"<thead><tr>{top}</tr><tr>{bottom}</tr></thead>"


def table_html(table: Table, ui_url: str) -> str:
    notes = ["note"] if table.has_notes else []
    body = []
    for i, r in enumerate(table.rows):
        cells = [_run_link(table, i, ui_url), *(escape(x) for x in table.lead(i)[1:])]
        tds = "".join(f"<td>{c}</td>" for c in cells)
        for c in table.columns:
            text, mark = escape(table.text(i, c.metric)), table.marks.get((i, c.metric))
            text = f"<strong>{text}</strong>" if mark == BEST else f"<u>{text}</u>" if mark == SECOND else text
            tds += f'<td class="num">{text}</td>'
        tds += f'<td class="note">{escape(r.note)}</td>' if notes else ""
        kind = "failed" if r.failed else "reported" if r.reported else "ok"
        body.append(f'<tr class="{kind}{" block-end" if table.block_ends(i) else ""}">{tds}</tr>')
    legend = f'<p class="legend" id="legend">{escape(table.legend)}</p>' if table.legend else ""
    if table.notes:
        legend += '<ul class="legend" id="notes">' + "".join(f"<li>{escape(n)}</li>" for n in table.notes) + "</ul>"
    return f'<table id="results">{_thead(table, notes)}<tbody>{"".join(body)}</tbody></table>{legend}'


def deltas_html(table: Table, base: int, ui_url: str) -> str:
    """Value - baseline per row and metric with a value, coloured better (green) / worse (red) by direction."""
    deltas, cols = table.deltas(base), _live_columns(table)
    body = []
    for i, r in enumerate(table.rows):
        if i == base or r.failed:
            continue
        tds = f"<td>{_run_link(table, i, ui_url)}</td>"
        for j in cols:
            c, d = table.columns[j], deltas[i][j]
            if d is None or round_half_up(d, table.precision) == 0:
                cls = "num"
            else:
                cls = "num better" if (d > 0) == (c.direction is Direction.higher) else "num worse"
            tds += f'<td class="{cls}">{"–" if d is None else fmt(d, table.precision, sign=True)}</td>'
        body.append(f"<tr>{tds}</tr>")
    head = "".join(f"<th>{escape(table.columns[j].label)}</th>" for j in cols)
    return f'<table id="deltas"><thead><tr><th>row</th>{head}</tr></thead><tbody>{"".join(body)}</tbody></table>'


def html_report(table: Table, base: int, curves: dict[str, Curves], ui_url: str, selector: str, store: str) -> str:
    """The whole page; ``curves`` maps a row's run id to its training curves."""
    section = []
    radar_img = radar(table)
    section.append("<h2>Radar (Fig. 1 normalisation)</h2>")
    section.append(
        "<p>Radius Metric<sub>i</sub>/Metric<sub>max</sub> for higher-is-better and Metric<sub>min</sub>/Metric"
        "<sub>i</sub> for lower-is-better metrics: 1 = best of these rows.</p>"
        + (radar_img or "<p>Fewer than three metrics with values: no radar.</p>")
    )
    section.append(f"<h2>Per metric</h2>{bars(table) or '<p>No metric of this layout has a value.</p>'}")
    base_label = escape(table.rows[base].label)
    delta_img = delta_bars(table, base)
    section.append(f"<h2>Deltas vs baseline {base_label}</h2>{deltas_html(table, base, ui_url)}")
    section.append(
        f"<p>Bars: relative change vs {base_label} in %, signed so that positive is better.</p>{delta_img}"
        if delta_img
        else "<p>No other row to compare with the baseline.</p>"
    )
    curves_img = curves_plot(table, curves)
    section.append(
        "<h2>Training curves</h2>"
        + (
            curves_img
            or "<p>No training history found: no stage run of these rows logged a metric at more than one step.</p>"
        )
    )
    generated = time.strftime("%Y-%m-%d %H:%M:%S")
    return (
        f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{escape(table.title)}</title>'
        f"<style>{_CSS}</style></head><body><h1>{escape(table.title)}</h1>"
        f'<p class="meta">{escape(selector)} · {escape(store)} · {len(table.rows)} rows · generated {generated}. '
        "– = not logged; the legend under the table says what the cells and marks mean, the notes which metrics are "
        "official or approximate, which stand on proxy data and which encoders each row used.</p>"
        f"{table_html(table, ui_url)}{''.join(section)}</body></html>\n"
    )
