"""``gdwm compare`` on a store in the sweep layout (row runs with a trial per seed): selection, cells recomputed
from the trials, marks earned by Welch's t-test over seeds, the four text formats, the HTML report, the CLI."""

import csv
import io
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from rich.console import Console
from scipy import stats

from gdwm.cli import main
from gdwm.compare.command import settings
from gdwm.compare.layout import ColumnConfig, CompareArgs, Direction, LayoutConfig, default_direction, resolve_columns
from gdwm.compare.render import tex_escape, to_csv, to_latex, to_markdown, to_rich
from gdwm.compare.report import error_bar, html_report, improvement
from gdwm.compare.runs import Row, SelectionError, Trial, linked_runs, select, training_curves
from gdwm.compare.samples import load_samples, scorer
from gdwm.compare.stats import Settings
from gdwm.compare.table import BEST, SECOND, build_table, normalise
from gdwm.config import load_config
from gdwm.tracking import TrackingBackend
from tests.gdwm.compare_runs import CORRECT, LOSS, N_SAMPLES, ROWS, log_store

LAYOUT = LayoutConfig(
    name="mixed",
    title="Mixed",
    columns={
        "nuinteract/rdp_bleu": ColumnConfig(header="BLEU", group="RD&P"),
        "nuinteract/vg2d_map": ColumnConfig(header="mAP", group="2D VG"),
        "nuinstruct/mae": ColumnConfig(header="MAE"),
        "nuinteract/avg": ColumnConfig(header="Avg."),
        "nuinteract/plan_acc": ColumnConfig(header="Acc", group="Plan"),
    },
)
MARKS = (
    "Bold: best; underlined: second. Marks by significance in every column: in value order, each row shares the mark "
    "of the row that opened it unless significantly worse than that row, and then opens the next mark; no row "
    "outranks a better value (Welch's t-test over seeds; Holm over each column's 3–6 pairs; α = 0.05)."
)
LEGEND = (
    f"{MARKS} Cells: mean ± std over n seeds; one seed without per-sample data: the value alone. "
    "(n=k): k of 3 seeds finished. Cells of one seed take no mark."
)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return log_store(tmp_path_factory.mktemp("compare"))


@pytest.fixture(scope="module")
def table(store):
    return build_table(select(store.backend(), sweep="abl").rows, LAYOUT)


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True)


@pytest.mark.parametrize(
    ("metric", "direction"),
    [
        ("nuinstruct/mae", "lower"),
        ("gen/shift_1m/fid", "lower"),
        ("gen/shift_4m/fvd", "lower"),
        ("gen/future_1s/fd_daisy", "lower"),
        ("gen/shift_1m/depth_absrel", "lower"),
        ("gen/shift_1m/depth_rmse", "lower"),
        ("gen/shift_1m/psnr", "higher"),
        ("nuinteract/vg2d_map", "higher"),
        ("nuinstruct/average_star", "higher"),
    ],
)
def test_direction_defaults_from_the_name(metric, direction):
    assert default_direction(metric) == direction


def test_sweep_selects_the_latest_sweeps_rows_with_their_trials(store):
    sel = select(store.backend(), sweep="abl")
    assert [r.label for r in sel.rows] == list(ROWS)  # not the older sweep's "old" trial
    assert sel.sweep_run_id == store.sweep_id and sel.name == "abl"
    assert [r.run_id for r in sel.rows] == [store.rows[label] for label in ROWS]
    assert sel.rows[0].factors == {"Coarse Selection": "Voxel Top-K", "Alignment": "none"}
    assert [r.planned for r in sel.rows] == [3] * 6
    assert [[t.seed for t in r.trials] for r in sel.rows] == [[0, 1, 2]] * 6
    assert [[t.seed for t in r.counted] for r in sel.rows] == [[0, 1, 2]] * 3 + [[0, 1], [0, 1, 2], [0]]
    assert [t.run_id for t in sel.rows[3].trials] == [store.trials["D"][s] for s in (0, 1, 2)]
    assert [r.failed for r in sel.rows] == [False] * 4 + [True, False]
    assert [r.note for r in sel.rows] == [""] * 4 + ["failed at lora: RuntimeError: CUDA out of memory", ""]


