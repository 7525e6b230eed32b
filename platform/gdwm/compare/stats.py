"""Uncertainty of every cell and the p-values behind the marks, from per-seed metrics and per-sample predictions.

Pure (no MLflow; ``runs`` and ``samples`` read what it needs). The statistics are scipy.stats':

- n >= 2 seeds: mean ± std (ddof=1); the interval is a bootstrap over held-out samples of the seed-mean when
  every seed kept its predictions, else Student's t over the seeds (``scipy.stats.t.interval``);
- one seed: a bootstrap interval over its held-out samples, the stage's scorer recomputing corpus metrics (CIDEr,
  mAP) on every resample; without per-sample data, no interval;
- one ``scipy.stats.bootstrap`` per evaluation stage resamples the sample ids every row shares and returns every
  row's value and every pairwise difference, so intervals and paired differences come from the same resamples;
- a pair of rows is compared by the two-sided bootstrap p-value of its difference (twice the share of resampled
  differences on the far side of 0) when both rows have samples, by Welch's t-test over seeds when both have >= 2
  seeds, by the larger of the two when both apply (an intersection-union test: the difference must survive the
  samples' noise and the seeds'), else not at all; ``marks`` adjusts a column's p-values together and walks the
  rows in value order. Reported rows (values copied from papers) take part by value only.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Collection, Hashable, Mapping, Sequence
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any

import numpy as np
from scipy import stats

from gdwm.compare.layout import Direction
from gdwm.compare.marks import BEST, SECOND, Correction, Decision, Entry, Rule, adjust, column_marks
from gdwm.compare.rounding import mean_of_printed, printed

__all__ = ["BEST", "SECOND", "Analysis", "Bootstrap", "Cell", "RowInput", "SampleSet", "Seed", "Settings", "analyse"]

ON_RESAMPLE: ContextVar[Callable[[str, int, int], None] | None] = ContextVar("gdwm_on_resample", default=None)
"""Called as ``hook(stage, resamples scored so far, resamples planned)`` while a bootstrap runs (progress output)."""


@dataclass(frozen=True)
class SampleSet:
    """One trial's per-sample predictions of one evaluation stage and the function that scores any subset."""

    ids: Sequence[Hashable]
    """``sample_id`` of each table row, in table order (unique)."""
    table: Any
    """The predictions: a ``pyarrow.Table`` (anything with ``take(indices)``)."""
    scorer: Callable[[Any, Collection[str] | None], Mapping[str, float]]
    """``scorer(table, wanted)``: the stage's metrics (the logged names) of any subset of the table's rows, in the
    given order; it may compute only the ``wanted`` ones (None: all)."""
    strata: Sequence[Hashable] | None = None
    """Group of each row (e.g. its task), resampled separately so each group keeps its size: a suite of per-task
    metrics stays defined on every resample. None: one group."""


@dataclass
class Seed:
    """One trial of a row: its metrics and, per evaluation stage, the predictions they came from."""

    metrics: Mapping[str, float]
    samples: Mapping[str, SampleSet] = field(default_factory=dict)
    seed: int | None = None


@dataclass
class RowInput:
    """A table row as the statistics see it: the trials that count (every finished seed)."""

    label: str
    seeds: list[Seed]
    planned: int = 1
    """Seeds the row was meant to have; cells with fewer show their n."""
    failed: bool = False
    """A failed row is shown but never gets or takes a mark."""
    reported: bool = False
    """Values copied from a paper (one number per cell, nothing to test): marked by value only."""


@dataclass(frozen=True)
class Settings:
    alpha: float = 0.05
    """Significance level of the tests behind the marks."""
    confidence: float = 0.95
    """Coverage of the intervals of the cells."""
    n_resamples: int = 1000
    """Bootstrap resamples (each scores every row's predictions once)."""
    seed: int = 0
    """Seed of the resampling: the same inputs give the same intervals and marks."""
    method: str = "BCa"
    """``scipy.stats.bootstrap`` method; where BCa is degenerate (NaN) the percentile interval is used."""
    correction: Correction = Correction.holm
    """Multiple-comparison control over the pairs of a column (``marks.adjust``)."""


