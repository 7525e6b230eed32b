"""The statistics behind ``gdwm compare``'s cells and marks, fed hand-made rows through the path the command uses
(``build_table`` -> ``stats.analyse`` -> a renderer), and checked against scipy.stats called directly."""

import csv
import io

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from scipy import stats

from gdwm.compare.layout import ColumnConfig, LayoutConfig
from gdwm.compare.render import to_csv, to_latex, to_markdown
from gdwm.compare.report import table_html
from gdwm.compare.runs import Row, Trial
from gdwm.compare.stats import BEST, SECOND, SampleSet, Settings, paired_bootstrap, seed_cell
from gdwm.compare.table import build_table

M = "nuinteract/avg"
LAYOUT = LayoutConfig(name="t", title="T", columns={M: ColumnConfig(header="Avg.")})
FAST = Settings(n_resamples=300)
"""Fewer resamples than the default: these tests check equalities and clear-cut decisions, not the last digit."""
WELCH = "Welch's t-test over seeds"
WALK = (
    "Marks by significance in every column: in value order, each row shares the mark of the row that opened it unless "
    "significantly worse than that row, and then opens the next mark; no row outranks a better value"
)


def sig(tests: str, pairs: int) -> str:
    """The legend's marks sentence for one significance-marked column of ``pairs`` pairs (Holm, α = 0.05)."""
    family = f"Holm over each column's {pairs} pair{'s' * (pairs > 1)}"
    return f"Bold: best; underlined: second. {WALK} ({tests}; {family}; α = 0.05)."


def accuracy(table: pa.Table, wanted=None) -> dict[str, float]:
    """100 x the mean of the 0/1 ``correct`` column (a scorer as an evaluation stage would name it)."""
    return {M: 100.0 * pc.mean(table.column("correct")).as_py()}


def samples(correct: np.ndarray, ids: list[str] | None = None) -> SampleSet:
    ids = ids or [f"s{i:03d}" for i in range(len(correct))]
    return SampleSet(ids, pa.table({"sample_id": ids, "correct": correct}), accuracy)


def row(label: str, values: list[float], planned: int = 3, sets: list[SampleSet] | None = None) -> Row:
    """A row run of ``planned`` seeds of which ``len(values)`` finished (the rest failed)."""
    trials = [
        Trial(f"{label}-{k}", k, "FINISHED", {M: v}, samples={"qa": sets[k]} if sets else {})
        for k, v in enumerate(values)
    ]
    failed = {"gdwm.failed_stage": "lora", "gdwm.error": "boom"}
    trials += [Trial(f"{label}-{k}", k, "FAILED", {}, failed) for k in range(len(values), planned)]
    return Row(f"{label}-run", label, "FINISHED", "0", {}, trials=trials, planned=planned)


def one_seed(label: str, correct: np.ndarray, ids: list[str] | None = None) -> Row:
    return row(label, [100.0 * correct.mean()], planned=1, sets=[samples(correct, ids)])


def marks(table) -> dict[str, str]:
    return {table.rows[i].label: mark for (i, _), mark in table.marks.items()}


BASE = (np.random.default_rng(1).random(96) < 0.55).astype(np.int64)


def _flip(correct: np.ndarray, up: int, down: int) -> np.ndarray:
    """``up`` wrong answers made right and ``down`` right ones made wrong, on fixed samples."""
    out = correct.copy()
    out[np.flatnonzero(correct == 0)[:up]] = 1
    out[np.flatnonzero(correct == 1)[:down]] = 0
    return out


def test_overlapping_seeds_share_the_mark():
    table = build_table([row("A", [10.0, 12.0, 11.0]), row("B", [11.5, 10.5, 12.5])], LAYOUT, FAST)
    assert marks(table) == {"A": BEST, "B": BEST}
    lines = to_markdown(table).splitlines()
    assert lines[4:6] == ["| A | **11.00 ± 1.00** |", "| B | **11.50 ± 1.00** |"]
    assert table.legend == f"{sig(WELCH, 1)} Cells: mean ± std over n seeds."