def test_cells_come_from_the_trials_not_the_rows_aggregate(table):
    a = table.cell(0, "nuinteract/avg")
    assert (a.mean, a.std, a.n, a.interval) == (
        pytest.approx(np.mean([59.0, 59.5, 59.2])),
        pytest.approx(np.std([59.0, 59.5, 59.2], ddof=1)),
        3,
        "t",
    )
    low, high = stats.t.interval(0.95, 2, loc=a.mean, scale=a.std / np.sqrt(3))
    assert (a.ci_low, a.ci_high) == (pytest.approx(low), pytest.approx(high))
    d = table.cell(3, "nuinteract/avg")  # D: 2 of 3 seeds finished
    assert (d.mean, d.n) == (pytest.approx(62.75), 2)
    f = table.cell(5, "nuinteract/avg")  # F: 1 of 3, no per-sample data: no std, no interval
    assert (f.mean, f.n, f.std, f.ci_low, f.interval) == (65.0, 1, None, None, None)
    assert all(c.mean != -1.0 for c in table.cells.values())  # the row runs' stale aggregate is never read
    assert table.legend == LEGEND


def test_marks_are_earned_direction_aware_and_skip_one_seed_missing_and_failed_rows(table):
    label = {i: r.label for i, r in enumerate(table.rows)}
    marks = {(label[i], m.split("/")[-1]): mark for (i, m), mark in table.marks.items()}
    assert marks == {
        ("C", "rdp_bleu"): BEST,  # E (failed, 99.0) and F (one seed, 75.0) take no mark
        ("B", "rdp_bleu"): BEST,  # 69.77 vs 70.17: Welch p = 0.55
        ("D", "rdp_bleu"): SECOND,
        ("B", "vg2d_map"): BEST,
        ("D", "vg2d_map"): BEST,  # equal means (C missing)
        ("A", "vg2d_map"): SECOND,
        ("B", "mae"): BEST,  # lower is better
        ("D", "mae"): SECOND,  # A and C: significantly worse than D
        ("D", "avg"): BEST,
        ("C", "avg"): SECOND,
        ("B", "avg"): SECOND,  # 61.23 vs 61.43: p = 0.32
    }  # plan_acc is 0.00 everywhere: no marks
    assert table.text(3, "nuinteract/vg2d_map") == "48.50 ± 1.41 (n=2)"
    assert table.text(2, "nuinteract/vg2d_map") == "–"
    assert table.text(4, "nuinteract/rdp_bleu") == "99.00"  # a failed row's logged value, without uncertainty
    assert table.factors == ["Coarse Selection", "Alignment"]


def test_markdown(table):
    lines = to_markdown(table).splitlines()
    assert lines[2] == (
        "| row | Coarse Selection | Alignment | RD&P BLEU ↑ | 2D VG mAP ↑ | MAE ↓ | Avg. ↑ | Plan Acc ↑ | note |"
    )
    assert lines[3] == "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | --- |"
    assert lines[5] == (
        "| B | Voxel Top-K | KL | **69.77 ± 0.75** | **48.50 ± 0.50** | **2.45 ± 0.05** | <u>61.23 ± 0.25</u> "
        "| 0.00 ± 0.00 |  |"
    )
    assert lines[7] == (
        "| D | Driving-Aware | KL & 50%_x | <u>65.30 ± 0.42 (n=2)</u> | **48.50 ± 1.41 (n=2)** | "
        "<u>2.71 ± 0.01 (n=2)</u> | **62.75 ± 0.07 (n=2)** | 0.00 ± 0.00 (n=2) |  |"
    )
    assert lines[8] == (
        "| E | Driving-Aware | none | 99.00 | – | – | – | – | failed at lora: RuntimeError: CUDA out of memory |"
    )
    assert lines[9] == (
        "| F | Voxel Top-K | KL & 50%_x | 75.00 (n=1) | 50.00 (n=1) | 2.00 (n=1) | 65.00 (n=1) | 0.00 (n=1) |  |"
    )
    assert lines[10:] == ["", LEGEND]