@dataclass(frozen=True)
class Cell:
    mean: float
    """Mean over the seeds that logged the metric."""
    n: int
    """Seeds behind the value."""
    std: float | None = None
    """Sample std over the seeds (ddof=1); None for one seed."""
    ci_low: float | None = None
    """Interval of the mean at ``Settings.confidence``; None without one."""
    ci_high: float | None = None
    interval: str | None = None
    """``bootstrap`` (over held-out samples), ``t`` (Student's t over seeds) or None."""


@dataclass
class Bootstrap:
    """One stage's paired bootstrap: intervals of every row's value and of every pairwise difference."""

    stage: str
    n_samples: int
    """Sample ids every included row and seed shares (what was resampled)."""
    largest: int
    """Size of the largest sample set before aligning."""
    seeds: list[int]
    """Seeds per included row."""
    values: dict[tuple[int, str], tuple[float, float]] = field(default_factory=dict)
    """(row, metric) -> interval of the seed-mean at ``confidence``."""
    diffs: dict[tuple[int, int, str], tuple[float, float]] = field(default_factory=dict)
    """(row a, row b, metric) -> two-sided interval of a - b at 1 - alpha."""
    p: dict[tuple[int, int, str], float] = field(default_factory=dict)
    """(row a, row b, metric) -> two-sided p of a - b = 0: twice the smaller share of resampled differences <= 0 or
    >= 0 (capped at 1; 0 when every resample falls on one side, i.e. p < 1 / resamples)."""
    fell_back: bool = False
    """Some interval is the percentile one because the configured method gave NaN (a degenerate distribution)."""


@dataclass
class Analysis:
    cells: dict[tuple[int, str], Cell]
    """(row, metric) -> the cell's value and uncertainty."""
    decisions: dict[str, Decision]
    """metric -> how its column was marked (rule, marks, raw and adjusted p-values of the pairs)."""
    bootstraps: list[Bootstrap]
    """One per evaluation stage whose samples were resampled."""
    seeded: bool
    """Some live row of the table's own has >= 2 seeds in some column: then its one-seed cells take no mark."""

    @property
    def marks(self) -> dict[tuple[int, str], str]:
        """(row, metric) -> ``best`` | ``second``."""
        return {(i, m): mark for m, d in self.decisions.items() for i, mark in d.marks.items()}


def seed_cell(values: Sequence[float], confidence: float = 0.95) -> Cell:
    """Mean, std (ddof=1) and the Student-t interval of the mean over n >= 2 seeds; the value alone for one."""
    x = np.asarray(values, dtype=float)
    mean = float(x.mean())
    if len(x) < 2:
        return Cell(mean, 1)
    std = float(x.std(ddof=1))
    if std == 0.0:  # scipy's t.interval is NaN at scale 0; identical seeds pin the mean
        return Cell(mean, len(x), std, mean, mean, "t")
    low, high = stats.t.interval(confidence, len(x) - 1, loc=mean, scale=std / math.sqrt(len(x)))
    return Cell(mean, len(x), std, float(low), float(high), "t")


