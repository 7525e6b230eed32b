"""Factor effects: pairs of rows that differ in one factor only, the difference of their means, Welch's interval over
seeds (scipy's), the paired bootstrap over shared held-out samples for single seeds, none without either."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from scipy import stats

from gdwm.compare.layout import ColumnConfig, LayoutConfig
from gdwm.compare.runs import Row, Trial
from gdwm.compare.stats import SampleSet, Settings
from gdwm.compare.table import build_table
from gdwm.ui.effects import effects, pairs

LAYOUT = LayoutConfig(name="t", columns={"acc": ColumnConfig(header="Acc")})


def _row(label: str, factors: dict[str, str], values: list[float], samples: list[int] | None = None) -> Row:
    trials = []
    for seed, v in enumerate(values):
        t = Trial(f"{label}-{seed}", seed, "FINISHED", {"acc": v})
        if samples is not None:
            table = pa.table({"sample_id": list(range(len(samples))), "correct": samples})
            t.samples["eval"] = SampleSet(list(range(len(samples))), table, _score)
        trials.append(t)
    row = Row(label, label, "FINISHED", "1", {}, factors, {}, trials)
    row.planned = len(values)
    return row


def _score(table, wanted=None) -> dict[str, float]:
    return {"acc": 100.0 * float(np.mean(table.column("correct").to_numpy()))}


def test_pairs_differ_in_exactly_one_factor():
    rows = [
        _row("base", {"Align": "✗", "Sel": "voxel"}, [50.0, 52.0, 51.0]),
        _row("+align", {"Align": "✓", "Sel": "voxel"}, [55.0, 56.5, 54.0]),
        _row("+both", {"Align": "✓", "Sel": "driving"}, [57.0, 58.0, 56.0]),
    ]
    table = build_table(rows, LAYOUT, Settings(n_resamples=50))
    assert pairs(table) == [("Align", 0, 1), ("Sel", 1, 2)]
    found = effects(table, Settings(n_resamples=50))
    first = found[0]
    assert (first["factor"], first["from"], first["to"], first["test"]) == ("Align", "✗", "✓", "welch")
    assert first["effect"] == pytest.approx(np.mean([55.0, 56.5, 54.0]) - 51.0)
    ci = stats.ttest_ind([55.0, 56.5, 54.0], [50.0, 52.0, 51.0], equal_var=False).confidence_interval(0.95)
    assert (first["low"], first["high"]) == pytest.approx((ci.low, ci.high))


def test_single_seeds_take_the_paired_bootstrap_or_no_interval():
    rng = np.random.default_rng(0)
    a = (rng.random(80) < 0.4).astype(int).tolist()
    b = (rng.random(80) < 0.8).astype(int).tolist()
    rows = [_row("A", {"F": "x"}, [_score(pa.table({"correct": a}))["acc"]], a),
            _row("B", {"F": "y"}, [_score(pa.table({"correct": b}))["acc"]], b),
            _row("C", {"F": "z"}, [40.0])]  # fmt: skip
    settings = Settings(n_resamples=200, method="percentile")
    table = build_table(rows, LAYOUT, settings)
    found = {(e["row_from"], e["row_to"]): e for e in effects(table, settings)}
    ab = found["A", "B"]
    assert ab["test"] == "bootstrap" and ab["low"] < ab["effect"] < ab["high"] and ab["low"] > 0
    assert ab["effect"] == pytest.approx(100.0 * (np.mean(b) - np.mean(a)))
    assert (found["A", "C"]["test"], found["A", "C"]["low"]) == ("none", None)