def test_csv_mean_std_n_ci_mark_per_metric_and_the_legend(table, store):
    text = to_csv(table)
    assert text.splitlines()[-1] == f"# {LEGEND}"
    rows = list(csv.DictReader(io.StringIO(text), restkey="rest"))[:-1]
    assert [r["row"] for r in rows] == list(ROWS)
    stats_columns = ("", "/std", "/n", "/ci_low", "/ci_high", "/mark")
    assert list(rows[0])[5:11] == [f"nuinteract/rdp_bleu{s}" for s in stats_columns]
    c = rows[2]
    assert c["run_id"] == store.rows["C"] and c["status"] == "FINISHED"
    assert float(c["nuinteract/rdp_bleu"]) == pytest.approx(np.mean([70.2, 69.4, 70.9]), abs=1e-12)
    assert float(c["nuinteract/rdp_bleu/std"]) == pytest.approx(np.std([70.2, 69.4, 70.9], ddof=1), abs=1e-12)
    assert (c["nuinteract/rdp_bleu/n"], c["nuinteract/rdp_bleu/mark"], c["nuinteract/avg/mark"]) == ("3", BEST, SECOND)
    assert [c[f"nuinteract/vg2d_map{s}"] for s in stats_columns] == [""] * 6
    d = rows[3]
    assert (d["Alignment"], d["nuinteract/avg"], d["nuinteract/avg/n"]) == ("KL & 50%_x", "62.75", "2")
    f = rows[5]
    assert [f[f"nuinteract/avg{s}"] for s in stats_columns] == [
        "65.0", "", "1", "", "", ""
    ]  # fmt: skip
    assert rows[4]["status"] == "FAILED" and rows[4]["note"].startswith("failed at lora")


def _unescaped(s: str, ch: str) -> int:
    return len(re.findall(rf"(?<!\\){re.escape(ch)}", s))


def test_latex_is_structurally_valid_booktabs(table):
    tex = to_latex(table)
    assert _unescaped(tex, "{") == _unescaped(tex, "}")
    assert tex.count(r"\begin{tabular}") == tex.count(r"\end{tabular}") == 1
    for rule in (r"\toprule", r"\midrule", r"\bottomrule"):
        assert tex.count(rule) == 1, rule
    ncols = len(re.search(r"\\begin\{tabular\}\{(\w+)\}", tex).group(1))
    assert ncols == 1 + 2 + 5 + 1  # row, two factors, five metrics, note
    rows = [line for line in tex.splitlines() if line.endswith(r"\\")]
    assert len(rows) == 2 + 6  # group header, header, six rows
    for line in rows:
        spans = sum(int(n) for n in re.findall(r"\\multicolumn\{(\d+)\}", line))
        cells = _unescaped(line, "&") + 1
        assert cells - len(re.findall(r"\\multicolumn", line)) + spans == ncols, line
    assert r"\multicolumn{1}{c}{RD\&P} & \multicolumn{1}{c}{2D VG}" in tex
    assert r"\cmidrule(lr){4-4}\cmidrule(lr){5-5}\cmidrule(lr){8-8}" in tex
    assert r"MAE $\downarrow$ & Avg. $\uparrow$" in tex
    assert (
        r"D & Driving-Aware & KL \& 50\%\_x & \underline{65.30{\scriptsize$\pm$0.42}{\scriptsize~(n=2)}} & "
        r"\textbf{48.50{\scriptsize$\pm$1.41}{\scriptsize~(n=2)}}" in tex
    )
    assert r"C & Driving-Aware & KL & \textbf{70.17{\scriptsize$\pm$0.75}} & -- & 3.05{\scriptsize$\pm$0.05} & " in tex
    assert r"F & Voxel Top-K & KL \& 50\%\_x & 75.00{\scriptsize~(n=1)} & " in tex
    lines = tex.splitlines()
    assert lines[1] == f"% Legend: {LEGEND}"
    assert lines[-1] == "% \\caption{Mixed. " + tex_escape(LEGEND) + "}"
    assert r"3--6 pairs; $\alpha$ = 0.05). Cells: mean $\pm$ std over n seeds" in lines[-1]


