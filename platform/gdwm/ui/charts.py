"""The dashboard's charts as Plotly figures (``plotly.graph_objects``; the browser draws them with the
``plotly.min.js`` the Python package ships, so nothing comes from a CDN).

- ``values``: each metric's value per row with its interval (the table's: bootstrap over held-out samples, or
  Student's t over seeds; the std where a cell has no interval), best / second coloured as the table marks them;
- ``effects``: each factor's effect (one row minus the row that differs only in that factor) with its interval;
- ``parallel``: parallel coordinates from the factors to the metrics, a line per row;
- ``curves``: a stage's logged curves, a line per row (the mean over its seeds) and a band (± one std over seeds);
- ``trend``: a regression metric over its runs with the baseline, its tolerance band and every verdict.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import plotly.graph_objects as go
from plotly.subplots import make_subplots

MARK_COLOUR = {"best": "#1f6feb", "second": "#7aa7f0", "": "#8c959f"}
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
LAYOUT = {"margin": {"l": 60, "r": 20, "t": 40, "b": 40}, "template": "plotly_white", "font": {"size": 11}}


def _json(fig: go.Figure) -> dict[str, Any]:
    return fig.to_plotly_json()


def _err(cell: Mapping[str, Any]) -> tuple[float, float]:
    """(below, above) the mean: the interval where the cell has one, else its std, else none."""
    m = cell["mean"]
    if cell.get("ci_low") is not None and cell.get("ci_high") is not None:
        return max(m - cell["ci_low"], 0.0), max(cell["ci_high"] - m, 0.0)
    if cell.get("std") is not None:
        return cell["std"], cell["std"]
    return 0.0, 0.0


def values(table: Mapping[str, Any], cols: int = 3) -> dict[str, Any]:
    """One panel per metric with a value: a point per row that did not fail, with its error bar."""
    live = [i for i, r in enumerate(table["rows"]) if not r["failed"]]
    by = {(c["row"], c["metric"]): c for c in table["cells"]}
    metrics = [c for c in table["columns"] if any((i, c["metric"]) in by for i in live)]
    if not metrics or not live:
        return {}
    nrows = math.ceil(len(metrics) / cols)
    fig = make_subplots(
        rows=nrows,
        cols=min(cols, len(metrics)),
        subplot_titles=[c["label"] for c in metrics],
        shared_yaxes=True,
        horizontal_spacing=0.04,
        vertical_spacing=0.3 / max(nrows, 1),
    )
    labels = [table["rows"][i]["label"] for i in live]
    for k, c in enumerate(metrics):
        cells = [by.get((i, c["metric"])) for i in live]
        xs = [x["mean"] if x else None for x in cells]
        err = [_err(x) if x else (0.0, 0.0) for x in cells]
        fig.add_trace(
            go.Scatter(
                x=xs,
                y=labels,
                mode="markers",
                name=c["label"],
                showlegend=False,
                marker={"size": 9, "color": [MARK_COLOUR[x["mark"] if x else ""] for x in cells]},
                error_x={
                    "type": "data",
                    "symmetric": False,
                    "array": [e[1] for e in err],
                    "arrayminus": [e[0] for e in err],
                    "thickness": 1.2,
                    "width": 4,
                },
                text=[x["text"] if x else "" for x in cells],
                hovertemplate="%{y}: %{text}<extra></extra>",
            ),
            row=k // cols + 1,
            col=k % cols + 1,
        )
    fig.update_yaxes(autorange="reversed")
    fig.update_layout(**LAYOUT, height=max(260, nrows * (60 + 22 * len(live))))
    return _json(fig)


def effects(items: Sequence[Mapping[str, Any]], key_metric: str | None) -> dict[str, Any]:
    """A forest plot of factor effects, one metric at a time (Plotly's dropdown picks it; the key metric first)."""
    if not items:
        return {}
    metrics = list(dict.fromkeys(e["metric"] for e in items))
    if key_metric in metrics:
        metrics.remove(key_metric)
        metrics.insert(0, key_metric)
    fig = go.Figure()
    for k, m in enumerate(metrics):
        mine = [e for e in items if e["metric"] == m]
        ys = [f"{e['factor']}: {e['from']} → {e['to']}<br><sub>{e['row_from']} → {e['row_to']}</sub>" for e in mine]
        hi = [(e["high"] - e["effect"]) if e["high"] is not None else 0.0 for e in mine]
        lo = [(e["effect"] - e["low"]) if e["low"] is not None else 0.0 for e in mine]
        tests = [f"{e['test']} {e['level']:.0%} interval" if e["test"] != "none" else "no interval" for e in mine]
        fig.add_trace(
            go.Scatter(
                x=[e["effect"] for e in mine],
                y=ys,
                mode="markers",
                name=mine[0]["label"],
                visible=k == 0,
                marker={"size": 10, "color": "#1f6feb"},
                error_x={"type": "data", "symmetric": False, "array": hi, "arrayminus": lo},
                text=tests,
                hovertemplate="%{x:.3g} (%{text})<extra></extra>",
            )
        )
    buttons = [
        {
            "label": fig.data[k].name,
            "method": "update",
            "args": [{"visible": [j == k for j in range(len(metrics))]}, {"title.text": fig.data[k].name}],
        }
        for k in range(len(metrics))
    ]
    fig.add_vline(x=0, line={"color": "#444", "width": 1})
    n = max(len([e for e in items if e["metric"] == m]) for m in metrics)
    fig.update_layout(
        **LAYOUT,
        height=140 + 50 * n,
        title={"text": fig.data[0].name},
        updatemenus=[{"buttons": buttons, "x": 1.0, "y": 1.18, "xanchor": "right"}],
        xaxis_title="effect (the row with the new value minus the row without)",
    )
    fig.update_yaxes(autorange="reversed")
    return _json(fig)


def _wrap(text: str, width: int = 12) -> str:
    """An axis title on several lines (Plotly breaks at ``<br>``): long factor names overlap their neighbours."""
    lines: list[str] = []
    for word in text.split():
        if lines and len(lines[-1]) + 1 + len(word) <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return "<br>".join(lines)


def parallel(table: Mapping[str, Any]) -> dict[str, Any]:
    """Parallel coordinates: each factor (its values as ticks), then each metric; a line per row that did not fail,
    coloured by the key metric."""
    live = [i for i, r in enumerate(table["rows"]) if not r["failed"]]
    by = {(c["row"], c["metric"]): c["mean"] for c in table["cells"]}
    metrics = [c for c in table["columns"] if all((i, c["metric"]) in by for i in live)]
    if len(live) < 2 or not metrics:
        return {}
    dims = []
    for f in table["factors"]:
        vals = [table["rows"][i]["factors"].get(f, "–") for i in live]
        ticks = list(dict.fromkeys(vals))
        dims.append(
            {
                "label": f,
                "values": [ticks.index(v) for v in vals],
                "tickvals": list(range(len(ticks))),
                "ticktext": ticks,
            }
        )
    for c in metrics:
        dims.append({"label": _wrap(c["label"]), "values": [by[i, c["metric"]] for i in live]})
    key = table.get("key_metric")
    colour = [by.get((i, key), 0.0) for i in live] if key else list(range(len(live)))
    fig = go.Figure(
        go.Parcoords(
            dimensions=dims,
            line={
                "color": colour,
                "colorscale": "Viridis",
                "showscale": True,
                "colorbar": {"title": {"text": table.get("key_label") or ""}},
            },
        )
    )
    fig.update_layout(**{**LAYOUT, "margin": {"l": 80, "r": 80, "t": 60, "b": 30}}, height=420)
    return _json(fig)


def _mean_band(histories: Iterable[Sequence[tuple[int, float]]]) -> tuple[list[int], list[float], list[float]]:
    """Per step: the mean over the seeds that logged it and its std (0 for one seed)."""
    at: dict[int, list[float]] = {}
    for h in histories:
        for step, v in h:
            if v is not None and not math.isnan(v):
                at.setdefault(step, []).append(v)
    steps = sorted(at)
    mean = [float(np.mean(at[s])) for s in steps]
    std = [float(np.std(at[s], ddof=1)) if len(at[s]) > 1 else 0.0 for s in steps]
    return steps, mean, std


def curves(
    stage: str, rows: Mapping[str, Mapping[str, list[Sequence[tuple[int, float]]]]], cols: int = 3
) -> dict[str, Any]:
    """``rows``: row label -> metric -> one history per seed. One panel per metric, a line per row (the mean over its
    seeds) in a band of ± one std."""
    metrics = sorted({m for r in rows.values() for m in r})
    if not metrics:
        return {}
    nrows = math.ceil(len(metrics) / cols)
    fig = make_subplots(
        rows=nrows,
        cols=min(cols, len(metrics)),
        subplot_titles=[f"{stage}/{m}" for m in metrics],
        vertical_spacing=0.3 / max(nrows, 1),
    )
    for j, (label, by_metric) in enumerate(rows.items()):
        colour = PALETTE[j % len(PALETTE)]
        for k, m in enumerate(metrics):
            if m not in by_metric:
                continue
            steps, mean, std = _mean_band(by_metric[m])
            seeds = len(by_metric[m])
            where = {"row": k // cols + 1, "col": k % cols + 1}
            if seeds > 1:
                fig.add_trace(
                    go.Scatter(
                        x=steps + steps[::-1],
                        y=[a + b for a, b in zip(mean, std, strict=True)]
                        + [a - b for a, b in zip(mean, std, strict=True)][::-1],
                        fill="toself",
                        fillcolor=colour,
                        opacity=0.18,
                        line={"width": 0},
                        hoverinfo="skip",
                        showlegend=False,
                        legendgroup=label,
                    ),
                    **where,
                )
            fig.add_trace(
                go.Scatter(
                    x=steps,
                    y=mean,
                    mode="lines",
                    line={"color": colour, "width": 1.6},
                    name=f"{label} (mean of {seeds} seeds)" if seeds > 1 else label,
                    legendgroup=label,
                    showlegend=k == 0,
                ),
                **where,
            )
    fig.update_xaxes(title_text="step")
    fig.update_layout(**LAYOUT, height=max(300, 260 * nrows), legend={"orientation": "h", "y": -0.15})
    return _json(fig)


def trend(metric: str, points: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``points``: per regression run, oldest first: date, commit, digest, value, verdict, baseline (value),
    allowed, direction, is_baseline. The latest run's baseline is the line, its tolerance the band; failed checks
    are red crosses, the baseline run ringed."""
    if not points:
        return {}
    xs = [f"{p['date']}<br>{p['commit'] or '–'}" for p in points]
    failed = [p["verdict"] in ("REGRESSION", "missing", "no spread", "untestable") for p in points]
    fig = go.Figure()
    fig.add_trace(
        go.Scatter(
            x=xs,
            y=[p["value"] for p in points],
            mode="lines+markers",
            name=metric,
            line={"color": "#1f6feb"},
            marker={
                "size": [14 if f else 9 for f in failed],
                "symbol": ["x" if f else "circle" for f in failed],
                "color": ["#cf222e" if f else "#1f6feb" for f in failed],
                "line": {"width": [3 if p["is_baseline"] else 0 for p in points], "color": "#111"},
            },
            text=[f"{p['verdict']} · code {p['digest'] or '–'}" for p in points],
            hovertemplate="%{x}: %{y:.4g} (%{text})<extra></extra>",
        )
    )
    last = next((p for p in reversed(points) if p.get("baseline") is not None), None)
    if last is not None:
        b, allowed = last["baseline"], last.get("allowed")
        fig.add_hline(
            y=b, line={"dash": "dash", "color": "#666"}, annotation_text="baseline", annotation_position="top right"
        )
        if allowed is not None:
            lo, hi = (b - allowed, b) if last.get("direction") == "higher" else (b, b + allowed)
            fig.add_hrect(
                y0=lo,
                y1=hi,
                fillcolor="#8c959f",
                opacity=0.18,
                line_width=0,
                annotation_text=f"tolerance {last.get('tolerance', '')}",
                annotation_position="bottom right",
            )
    fig.update_layout(**LAYOUT, height=300, title={"text": metric}, showlegend=False)
    return _json(fig)