def test_separated_seeds_get_bold_underline_and_none():
    rows = [row("A", [30.0, 31.0, 30.5]), row("B", [20.0, 21.0, 20.5]), row("C", [10.0, 11.0, 10.5])]
    table = build_table(rows, LAYOUT, FAST)
    assert marks(table) == {"A": BEST, "B": SECOND}
    assert to_markdown(table).splitlines()[4:7] == [
        "| A | **30.50 ± 0.50** |",
        "| B | <u>20.50 ± 0.50</u> |",
        "| C | 10.50 ± 0.50 |",
    ]
    assert stats.ttest_ind([20.0, 21.0, 20.5], [10.0, 11.0, 10.5], equal_var=False).pvalue < 0.05 / 3
    assert table.legend.startswith(sig(WELCH, 3))


def test_lower_is_better_and_identical_values_give_no_marks():
    layout = LayoutConfig(columns={"x/mae": ColumnConfig(), "x/plan": ColumnConfig()})

    def trow(label, mae):
        r = row(label, [0.0] * 3)
        for t, v in zip(r.trials, mae, strict=True):
            t.metrics = {"x/mae": v, "x/plan": 0.0}
        return r

    table = build_table([trow("A", [3.0, 3.1, 3.2]), trow("B", [1.0, 1.1, 1.2])], layout, FAST)
    assert table.marks == {(1, "x/mae"): BEST, (0, "x/mae"): SECOND}  # plan: 0.00 everywhere, no mark


def test_t_interval_over_seeds_is_scipys():
    c = seed_cell([61.0, 61.5, 61.2])
    low, high = stats.t.interval(0.95, 2, loc=np.mean([61.0, 61.5, 61.2]), scale=c.std / np.sqrt(3))
    assert (c.n, c.std, c.interval) == (3, pytest.approx(np.std([61.0, 61.5, 61.2], ddof=1)), "t")
    assert (c.ci_low, c.ci_high) == (pytest.approx(low), pytest.approx(high))
    assert seed_cell([2.0, 2.0]).ci_low == seed_cell([2.0, 2.0]).ci_high == 2.0  # scipy is NaN at std 0
    assert seed_cell([4.0]) == seed_cell([4.0], 0.9) and seed_cell([4.0]).std is None


@pytest.mark.parametrize("method", ["BCa", "percentile"])
def test_one_seed_interval_is_scipys_bootstrap_over_the_samples(method):
    settings = Settings(n_resamples=400, seed=5, method=method)
    table = build_table([one_seed("A", BASE)], LAYOUT, settings)
    ref = stats.bootstrap(
        (100.0 * BASE,), np.mean, n_resamples=400, rng=np.random.default_rng(5), method=method
    ).confidence_interval
    cell = table.cell(0, M)
    assert (cell.n, cell.std, cell.interval) == (1, None, "bootstrap")
    assert (cell.ci_low, cell.ci_high) == (pytest.approx(ref.low, rel=1e-12), pytest.approx(ref.high, rel=1e-12))
    assert table.text(0, M) == f"{100 * BASE.mean():.2f} [{ref.low:.2f}, {ref.high:.2f}]"
    assert table.legend == f"Cells: one seed: value [95% bootstrap CI over held-out samples ({method})]."


def test_several_seeds_with_samples_bootstrap_the_seed_mean():
    s0, s1 = BASE, _flip(BASE, 6, 2)
    # percentile: BCa's bias term counts resamples strictly below the estimate, and on accuracies many tie with it
    # up to the last bit, which the two ways of averaging round differently
    settings = Settings(n_resamples=300, method="percentile")
    table = build_table([row("A", [100 * s0.mean(), 100 * s1.mean()], 2, [samples(s0), samples(s1)])], LAYOUT, settings)
    ref = stats.bootstrap(
        (50.0 * (s0 + s1),), np.mean, n_resamples=300, rng=np.random.default_rng(0), method="percentile"
    ).confidence_interval  # the mean of the two seeds' accuracies is the accuracy of their per-sample mean
    cell = table.cell(0, M)
    std = np.std([s0.mean(), s1.mean()], ddof=1) * 100
    assert (cell.n, cell.interval, cell.std) == (2, "bootstrap", pytest.approx(std))
    assert (cell.ci_low, cell.ci_high) == (pytest.approx(ref.low, rel=1e-12), pytest.approx(ref.high, rel=1e-12))
    assert table.text(0, M) == f"{50 * (s0.mean() + s1.mean()):.2f} ± {std:.2f}"  # seeds show mean ± std