def test_tex_escape_special_characters():
    assert tex_escape("a&b %c_d #e {f} ~ ^ \\") == (
        r"a\&b \%c\_d \#e \{f\} \textasciitilde{} \textasciicircum{} \textbackslash{}"
    )


def test_rich_table_bolds_best_and_underlines_second_with_the_legend(table):
    buf = io.StringIO()
    Console(file=buf, force_terminal=True, color_system="standard", width=250).print(to_rich(table))
    out = buf.getvalue()
    styled = re.findall(
        r"\x1b\[(\d)m *([\d.]+(?: ± [\d.]+)?(?: \(n=\d\))?)\x1b\[0m", out
    )  # (1 bold | 4 underline | 2 dim)
    assert sorted(v for s, v in styled if s == "1") == [
        "2.45 ± 0.05", "48.50 ± 0.50", "48.50 ± 1.41 (n=2)", "62.75 ± 0.07 (n=2)", "69.77 ± 0.75", "70.17 ± 0.75"
    ]  # fmt: skip
    assert sorted(v for s, v in styled if s == "4") == [
        "2.71 ± 0.01 (n=2)", "35.00 ± 1.00", "61.23 ± 0.25", "61.43 ± 0.15", "65.30 ± 0.42 (n=2)"
    ]  # fmt: skip
    assert ("2", "99.00") in styled  # the failed row is dimmed, not marked
    plain = re.sub(r"\x1b\[[\d;]*m", "", out)
    assert " ".join(plain.split()).endswith(LEGEND)


def test_radar_normalisation_is_fig1s():
    assert normalise([50.0, 100.0, 25.0, None], Direction.higher) == [0.5, 1.0, 0.25, None]
    assert normalise([10.0, 20.0, 40.0], Direction.lower) == [1.0, 0.5, 0.25]
    assert normalise([0.0, 2.0], Direction.lower) == [1.0, 0.0]  # a perfect zero error is the best


def test_improvement_is_positive_when_better():
    assert improvement(5.0, 50.0, Direction.higher) == pytest.approx(10.0)
    assert improvement(-0.5, 2.5, Direction.lower) == pytest.approx(20.0)
    assert improvement(1.0, 0.0, Direction.higher) is None


def test_generation_layout_discovers_every_target(tmp_path):
    cfg = load_config([f"workdir={tmp_path}", "compare=generation"])
    from omegaconf import OmegaConf

    layout = OmegaConf.to_object(cfg.compare)
    logged = ["gen/shift_4m/psnr", "gen/shift_1m/fid", "gen/shift_1m/psnr", "gen/future_1s/fd_daisy", "nuinteract/avg"]
    cols = resolve_columns(layout, logged)
    assert [(c.group, c.header, c.direction.value) for c in cols] == [
        ("future_1s", "FD (daisy)", "lower"),
        ("shift_1m", "PSNR", "higher"),
        ("shift_1m", "FID", "lower"),
        ("shift_4m", "PSNR", "higher"),
    ]


