"""The marking rule (``gdwm.compare.marks``): by value as papers do, by significance walked in value order with a
multiple-comparison control, ``auto`` per column; hand-made cases with their numbers, run through ``build_table``
(the path ``gdwm compare`` takes) where they need real tests."""

from decimal import Decimal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from scipy import stats

from gdwm.compare.layout import ColumnConfig, Correction, Direction, LayoutConfig, Rule
from gdwm.compare.marks import BEST, SECOND, Entry, adjust, column_marks
from gdwm.compare.runs import Row, Source, Trial
from gdwm.compare.stats import SampleSet, Settings
from gdwm.compare.table import build_table

M = "x/acc"
LAYOUT = LayoutConfig(name="t", title="T", columns={M: ColumnConfig(header="Acc")})


def seeded(label: str, values: list[float], metric: str = M) -> Row:
    """A row of ``len(values)`` finished seeds without per-sample data (Welch's t-test over seeds compares it)."""
    trials = [Trial(f"{label}-{k}", k, "FINISHED", {metric: v}) for k, v in enumerate(values)]
    return Row(f"{label}-run", label, "FINISHED", "0", {}, trials=trials, planned=len(values))


def reported(label: str, values: dict[str, float]) -> Row:
    trial = Trial("", None, "FINISHED", dict(values))
    return Row("", label, "FINISHED", "", dict(values), trials=[trial], source=Source("Paper", "Tab. 1", "2025"))


def marks(table, metric: str = M) -> dict[str, str]:
    return {table.rows[i].label: mark for i, mark in table.decisions[metric].marks.items()}


def entries(values: dict[int, float], tested: bool = True) -> dict[int, Entry]:
    return {i: Entry(v, Decimal(f"{v:.2f}"), tested) for i, v in values.items()}


def test_holm_and_bonferroni_adjust_a_family():
    p = {"a": 0.01, "b": 0.04, "c": 0.03}
    # Holm: 3 x 0.01, then max(0.03, 2 x 0.03), then max(0.06, 1 x 0.04)
    assert adjust(p, Correction.holm) == pytest.approx({"a": 0.03, "c": 0.06, "b": 0.06})
    assert adjust(p, Correction.bonferroni) == pytest.approx({"a": 0.03, "b": 0.12, "c": 0.09})
    assert adjust(p, Correction.none) == p
    assert adjust({"a": 0.6, "b": 0.5}, Correction.holm) == {"b": 1.0, "a": 1.0}  # capped at 1
    assert adjust({}, Correction.holm) == {}


def test_value_rule_bolds_the_best_printed_value_underlines_the_second_and_ties_share():
    # 3.004 and 2.996 both print 3.00: they tie for best; 2.50 is second; lower is better flips it
    values = {0: 3.004, 1: 1.0, 2: 2.996, 3: 2.5, 4: 2.5}
    assert column_marks(entries(values, tested=False), Direction.higher) == {0: BEST, 2: BEST, 3: SECOND, 4: SECOND}
    assert column_marks(entries(values, tested=False), Direction.lower) == {1: BEST, 3: SECOND, 4: SECOND}
    assert column_marks(entries({0: 0.001, 1: 0.004}), Direction.higher) == {}  # every value prints 0.00


def test_a_lower_value_never_outranks_a_higher_one():
    # the contradiction: rows 1 (30.09) and 2 (28.96) below the top row 0 (31.57); the test tells 1 from 0
    # but not 2 from 0 (2 is noisier). Marking "every row not significantly worse than the best" would bold 2 and
    # underline 1; the walk stops at 1, which opens the underline, and 2 can at most share it
    values = {0: 31.57, 1: 30.09, 2: 28.96}
    apart = {(0, 1)}
    got = column_marks(entries(values), Direction.higher, lambda a, b: (a, b) in apart)
    assert got == {0: BEST, 1: SECOND, 2: SECOND}
    assert column_marks(entries(values), Direction.higher, lambda a, b: True) == {0: BEST, 1: SECOND}


def test_a_lower_value_never_outranks_a_higher_one_with_welchs_test_over_seeds():
    tight, steady, noisy = [31.5, 31.6, 31.7], [30.0, 30.1, 30.2], [24.0, 29.0, 34.0]
    assert stats.ttest_ind(tight, steady, equal_var=False).pvalue < 0.001  # steady is significantly worse
    assert stats.ttest_ind(tight, noisy, equal_var=False).pvalue > 0.4  # noisy cannot be told from the top
    table = build_table([seeded("T", tight), seeded("S", steady), seeded("N", noisy)], LAYOUT)
    assert marks(table) == {"T": BEST, "S": SECOND, "N": SECOND}  # N (29.00) never above S (30.10)
    assert table.decisions[M].rule is Rule.significance


A, B, C = [30.0, 31.0, 30.5], [27.9, 28.7, 29.5], [27.2, 27.7, 28.2]