def welch_p(a: Sequence[float], b: Sequence[float]) -> float:
    """Two-sided p of Welch's t-test (``ttest_ind(equal_var=False)``); NaN when both are constant and equal."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # near-constant seeds: scipy warns, the p is still right
        return float(stats.ttest_ind(a, b, equal_var=False).pvalue)


def _align(stage: str, sets: Mapping[int, Sequence[SampleSet]], labels: Mapping[int, str]) -> tuple[list, list]:
    """The ids every set shares (in the first set's order) and, per set, the table positions of those ids."""
    index = []
    for i, seeds in sets.items():
        for k, s in enumerate(seeds):
            pos = {sid: p for p, sid in enumerate(s.ids)}
            if len(pos) != len(s.ids):
                raise ValueError(f"row {labels[i]}, trial {k}, stage {stage}: sample_id repeats in its predictions")
            index.append(pos)
    shared = set(index[0]).intersection(*index[1:])
    common = [sid for sid in next(iter(sets.values()))[0].ids if sid in shared]
    return common, [np.array([pos[sid] for sid in common], dtype=np.intp) for pos in index]


def _interval(data, statistic, res, level: float, settings: Settings) -> tuple[np.ndarray, np.ndarray, bool]:
    """Interval of every component at ``level`` from ``res``'s resamples (no new ones), the percentile one where
    ``settings.method`` gives NaN; returns (low, high, whether it fell back)."""
    method = settings.method
    kw = {"vectorized": False, "n_resamples": 0, "bootstrap_result": res, "confidence_level": level}
    same = math.isclose(level, settings.confidence)  # res holds the intervals at settings.confidence
    ci = res.confidence_interval if same else stats.bootstrap(data, statistic, method=method, **kw).confidence_interval
    low, high = np.atleast_1d(ci.low).astype(float), np.atleast_1d(ci.high).astype(float)
    bad = np.isnan(low) | np.isnan(high)
    if bad.any() and method.lower() != "percentile":
        p = stats.bootstrap(data, statistic, method="percentile", **kw).confidence_interval
        low[bad], high[bad] = np.atleast_1d(p.low)[bad], np.atleast_1d(p.high)[bad]
    return low, high, bool(bad.any())


def _strata(first: SampleSet, pos: np.ndarray) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """Positions 0..n-1 of the common ids, one array per stratum of ``first`` (scipy resamples each separately, at
    its own size), and the positions of one-sample strata, which have nothing to resample and are always kept."""
    labels = [None] * len(pos) if first.strata is None else [first.strata[p] for p in pos]
    groups: dict = {}
    for k, g in enumerate(labels):
        groups.setdefault(g, []).append(k)
    ordered = [np.array(v, dtype=np.intp) for _, v in sorted(groups.items(), key=lambda kv: str(kv[0]))]
    fixed = [g for g in ordered if len(g) < 2]
    return tuple(g for g in ordered if len(g) >= 2), np.concatenate(fixed) if fixed else np.zeros(0, np.intp)


def paired_bootstrap(
    stage: str,
    sets: Mapping[int, Sequence[SampleSet]],
    metrics: Sequence[str],
    settings: Settings = Settings(),
    labels: Mapping[int, str] | None = None,
) -> Bootstrap | None:
    """One ``scipy.stats.bootstrap`` over the sample ids all rows' sets share: row -> its seeds' sample sets.

    The statistic is, for every metric the scorers return, each row's seed-mean then each pairwise difference;
    each (row, seed) table is scored once per resample, its rows taken in their original order (grounding mAP
    ranks by row order). With strata, each stratum is resampled at its own size (a stratified bootstrap). None when
    fewer than two ids are shared, nothing can be resampled, or no scorer returns one of ``metrics``."""
    rows = list(sets)
    labels = labels or {i: str(i) for i in rows}
    common, positions = _align(stage, sets, labels)
    if len(common) < 2:
        return None
    flat = list(zip((s for i in rows for s in sets[i]), positions, strict=True))
    wanted = frozenset(metrics)  # a scorer may skip the rest: every resample scores every table once
    names = [f"row {labels[i]}, trial {k}" for i in rows for k in range(len(sets[i]))]

    def score(j: int, idx: np.ndarray) -> Mapping[str, float]:
        s, pos = flat[j]
        try:
            return s.scorer(s.table.take(np.sort(pos[idx])), wanted)
        except Exception as e:  # the scorer is pipeline code: say whose predictions it failed on
            raise ValueError(f"{names[j]}, stage {stage}: its scorer failed on {len(idx)} samples: {e!r}") from e

    full = [score(j, np.arange(len(common))) for j in range(len(flat))]
    found = [m for m in metrics if all(m in out for out in full)]
    if not found:
        return None
    seeds = [len(sets[i]) for i in rows]
    starts = np.cumsum([0, *seeds])
    pairs = list(combinations(range(len(rows)), 2))
    ia, ib = np.array([a for a, _ in pairs], dtype=np.intp), np.array([b for _, b in pairs], dtype=np.intp)

    data, fixed = _strata(next(iter(sets.values()))[0], positions[0])
    if not data:
        return None

    calls = [0]
    hook = ON_RESAMPLE.get()

    def statistic(*groups: np.ndarray) -> np.ndarray:
        if hook is not None:  # the launch's progress: the bootstrap is the slow part of compare and regress
            calls[0] += 1
            hook(stage, calls[0], settings.n_resamples)
        idx = np.concatenate([fixed, *(np.asarray(g, dtype=np.intp) for g in groups)])
        # a metric a resample leaves undefined (no parsable answer left, say) is NaN there
        outs = (score(j, idx) for j in range(len(flat)))
        scored = np.array([[out.get(m, np.nan) for m in found] for out in outs], dtype=float)
        values = np.stack([scored[starts[r] : starts[r + 1]].mean(axis=0) for r in range(len(rows))])
        return np.concatenate([values.ravel(), (values[ia] - values[ib]).ravel()])

    with warnings.catch_warnings():
        # a metric constant on every resample (0 everywhere) makes BCa NaN with a warning: the percentile fallback
        warnings.simplefilter("ignore", stats.DegenerateDataWarning)
        warnings.simplefilter("ignore", RuntimeWarning)
        res = stats.bootstrap(
            data,
            statistic,
            n_resamples=settings.n_resamples,
            vectorized=False,
            confidence_level=settings.confidence,
            method=settings.method,
            rng=np.random.default_rng(settings.seed),
        )
        low, high, fell_back = _interval(data, statistic, res, settings.confidence, settings)
        dlow, dhigh, dfell = _interval(data, statistic, res, 1 - settings.alpha, settings)
    nv = len(rows) * len(found)
    largest = max(len(s.ids) for i in rows for s in sets[i])
    out = Bootstrap(stage, len(common), largest, seeds, fell_back=fell_back or dfell)
    for r, i in enumerate(rows):
        for k, m in enumerate(found):
            out.values[i, m] = (float(low[r * len(found) + k]), float(high[r * len(found) + k]))
    for p, (a, b) in enumerate(pairs):
        for k, m in enumerate(found):
            j = nv + p * len(found) + k
            out.diffs[rows[a], rows[b], m] = (float(dlow[j]), float(dhigh[j]))
            out.p[rows[a], rows[b], m] = bootstrap_p(res.bootstrap_distribution[j])
    return out


def bootstrap_p(diffs: np.ndarray) -> float:
    """Two-sided p-value of "no difference" from resampled differences (the percentile interval inverted: the
    smallest α whose 1 - α interval excludes 0); NaN resamples (a metric undefined there) are left out."""
    d = diffs[np.isfinite(diffs)]
    if not d.size:
        return math.nan
    return min(1.0, 2.0 * min(float(np.mean(d <= 0)), float(np.mean(d >= 0))))


def pair_p(
    a: int, b: int, metric: str, values: Mapping[tuple[int, str], Sequence[float]], boots: Sequence[Bootstrap]
) -> tuple[float, str] | None:
    """(p, test) of rows a and b on ``metric``: the bootstrap's p, Welch's over >= 2 seeds each, or the larger of the
    two when both apply; None when neither can be computed."""
    boot = next((bs.p.get((a, b, metric), bs.p.get((b, a, metric))) for bs in boots if _has(bs, a, b, metric)), None)
    seeds = len(values.get((a, metric), ())) >= 2 and len(values.get((b, metric), ())) >= 2
    welch = None
    if seeds:
        welch = welch_p(values[a, metric], values[b, metric])
        welch = 1.0 if math.isnan(welch) else welch  # two constant, equal sets of seeds: nothing to tell apart
    if boot is not None and not math.isnan(boot):
        return (max(boot, welch), "bootstrap+welch") if welch is not None else (boot, "bootstrap")
    return (welch, "welch") if welch is not None else None


def _has(b: Bootstrap, i: int, j: int, metric: str) -> bool:
    return (i, j, metric) in b.p or (j, i, metric) in b.p


def analyse(
    rows: Sequence[RowInput],
    columns: Sequence[tuple[str, Direction]],
    settings: Settings = Settings(),
    precision: int = 2,
    rule: Rule = Rule.auto,
    means: Mapping[str, Sequence[tuple[str, int]]] | None = None,
) -> Analysis:
    """Cells (with intervals) and, per column (metric, direction), its marks by ``rule``. ``means``: aggregate
    metric -> its (part, sign)s; its cell's value becomes the mean of the printed parts (``mean_of_printed``) in
    every row that has them all, the uncertainty staying that of the logged aggregate."""
    labels = {i: r.label for i, r in enumerate(rows)}
    values: dict[tuple[int, str], list[float]] = {}
    for i, r in enumerate(rows):
        for m, _ in columns:
            xs = [float(s.metrics[m]) for s in r.seeds if m in s.metrics and not math.isnan(s.metrics[m])]
            if xs:
                values[i, m] = xs
    cells = {key: seed_cell(xs, settings.confidence) for key, xs in values.items()}
    for m, parts in (means or {}).items():
        for i in range(len(rows)):
            got = [cells.get((i, p)) for p, _ in parts]
            if all(c is not None for c in got):
                v = mean_of_printed([c.mean * sign for c, (_, sign) in zip(got, parts, strict=True)], precision)
                cells[i, m] = replace(cells[i, m], mean=v) if (i, m) in cells else Cell(v, min(c.n for c in got))

    boots: list[Bootstrap] = []
    todo = [m for m, _ in columns]
    own = [i for i, r in enumerate(rows) if not r.failed and not r.reported]
    for stage in sorted({st for i in own for s in rows[i].seeds for st in s.samples}):
        sets = {
            i: [s.samples[stage] for s in rows[i].seeds]
            for i in own
            if rows[i].seeds and all(stage in s.samples for s in rows[i].seeds)
        }
        b = paired_bootstrap(stage, sets, todo, settings, labels) if sets else None
        if b is None:
            continue
        boots.append(b)
        for (i, m), (low, high) in b.values.items():
            if (i, m) in cells and not (math.isnan(low) or math.isnan(high)):
                cells[i, m] = replace(cells[i, m], ci_low=low, ci_high=high, interval="bootstrap")
        todo = [m for m in todo if not any(key[1] == m for key in b.values)]

    live = {key: c for key, c in cells.items() if not rows[key[0]].failed}
    seeded = any(c.n >= 2 for (i, _), c in live.items() if not rows[i].reported)
    sampled = {(i, m) for b in boots for (i, m) in b.values}
    decisions: dict[str, Decision] = {}
    for m, direction in columns:
        cand = [i for (i, mm), c in live.items() if mm == m and (rows[i].reported or c.n >= 2 or not seeded)]
        mine = [i for i in cand if not rows[i].reported]
        testable = all(len(values.get((i, m), ())) >= 2 or (i, m) in sampled for i in mine)
        chosen = Rule.value if rule is Rule.value or len(mine) < 2 else Rule.significance
        if rule is Rule.auto and not testable:
            chosen = Rule.value
        d = Decision(chosen)
        if chosen is Rule.significance:
            for a, b in combinations(sorted(mine), 2):
                found = pair_p(a, b, m, values, boots)
                if found is None:
                    d.tests.add("untested")
                    continue
                d.pvalues[a, b], test = found
                d.tests.add(test)
            d.adjusted = adjust(d.pvalues, settings.correction)
        tested = chosen is Rule.significance
        entries = {i: Entry(cells[i, m].mean, printed(cells[i, m].mean, precision), tested and i in mine) for i in cand}

        def worse(a: int, b: int, d: Decision = d) -> bool:
            p = d.adjusted.get((min(a, b), max(a, b)))
            return p is not None and p < settings.alpha

        d.marks = column_marks(entries, direction, worse if tested else None)
        decisions[m] = d
    return Analysis(cells, decisions, boots, seeded)