def test_factors_from_params_for_plain_runs(store):
    rows = select(store.backend(), runs=[store.plain_run], factor_params=["model.selector.name"]).rows
    assert [(r.label, r.factors) for r in rows] == [("run-gaussiandwm_pp", {"model.selector.name": "driving_aware"})]
    assert [(t.run_id, t.seed) for t in rows[0].trials] == [(store.plain_run, 0)]  # one seed: its own trial


def test_runs_by_id_a_row_brings_its_trials_a_trial_stands_alone(store):
    rows = select(store.backend(), runs=[store.rows["D"], store.trials["B"][1], store.old_trial]).rows
    assert [(r.label, r.planned, [t.seed for t in r.counted]) for r in rows] == [
        ("D", 3, [0, 1]),
        ("B", 1, [1]),
        ("old", 1, [None]),  # a trial from before seeds
    ]
    assert rows[1].trials[0].run_id == store.trials["B"][1]


def test_a_row_fails_when_all_its_trials_do():
    error = {"gdwm.failed_stage": "lora", "gdwm.error": "OOM\ntrace"}
    ok, bad = Trial("t0", 0, "FINISHED", {"m": 1.0}), Trial("t1", 1, "FAILED", {}, error)
    # a multi-seed `gdwm run` ends FAILED when a seed failed: its finished seeds still count
    run = Row("r", "run", "FAILED", "0", {}, trials=[ok, bad], planned=2)
    assert (run.failed, run.note, [t.seed for t in run.counted]) == (False, "", [0])
    lost = Row("r", "run", "FAILED", "0", {}, trials=[bad], planned=2)
    assert (lost.failed, lost.note, lost.counted) == (True, "failed at lora: OOM", [bad])
    alone = Row("t1", "seed", "FAILED", "0", {}, tags=error, trials=[Trial("t1", 1, "FAILED", {}, error)])
    assert (alone.failed, alone.note) == (True, "failed at lora: OOM")


def test_filter_keeps_rows_plain_runs_and_old_trials_under_a_sweep(store):
    rows = select(store.backend(), filter_string="attributes.status = 'FINISHED'").rows
    # no sweep, no stage run, no trial of a row (its row stands for it); E's row FAILED
    assert [r.label for r in rows] == ["old", "A", "B", "C", "D", "F", "run-gaussiandwm_pp"]


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"sweep": "nope"}, "args.sweep=nope: no sweep named 'nope' in experiment 'gdwm'"),
        ({"runs": ["0" * 32]}, f"args.runs=['{'0' * 32}']: no run '{'0' * 32}'"),
        ({"filter_string": "tags.`gdwm.row` = 'Z'"}, "args.filter=\"tags.`gdwm.row` = 'Z'\": no runs tagged gdwm.kind"),
        ({"filter_string": "tags.x ~ 1"}, "args.filter='tags.x ~ 1': "),
        ({"sweep": "abl", "runs": ["x"]}, "give one selector, not args.sweep and args.runs"),
    ],
)
def test_selection_errors_name_the_selector(store, kw, message):
    with pytest.raises(SelectionError) as e:
        select(store.backend(), **kw)
    assert str(e.value).startswith(message)


def test_load_samples_reads_the_predictions_and_names_what_it_cannot_read(store, tmp_path):
    b = store.backend()
    row = select(b, runs=[store.plain_run]).rows[0]
    assert load_samples(b, [row], tmp_path) == []
    qa = row.trials[0].samples["evaluate_qa"]
    assert qa.ids[:2] == ["val-000", "val-001"] and len(qa.ids) == N_SAMPLES
    assert qa.table.column("correct").to_pylist() == CORRECT.tolist()
    assert qa.scorer(qa.table) == {"nuinteract/avg": pytest.approx(100 * CORRECT.mean())}
    tags = {"gdwm.samples.evaluate_qa": "evaluate_qa/predictions.parquet", "gdwm.scorer.evaluate_qa": "no_such_mod:f"}
    broken = Row(store.plain_run, "X", "FINISHED", "0", {}, trials=[Trial(store.plain_run, 2, "FINISHED", {}, tags)])
    assert load_samples(b, [broken], tmp_path) == [
        f"row X seed 2 (run {store.plain_run}), gdwm.samples.evaluate_qa=evaluate_qa/predictions.parquet: "
        "ModuleNotFoundError: No module named 'no_such_mod'"
    ]
    assert broken.trials[0].samples == {}