def test_paired_bootstrap_tells_a_consistent_margin_from_noise():
    margin, noise = _flip(BASE, 12, 0), _flip(BASE, 6, 4)  # +12.5 on the same samples; +2.1 from 10 flips
    rows = [one_seed("A", BASE), one_seed("N", noise), one_seed("M", margin)]
    table = build_table(rows, LAYOUT, FAST)
    assert marks(table) == {"M": BEST, "N": SECOND, "A": SECOND}
    a, m = table.cell(0, M), table.cell(2, M)
    assert m.ci_low < a.ci_high  # the rows' own intervals overlap: only the paired test tells them apart
    b = paired_bootstrap("qa", {i: [r.trials[0].samples["qa"]] for i, r in enumerate(rows)}, [M], FAST)
    assert b.diffs[0, 2, M][1] < 0  # A - M: the whole interval below 0
    assert b.diffs[0, 1, M][0] < 0 < b.diffs[0, 1, M][1]  # A - N: 0 inside
    boot = "a paired bootstrap over 96 held-out samples, 1 seed: two-sided p from the 300 resampled differences"
    assert table.legend == f"{sig(boot, 3)} Cells: one seed: value [95% bootstrap CI over held-out samples (BCa)]."


def test_rows_are_aligned_on_the_sample_ids_they_share():
    ids = [f"s{i:03d}" for i in range(96)]
    rows = [one_seed("A", BASE), one_seed("B", _flip(BASE, 12, 0)[6:], ids[6:])]  # B lost 6 samples
    table = build_table(rows, LAYOUT, FAST)
    assert table.legend.endswith("qa: rows are compared on the 90 sample ids they all share (of up to 96).")
    assert "paired bootstrap over 90 held-out samples" in table.legend


def test_degenerate_bca_falls_back_to_percentile_and_rows_keep_their_order():
    def ordered(table: pa.Table, wanted=None) -> dict[str, float]:  # 1 when the rows arrive in their original order
        pos = np.asarray(table.column("pos"))
        return {"ordered": float(np.all(np.diff(pos) >= 0))}

    ids = [f"s{i}" for i in range(20)]
    s = SampleSet(ids, pa.table({"sample_id": ids, "pos": np.arange(20)}), ordered)
    b = paired_bootstrap("qa", {0: [s], 1: [s]}, ["ordered"], FAST)
    assert b.values == {(0, "ordered"): (1.0, 1.0), (1, "ordered"): (1.0, 1.0)}  # BCa is NaN here
    assert b.diffs == {(0, 1, "ordered"): (0.0, 0.0)} and b.fell_back


def test_errors_name_the_row_trial_and_stage():
    def broken(table: pa.Table, wanted=None) -> dict[str, float]:
        return {M: 1 / 0}

    ok, bad = samples(BASE), SampleSet([f"s{i:03d}" for i in range(96)], samples(BASE).table, broken)
    with pytest.raises(ValueError) as e:
        build_table([row("A", [1.0], 1, [ok]), row("B", [1.0], 1, [bad])], LAYOUT, FAST)
    assert str(e.value) == (
        "row B, trial 0, stage qa: its scorer failed on 96 samples: ZeroDivisionError('division by zero')"
    )
    twice = samples(BASE[:2], ["s0", "s0"])
    with pytest.raises(ValueError, match=r"^row A, trial 0, stage qa: sample_id repeats in its predictions$"):
        build_table([row("A", [1.0], 1, [twice])], LAYOUT, FAST)


def test_surviving_seeds_show_n_in_every_format_and_one_seed_takes_no_mark():
    rows = [row("A", [30.0, 31.0, 30.5]), row("B", [20.0, 21.0]), row("C", [90.0])]
    table = build_table(rows, LAYOUT, FAST)
    assert marks(table) == {"A": BEST, "B": SECOND}  # C (1 of 3 seeds) is highest but takes no mark
    assert table.text(1, M) == "20.50 ± 0.71 (n=2)" and table.text(2, M) == "90.00 (n=1)"
    assert table.cell(2, M).std is None
    md = to_markdown(table).splitlines()
    assert md[5:7] == ["| B | <u>20.50 ± 0.71 (n=2)</u> |", "| C | 90.00 (n=1) |"]
    tex = to_latex(table)
    assert r"B & \underline{20.50{\scriptsize$\pm$0.71}{\scriptsize~(n=2)}} \\" in tex
    assert r"C & 90.00{\scriptsize~(n=1)} \\" in tex
    lines = to_csv(table).splitlines()
    got = list(csv.DictReader(io.StringIO("\n".join(lines[:-1]))))
    assert [(r[f"{M}/n"], r[f"{M}/std"] != "", r[f"{M}/mark"]) for r in got] == [
        ("3", True, BEST),
        ("2", True, SECOND),
        ("1", False, ""),
    ]
    assert "<u>20.50 ± 0.71 (n=2)</u>" in table_html(table, "http://ui/")
    legend = (
        f"{sig(WELCH, 1)} Cells: mean ± std over n seeds; one seed without per-sample data: the value alone. "
        "(n=k): k of 3 seeds finished. Cells of one seed take no mark."
    )
    assert table.legend == legend
    assert md[-1] == legend and lines[-1] == f"# {legend}" and f"% Legend: {legend}" in tex