def test_holm_changes_a_mark_the_raw_p_value_gives():
    raw = build_table([seeded("A", A), seeded("B", B), seeded("C", C)], LAYOUT, Settings(correction=Correction.none))
    holm = build_table([seeded("A", A), seeded("B", B), seeded("C", C)], LAYOUT, Settings())
    p = raw.decisions[M].pvalues
    assert p[0, 1] == pytest.approx(stats.ttest_ind(A, B, equal_var=False).pvalue) == pytest.approx(0.03867, abs=1e-5)
    assert (p[0, 2], p[1, 2]) == (pytest.approx(0.002366, abs=1e-6), pytest.approx(0.15386, abs=1e-5))
    # raw: B is significantly worse than A (0.0387 < 0.05), so B opens the underline and C (p 0.15 vs B) shares it
    assert marks(raw) == {"A": BEST, "B": SECOND, "C": SECOND}
    # Holm over the 3 pairs: A-C 3 x 0.00237 = 0.0071, A-B max(0.0071, 2 x 0.0387) = 0.0773 >= 0.05: B keeps the bold
    assert holm.decisions[M].adjusted[0, 1] == pytest.approx(2 * p[0, 1])
    assert holm.decisions[M].adjusted[0, 2] == pytest.approx(3 * p[0, 2])
    assert marks(holm) == {"A": BEST, "B": BEST, "C": SECOND}
    assert "Holm over each column's 3 pairs; α = 0.05" in holm.legend
    assert "no correction over each column's 3 pairs" in raw.legend
    bonferroni = build_table(
        [seeded("A", A), seeded("B", B), seeded("C", C)], LAYOUT, Settings(correction="bonferroni")
    )
    assert bonferroni.decisions[M].adjusted[0, 1] == pytest.approx(3 * p[0, 1])  # 0.116
    assert marks(bonferroni) == {"A": BEST, "B": BEST, "C": SECOND}
    assert "Bonferroni over each column's 3 pairs" in bonferroni.legend


def test_ties_share_even_where_the_test_would_tell_them_apart():
    # 50.004 and 49.996 print 50.00: one mark, though their seeds (spread 0.001) are far apart for Welch's test
    rows = [
        seeded("A", [50.003, 50.004, 50.005]),
        seeded("B", [49.995, 49.996, 49.997]),
        seeded("C", [40.0, 41.0, 42.0]),
    ]
    table = build_table(rows, LAYOUT)
    assert table.decisions[M].adjusted[0, 1] < 0.05
    assert marks(table) == {"A": BEST, "B": BEST, "C": SECOND}


def test_auto_marks_by_value_where_a_row_has_neither_samples_nor_seeds_and_on_request():
    flat = [seeded("A", [60.0]), seeded("B", [58.0]), seeded("D", [70.0])]  # one seed each, no per-sample data
    table = build_table(flat, LAYOUT)
    assert table.decisions[M].rule is Rule.value and table.decisions[M].pvalues == {}
    assert marks(table) == {"D": BEST, "A": SECOND}
    assert "Marks by value in every column (some row has neither per-sample data nor 2 seeds)" in table.legend
    value = LayoutConfig(name="t", columns={M: ColumnConfig(header="Acc")}, marks=Rule.value)
    by_value = build_table([seeded("A", A), seeded("B", B), seeded("C", C)], value)
    assert marks(by_value) == {"A": BEST, "B": SECOND} and by_value.decisions[M].pvalues == {}
    assert "Marks by value in every column (compare.marks=value)" in by_value.legend
    untested = LayoutConfig(name="t", columns={M: ColumnConfig(header="Acc")}, marks=Rule.significance)
    forced = build_table(flat, untested)  # significance asked for rows that cannot be tested: nothing tells them apart
    assert marks(forced) == {"D": BEST, "A": BEST, "B": BEST}
    assert "pairs with neither per-sample data nor 2 seeds on both sides cannot be told apart" in forced.legend


def accuracy(table: pa.Table, wanted=None) -> dict[str, float]:
    return {M: 100.0 * pc.mean(table.column("correct")).as_py()}


def test_auto_chooses_per_column_and_the_legend_names_the_columns():
    # Acc comes with per-sample predictions (a paired bootstrap tests it), BLEU is a bare logged number
    layout = LayoutConfig(name="t", columns={M: ColumnConfig(header="Acc"), "x/bleu": ColumnConfig(header="BLEU")})
    ids = [f"s{i:02d}" for i in range(60)]
    rows = []
    for label, right, bleu in (("A", 50, 30.0), ("B", 20, 35.0), ("C", 48, 20.0)):
        correct = np.array([1] * right + [0] * (60 - right), dtype=np.int64)
        samples = SampleSet(ids, pa.table({"sample_id": ids, "correct": correct}), accuracy)
        trial = Trial(label, 0, "FINISHED", {M: 100.0 * right / 60, "x/bleu": bleu}, samples={"qa": samples})
        rows.append(Row(label, label, "FINISHED", "0", {}, trials=[trial]))
    table = build_table(rows, layout, Settings(n_resamples=200))
    assert {m: d.rule for m, d in table.decisions.items()} == {M: Rule.significance, "x/bleu": Rule.value}
    assert marks(table) == {"A": BEST, "C": BEST, "B": SECOND}  # A, C: 2 answers apart on the same 60 samples
    assert marks(table, "x/bleu") == {"B": BEST, "A": SECOND}
    assert table.legend.startswith("Bold: best; underlined: second. Marks by significance in Acc: in value order,")
    assert "Marks by value in BLEU (some row has neither per-sample data nor 2 seeds)" in table.legend


def test_a_reported_row_is_marked_by_value_and_ends_a_shared_mark():
    # B is not significantly worse than A, but a reported row sits between them: B cannot share A's bold past it
    rows = [seeded("A", [30.0, 31.0, 30.5]), seeded("B", [29.0, 30.0, 29.5]), reported("Paper", {M: 30.2})]
    table = build_table(rows, LAYOUT)
    assert [r.label for r in table.rows] == ["Paper", "A", "B"]  # reported rows first, as a block
    assert table.decisions[M].pvalues[1, 2] > 0.05
    assert marks(table) == {"A": BEST, "Paper": SECOND}
    rows = [seeded("A", [30.0, 31.0, 30.5]), seeded("B", [29.0, 30.0, 29.5]), reported("P", {M: 31.0})]
    above = build_table(rows, LAYOUT)
    assert marks(above) == {"P": BEST, "A": SECOND, "B": SECOND}  # below a reported best, the tests share again