def test_scorer_is_imported_by_the_name_its_tag_gives():
    from tests.gdwm.compare_runs import accuracy

    assert scorer("tests.gdwm.compare_runs:accuracy") is scorer("tests.gdwm.compare_runs.accuracy") is accuracy
    with pytest.raises(ValueError, match=r"^scorer 'accuracy' is not <module>:<function>$"):
        scorer("accuracy")
    with pytest.raises(ValueError, match=r"^scorer 'tests.gdwm.compare_runs:nope': module tests.gdwm.compare_runs "):
        scorer("tests.gdwm.compare_runs:nope")


def test_settings_name_the_argument_out_of_range():
    assert settings(CompareArgs(alpha=0.01, resamples=50, stats_seed=3)) == Settings(0.01, 0.95, 50, 3)
    with pytest.raises(ValueError, match=r"^args\.alpha=1\.5: must lie strictly between 0 and 1$"):
        settings(CompareArgs(alpha=1.5))
    with pytest.raises(ValueError, match=r"^args\.resamples=1: the bootstrap needs at least 2 resamples$"):
        settings(CompareArgs(resamples=1))
    with pytest.raises(ValueError, match=r"^args\.bootstrap_method=bca: must be one of BCa, percentile, basic$"):
        settings(CompareArgs(bootstrap_method="bca"))


def test_training_curves_from_the_first_trials_stage_runs(store):
    rows = select(store.backend(), sweep="abl").rows
    assert training_curves(store.backend(), rows[0]) == {"lora/loss": list(enumerate(LOSS))}  # no system/*, no 1-step
    assert training_curves(store.backend(), rows[1]) == {}


def _linked_sweep(workdir, n: int) -> TrackingBackend:
    """A sweep of ``n`` one-seed rows as the runner logs them: each trial links its stage runs (children of the
    sweep) with ``gdwm.stage_run.<stage>``; the last trial links none (its stage run names it by ``gdwm.trial``)."""
    b = TrackingBackend(f"sqlite:///{workdir}/mlflow.db", "linked", str(workdir / "mlartifacts"))
    b.system_metrics_interval_s = 0
    sweep = b.create_run("sweep-big", {"gdwm.kind": "sweep", "gdwm.sweep": "big"})
    for i in range(n):
        tags = {"gdwm.sweep": "big", "gdwm.row": f"r{i}", "gdwm.trial_index": str(i), "gdwm.seeds": "0"}
        row = b.create_run(f"row-{i}", tags | {"gdwm.kind": "row"}, sweep)
        trial = b.create_run(f"trial-{i}", tags | {"gdwm.kind": "trial", "gdwm.seed": "0"}, row)
        stage = b.create_run(f"lora-{i}", {"gdwm.stage": "lora", "gdwm.kind": "stage"} | (
            {"gdwm.trial": trial} if i == n - 1 else {}), sweep)  # fmt: skip
        for step in range(3):
            b.log_metrics(stage, {"loss": float(i + step)}, step=step)
        b.end_run(stage)
        if i < n - 1:
            b.set_tags(trial, {"gdwm.stage_run.lora": stage})
        b.log_metrics(trial, {"nuinteract/plan_acc": float(i)})
        b.end_run(trial)
        b.end_run(row)
    b.end_run(sweep)
    return b