def per_task(table: pa.Table, wanted=None) -> dict[str, float]:
    """A suite of per-task accuracies and their mean: undefined on a resample that drops a task entirely."""
    out = {}
    for task in sorted(set(table.column("task").to_pylist())):
        sel = table.filter(pc.equal(table.column("task"), task))
        out[f"acc/{task}"] = 100.0 * pc.mean(sel.column("correct")).as_py()
    if len(out) == 3:
        out[M] = sum(out.values()) / 3
    return out


def test_strata_keep_every_task_in_every_resample_and_match_scipys_multi_sample_bootstrap():
    # 40 samples of which only 3 are 'plan': an unstratified resample loses the task (and the suite's mean) often
    tasks = ["rdp"] * 25 + ["vg2d"] * 12 + ["plan"] * 3
    correct = (np.random.default_rng(4).random(40) < 0.5).astype(np.int64)
    ids = [f"s{i:02d}" for i in range(40)]
    table = pa.table({"sample_id": ids, "task": tasks, "correct": correct})
    sset = SampleSet(ids, table, per_task, strata=tasks)
    settings = Settings(n_resamples=200, method="percentile")
    b = paired_bootstrap("qa", {0: [sset]}, [M], settings)
    low, high = b.values[0, M]

    def reference(*groups):  # scipy resamples each task separately; the suite's mean of the concatenation
        idx = np.sort(np.concatenate(groups))
        return per_task(table.take(idx))[M]

    groups = tuple(np.flatnonzero(np.array(tasks) == t) for t in ("plan", "rdp", "vg2d"))  # strata sorted by name
    ref = stats.bootstrap(groups, reference, n_resamples=200, vectorized=False, method="percentile",
                          rng=np.random.default_rng(0)).confidence_interval  # fmt: skip
    assert (low, high) == pytest.approx((ref.low, ref.high))
    assert low < per_task(table)[M] < high


def _rate(k: int, seed: int) -> np.ndarray:
    """96 answers of which exactly ``k`` are right, in a seeded order."""
    return np.random.default_rng(seed).permutation(np.array([1] * k + [0] * (96 - k), dtype=np.int64))


def _seeded(label: str, rights: list[int], offset: int) -> Row:
    sets = [samples(_rate(k, offset + s)) for s, k in enumerate(rights)]
    return row(label, [100.0 * k / 96 for k in rights], planned=len(rights), sets=sets)


def test_with_seeds_a_difference_must_survive_both_the_samples_and_the_seeds():
    # 15 points apart on 96 samples x 3 seeds (the bootstrap over samples alone calls that significant), but the
    # seeds scatter by 20 points: Welch's test over the seeds does not, so both rows keep the bold
    noisy = [_seeded("A", [67, 29, 58], 0), _seeded("B", [48, 19, 43], 10)]
    sets = {i: [t.samples["qa"] for t in r.trials] for i, r in enumerate(noisy)}
    assert paired_bootstrap("qa", sets, [M], FAST).diffs[0, 1, M][0] > 0  # the samples alone: A is better
    table = build_table(noisy, LAYOUT, FAST)
    assert marks(table) == {"A": BEST, "B": BEST}
    assert "and, between rows of >= 2 seeds, Welch's t-test over the seeds: the larger p counts" in table.legend
    # the same gap with seeds that agree: both tests reject
    steady = [_seeded("A", [67, 66, 68], 0), _seeded("B", [48, 47, 49], 10)]
    assert marks(build_table(steady, LAYOUT, FAST)) == {"A": BEST, "B": SECOND}
