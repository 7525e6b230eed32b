"""Factor effects: for every pair of rows that differ in exactly one factor (``Alignment ✓`` vs ``✗`` with all else
equal), the difference of their values per metric with its (1 - alpha) interval.

The intervals are compare's statistics: with >= 2 seeds in both rows, Welch's interval of the difference of the
seed means (``scipy.stats.ttest_ind``); with one seed, the paired bootstrap over the held-out samples both rows
answered (``gdwm.compare.stats.paired_bootstrap``, the resampling behind the table's marks); else no interval.
"""

from __future__ import annotations

import math
from itertools import combinations

from scipy import stats

from gdwm.compare.stats import Settings, paired_bootstrap
from gdwm.compare.table import Table


def pairs(table: Table) -> list[tuple[str, int, int]]:
    """(factor, a, b): rows a < b, neither failed, that set the same factors and differ only in ``factor``."""
    out = []
    live = [i for i, r in enumerate(table.rows) if not r.failed and r.factors]
    for a, b in combinations(live, 2):
        fa, fb = table.rows[a].factors, table.rows[b].factors
        if fa.keys() != fb.keys():
            continue
        differ = [f for f in fa if fa[f] != fb[f]]
        if len(differ) == 1:
            out.append((differ[0], a, b))
    return out


def _bootstrap_diffs(table: Table, rows: set[int], metrics: list[str], settings: Settings) -> dict:
    """(a, b, metric) -> interval of a - b from one paired bootstrap per evaluation stage over ``rows``."""
    diffs: dict = {}
    stages = {s for i in rows for t in table.rows[i].counted for s in t.samples}
    labels = {i: table.rows[i].label for i in rows}
    for stage in sorted(stages):
        sets = {
            i: [t.samples[stage] for t in table.rows[i].counted]
            for i in sorted(rows)
            if table.rows[i].counted and all(stage in t.samples for t in table.rows[i].counted)
        }
        if len(sets) < 2:
            continue
        b = paired_bootstrap(stage, sets, metrics, settings, labels)
        if b is not None:  # a metric's first stage with samples answers for it, as in the table
            covered = {m for _, _, m in diffs}
            diffs |= {k: v for k, v in b.diffs.items() if k[2] not in covered}
    return diffs


def effects(table: Table, settings: Settings) -> list[dict]:
    """One entry per (factor pair, metric with a value in both rows): factor, from / to values and rows, effect
    (to - from), interval (or None), how it was tested."""
    found = pairs(table)
    if not found:
        return []
    metrics = [c.metric for c in table.columns]
    single = {i for _, a, b in found for i in (a, b) if len(table.rows[i].counted) < 2}
    diffs = _bootstrap_diffs(table, single, metrics, settings) if single else {}
    out = []
    level = 1 - settings.alpha
    for factor, a, b in found:
        ra, rb = table.rows[a], table.rows[b]
        for c in table.columns:
            ca, cb = table.cell(a, c.metric), table.cell(b, c.metric)
            if ca is None or cb is None:
                continue
            effect = cb.mean - ca.mean
            low = high = None
            how = "none"
            xa = [t.metrics[c.metric] for t in ra.counted if c.metric in t.metrics]
            xb = [t.metrics[c.metric] for t in rb.counted if c.metric in t.metrics]
            if len(xa) >= 2 and len(xb) >= 2:
                ci = stats.ttest_ind(xb, xa, equal_var=False).confidence_interval(level)
                low, high, how = float(ci.low), float(ci.high), "welch"
            elif (a, b, c.metric) in diffs:  # a - b: the effect is its negation
                lo, hi = diffs[a, b, c.metric]
                low, high, how = -hi, -lo, "bootstrap"
            if low is not None and (math.isnan(low) or math.isnan(high)):
                low = high = None
                how = "none"
            out.append(
                {
                    "factor": factor,
                    "from": ra.factors[factor],
                    "to": rb.factors[factor],
                    "row_from": ra.label,
                    "row_to": rb.label,
                    "metric": c.metric,
                    "label": c.label,
                    "direction": c.direction.value,
                    "effect": effect,
                    "low": low,
                    "high": high,
                    "test": how,
                    "level": level,
                }
            )
    return out