def test_a_sweeps_rows_trials_and_curves_take_the_same_searches_for_3_rows_as_for_12(tmp_path):
    """Rows' trials come from one search for the sweep, linked stage runs from one search per 100: what compare
    and the dashboard ask the store does not grow with the rows (a team's server answers each request in tens of
    ms). The curves are those each row's trial links, or the runs naming the trial (the unlinked last row)."""
    searches = {}
    for n in (3, 12):
        (tmp_path / str(n)).mkdir()
        b = _linked_sweep(tmp_path / str(n), n)
        calls = []

        def counted(*a, _search=b.search_runs, _calls=calls, **kw):
            _calls.append(a[0] if a else kw.get("filter_string"))
            return _search(*a, **kw)

        b.search_runs = counted
        rows = select(b, sweep="big").rows
        linked = linked_runs(b, rows, "args.sweep=big")
        curves = {r.label: training_curves(b, r, linked) for r in rows}
        searches[n] = len(calls)
        assert [len(r.trials) for r in rows] == [1] * n
        assert curves == {f"r{i}": {"lora/loss": [(s, float(i + s)) for s in range(3)]} for i in range(n)}
        assert curves == {r.label: training_curves(b, r) for r in rows}  # as without the batch, a request a run
    assert searches[3] == searches[12] == 7, searches  # sweep, its children, its trials, linked x2, unlinked x2


def test_html_report_cells_error_bars_legend_and_links(table, store):
    html = html_report(table, 0, {}, "http://mlflow.example:5000/", "args.sweep=abl", store.uri)
    for run_id in store.rows.values():
        assert f'href="http://mlflow.example:5000/#/experiments/{store.experiment_id}/runs/{run_id}"' in html
    assert "No training history found" in html
    assert html.count("<img") == 3  # radar, per-metric bars, delta bars
    assert html.count('src="data:image/png;base64,') == 3
    assert "<strong>70.17 ± 0.75</strong>" in html and "<u>65.30 ± 0.42 (n=2)</u>" in html
    assert '<th colspan="1">RD&amp;P</th>' in html
    assert '<p class="legend" id="legend">Bold: best; underlined: second.' in html
    assert "(Welch&#x27;s t-test over seeds; Holm over each column&#x27;s 3–6 pairs; α = 0.05)" in html
    # deltas vs A on the means: B's BLEU +9.27 is better, its MAE -0.60 is better (lower), C's missing 2D mAP is –
    assert (
        '<td class="num better">+9.27</td><td class="num better">+13.50</td><td class="num better">-0.60</td>' in html
    )
    # error bars: the std with seeds, nothing for a one-seed cell without samples
    assert error_bar(table, 1, "nuinteract/avg") == (pytest.approx(0.2517, abs=1e-4),) * 2
    assert error_bar(table, 5, "nuinteract/avg") == (0.0, 0.0)


def test_cli_compares_a_sweep_and_logs_the_report_to_it(store):
    out = store.workdir / "reports" / "abl"
    r = _gdwm("compare", f"workdir={store.workdir}", "args.sweep=abl", "args.baseline=B")
    assert r.returncode == 0, r.stderr
    assert "NuInteract" in r.stdout and "failed at" in r.stdout  # 11 columns ± std wrap in 160 characters
    names = sorted(p.name for p in out.iterdir() if p.name != ".gdwm-report")
    assert names == ["nuinteract.csv", "nuinteract.html", "nuinteract.md", "nuinteract.tex"]
    assert (out / ".gdwm-report").is_file()  # the folder is gdwm's: the next report may replace its files
    html = (out / "nuinteract.html").read_text()
    assert "Deltas vs baseline B" in html and "No training history" not in html
    assert html.count("<img") == 4  # radar, bars, deltas, training curves
    md = (out / "nuinteract.md").read_text().splitlines()
    assert md[-1].startswith(MARKS)
    assert md[5].startswith("| B | Voxel Top-K | KL | **69.77 ± 0.75** | – | – | **48.50 ± 0.50** |")
    logged = store.backend().client.list_artifacts(store.sweep_id, "compare/nuinteract")
    assert sorted(a.path for a in logged) == [f"compare/nuinteract/{n}" for n in names]


