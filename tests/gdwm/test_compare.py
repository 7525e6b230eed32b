"""``gdwm compare``: rows from MLflow, direction-aware best/second marks, the four text formats, the HTML report."""

import csv
import io
import re
import subprocess
import sys

import pytest
from rich.console import Console

from gdwm.compare.layout import ColumnConfig, Direction, LayoutConfig, default_direction, resolve_columns
from gdwm.compare.render import tex_escape, to_csv, to_latex, to_markdown, to_rich
from gdwm.compare.report import html_report, improvement
from gdwm.compare.runs import SelectionError, select, training_curves
from gdwm.compare.table import BEST, SECOND, build_table, mark_column, normalise
from gdwm.config import load_config
from tests.gdwm.compare_runs import LOSS, TRIALS, log_store

LAYOUT = LayoutConfig(
    name="mixed",
    title="Mixed",
    columns={
        "nuinteract/rdp_bleu": ColumnConfig(header="BLEU", group="RD&P"),
        "nuinteract/vg2d_map": ColumnConfig(header="mAP", group="2D VG"),
        "nuinstruct/mae": ColumnConfig(header="MAE"),
        "nuinteract/avg": ColumnConfig(header="Avg."),
    },
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


def test_mark_column_ties_share_and_missing_is_excluded():
    # 3.0 and 3.004 print the same at 2 decimals: both best; 2.0 is second; None is never marked.
    assert mark_column([1.0, None, 3.0, 3.004, 2.0], Direction.higher, 2) == [None, None, BEST, BEST, SECOND]
    assert mark_column([1.0, None, 3.0, 2.0], Direction.lower, 2) == [BEST, None, None, SECOND]
    assert mark_column([None, float("nan")], Direction.lower, 2) == [None, None]


def test_sweep_selects_the_latest_sweeps_trials_in_trial_order(store):
    sel = select(store.backend(), sweep="abl")
    assert [r.label for r in sel.rows] == list(TRIALS)  # not the older sweep's "old" trial
    assert sel.sweep_run_id == store.sweep_id and sel.name == "abl"
    assert sel.rows[0].factors == {"Coarse Selection": "Voxel Top-K", "Alignment": "none"}
    assert [r.failed for r in sel.rows] == [False] * 4 + [True]
    assert sel.rows[4].note == "failed at lora: RuntimeError: CUDA out of memory"


def test_marks_are_direction_aware_and_skip_missing_and_failed_rows(table):
    label = {i: r.label for i, r in enumerate(table.rows)}
    marks = {(label[i], m.split("/")[-1]): mark for (i, m), mark in table.marks.items()}
    assert marks == {
        ("C", "rdp_bleu"): BEST,  # E (failed, 99.0) takes no mark
        ("B", "rdp_bleu"): SECOND,
        ("D", "rdp_bleu"): SECOND,  # tie at 69.97
        ("B", "vg2d_map"): BEST,
        ("D", "vg2d_map"): SECOND,  # C missing
        ("B", "mae"): BEST,  # lower is better; A and C tie at 3.08 behind D
        ("D", "mae"): SECOND,
        ("D", "avg"): BEST,
        ("C", "avg"): SECOND,
    }
    assert table.fmt(table.value(2, "nuinteract/vg2d_map")) == "–"
    assert table.factors == ["Coarse Selection", "Alignment"]


def test_markdown(table):
    lines = to_markdown(table).splitlines()
    assert lines[2] == ("| row | Coarse Selection | Alignment | RD&P BLEU ↑ | 2D VG mAP ↑ | MAE ↓ | Avg. ↑ | note |")
    assert lines[3] == "| --- | --- | --- | ---: | ---: | ---: | ---: | --- |"
    assert lines[5] == "| B | Voxel Top-K | KL | <u>69.97</u> | **48.59** | **2.41** | 61.24 |  |"
    assert lines[6] == "| C | Driving-Aware | KL | **70.19** | – | 3.08 | <u>61.37</u> |  |"
    assert lines[8] == (
        "| E | Driving-Aware | none | 99.00 | – | – | – | failed at lora: RuntimeError: CUDA out of memory |"
    )


def test_csv_plain_numbers_and_empty_for_missing(table, store):
    rows = list(csv.DictReader(io.StringIO(to_csv(table))))
    assert [r["row"] for r in rows] == list(TRIALS)
    c = rows[2]
    assert c["run_id"] == store.trials["C"] and c["status"] == "FINISHED"
    assert (c["nuinteract/rdp_bleu"], c["nuinteract/vg2d_map"], c["nuinstruct/mae"]) == ("70.19", "", "3.08")
    assert rows[3]["Alignment"] == "KL & 50%_x"
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
    assert ncols == 1 + 2 + 4 + 1  # row, two factors, four metrics, note
    rows = [line for line in tex.splitlines() if line.endswith(r"\\")]
    assert len(rows) == 2 + 5  # group header, header, five rows
    for line in rows:
        spans = sum(int(n) for n in re.findall(r"\\multicolumn\{(\d+)\}", line))
        cells = _unescaped(line, "&") + 1
        assert cells - len(re.findall(r"\\multicolumn", line)) + spans == ncols, line
    assert r"\multicolumn{1}{c}{RD\&P} & \multicolumn{1}{c}{2D VG}" in tex
    assert r"\cmidrule(lr){4-4}\cmidrule(lr){5-5}" in tex
    assert r"MAE $\downarrow$ & Avg. $\uparrow$" in tex
    assert (
        r"D & Driving-Aware & KL \& 50\%\_x & \underline{69.97} & \underline{48.10} & \underline{2.90} & \textbf{62.71}"
        in tex
    )
    assert r"C & Driving-Aware & KL & \textbf{70.19} & -- & 3.08 & \underline{61.37} &  \\" in tex


def test_tex_escape_special_characters():
    assert tex_escape("a&b %c_d #e {f} ~ ^ \\") == (
        r"a\&b \%c\_d \#e \{f\} \textasciitilde{} \textasciicircum{} \textbackslash{}"
    )


def test_rich_table_bolds_best_and_underlines_second(table):
    buf = io.StringIO()
    Console(file=buf, force_terminal=True, color_system="standard", width=250).print(to_rich(table))
    out = buf.getvalue()
    styled = re.findall(r"\x1b\[(\d)m *([\d.]+)\x1b\[0m", out)  # (1 = bold | 4 = underline | 2 = dim, value)
    assert sorted(v for s, v in styled if s == "1") == ["2.41", "48.59", "62.71", "70.19"]
    assert sorted(v for s, v in styled if s == "4") == ["2.90", "48.10", "61.37", "69.97", "69.97"]
    assert ("2", "99.00") in styled  # the failed row is dimmed, not marked


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


def test_filter_keeps_only_comparable_runs(store):
    rows = select(store.backend(), filter_string="attributes.status = 'FINISHED'").rows
    assert {r.label for r in rows} == {"old", "A", "B", "C", "D", "run-gaussiandwm_pp"}  # no sweep, no stage run


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


def test_training_curves_from_the_trials_stage_runs(store):
    rows = select(store.backend(), sweep="abl").rows
    assert training_curves(store.backend(), rows[0]) == {"lora/loss": list(enumerate(LOSS))}  # no system/*, no 1-step
    assert training_curves(store.backend(), rows[1]) == {}


def test_html_report_links_runs_and_says_when_there_is_no_history(table, store):
    html = html_report(table, 0, {}, "http://mlflow.example:5000/", "args.sweep=abl", store.uri)
    for run_id in store.trials.values():
        assert f'href="http://mlflow.example:5000/#/experiments/{store.experiment_id}/runs/{run_id}"' in html
    assert "No training history found" in html
    assert html.count("<img") == 3  # radar, per-metric bars, delta bars
    assert html.count('src="data:image/png;base64,') == 3
    assert "<strong>70.19</strong>" in html and html.count("<u>69.97</u>") == 2
    assert '<th colspan="1">RD&amp;P</th>' in html
    # deltas vs A: B's BLEU +1.19 is better, its MAE -0.67 is better (lower), C's missing 2D mAP is –
    assert (
        '<td class="num better">+1.19</td><td class="num better">+13.64</td><td class="num better">-0.67</td>' in html
    )


def test_cli_compares_a_sweep_and_logs_the_report_to_it(store):
    out = store.workdir / "reports" / "abl"
    r = _gdwm("compare", f"workdir={store.workdir}", "args.sweep=abl", "args.baseline=B")
    assert r.returncode == 0, r.stderr
    assert "NuInteract" in r.stdout and "failed at lora" in r.stdout
    names = sorted(p.name for p in out.iterdir())
    assert names == ["nuinteract.csv", "nuinteract.html", "nuinteract.md", "nuinteract.tex"]
    html = (out / "nuinteract.html").read_text()
    assert "Deltas vs baseline B" in html and "No training history" not in html
    assert html.count("<img") == 4  # radar, bars, deltas, training curves
    logged = store.backend().client.list_artifacts(store.sweep_id, "compare/nuinteract")
    assert sorted(a.path for a in logged) == [f"compare/nuinteract/{n}" for n in names]


def test_cli_layout_formats_and_out(store, tmp_path):
    args = [f"args.runs=[{store.plain_run}]", "compare=generation", "args.formats=[csv]", f"args.out={tmp_path}"]
    r = _gdwm("compare", f"workdir={store.workdir}", *args)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"wrote {tmp_path}/generation.csv"
    assert (tmp_path / "generation.csv").read_text().splitlines()[1].endswith(",FINISHED,9.5,")


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (
            ["args.filter=\"tags.gdwm.row = 'Z'\""],
            1,
            "gdwm compare: CommandError: args.filter=\"tags.gdwm.row = 'Z'\": no runs",
        ),
        (["args.sweep=abl", "args.baseline=Q"], 1, "args.baseline=Q: no such row (rows: A, B, C, D, E)"),
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