def test_cli_one_seed_interval_is_scipys_bootstrap_over_the_samples(store, tmp_path):
    args = [f"args.runs=[{store.plain_run}]", "args.formats=[csv]", f"args.out={tmp_path}"]
    r = _gdwm("compare", f"workdir={store.workdir}", *args, "args.resamples=200", "args.stats_seed=7")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"wrote {tmp_path}/nuinteract.csv"
    text = (tmp_path / "nuinteract.csv").read_text()
    row = next(csv.DictReader(io.StringIO(text)))
    ref = stats.bootstrap(
        (100.0 * CORRECT,), np.mean, n_resamples=200, rng=np.random.default_rng(7), method="BCa"
    ).confidence_interval
    assert float(row["nuinteract/avg"]) == pytest.approx(100 * CORRECT.mean())
    assert (row["nuinteract/avg/std"], row["nuinteract/avg/n"], row["nuinteract/avg/mark"]) == ("", "1", "")
    assert float(row["nuinteract/avg/ci_low"]) == pytest.approx(ref.low, rel=1e-12)
    assert float(row["nuinteract/avg/ci_high"]) == pytest.approx(ref.high, rel=1e-12)
    assert text.splitlines()[-1] == "# Cells: one seed: value [95% bootstrap CI over held-out samples (BCa)]."


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (
            ["args.filter=\"tags.gdwm.row = 'Z'\""],
            1,
            "gdwm compare: CommandError: args.filter=\"tags.gdwm.row = 'Z'\": no runs",
        ),
        (["args.sweep=abl", "args.baseline=Q"], 1, "args.baseline=Q: no such row (rows: A, B, C, D, E, F)"),
        (["compare=nuintract"], 2, "config group 'compare' has no option 'nuintract'; allowed values: generation"),
        (["args.sweeep=abl"], 2, "unknown config key 'args.sweeep'"),
        (["args.formats=[pdf]"], 2, "args.formats"),
    ],
)
def test_cli_errors(store, args, code, message):
    r = _gdwm("compare", f"workdir={store.workdir}", *args)
    assert r.returncode == code, r.stderr
    assert message in r.stderr.replace("\n", " ")


def test_cli_without_a_store_says_so(tmp_path):
    r = _gdwm("compare", f"workdir={tmp_path}")
    assert r.returncode == 1
    assert f"no MLflow store at {tmp_path.resolve()}/mlflow.db (tracking.uri)" in r.stderr.replace("\n", " ")


def test_a_report_never_overwrites_a_folder_gdwm_did_not_create(store, tmp_path, capsys):
    """args.out naming a user's folder (holding, say, their own nuinteract.csv) is refused; a folder of reports an
    older gdwm wrote is recognised and marked."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "nuinteract.csv").write_text("my numbers")
    (mine / "notes.txt").write_text("my notes")
    args = ["compare", f"workdir={store.workdir}", f"args.runs=[{store.plain_run}]", "args.formats=[csv]"]
    rc = main([*args, f"args.out={mine}"])
    err = " ".join(capsys.readouterr().err.split())
    assert rc == 1 and err == (
        f"gdwm compare: CommandError: {mine}: not a gdwm report directory (notes.txt is not gdwm's, and there is no "
        ".gdwm-report); choose an empty or new directory"
    )
    assert (mine / "nuinteract.csv").read_text() == "my numbers" and sorted(os.listdir(mine)) == [
        "notes.txt",
        "nuinteract.csv",
    ]
    old = tmp_path / "old"
    old.mkdir()
    (old / "nuinteract.md").write_text("an older gdwm's report")
    assert main([*args, f"args.out={old}"]) == 0
    assert sorted(os.listdir(old)) == [".gdwm-report", "nuinteract.csv", "nuinteract.md"]
