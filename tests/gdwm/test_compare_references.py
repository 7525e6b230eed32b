"""Reported rows (``compare.references``): a published table through ``gdwm compare`` gets the paper's marks and
averages to the digit; mixed with a toy sweep, toy rows are marked by significance and reported rows by value; the
rows can be logged as runs; a bad file exits 2 naming file, line and field. The CLI runs in-process (``gdwm.cli.main``,
output captured: not a terminal, so the terminal table prints its marks as characters)."""

import csv
import io
import re
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gdwm.cli import main
from gdwm.compare.layout import ColumnConfig, LayoutConfig
from gdwm.compare.references import ReferencesError, load_references
from gdwm.compare.rounding import fmt, mean_of_printed
from gdwm.compare.runs import Row, Trial, select
from gdwm.compare.table import build_table
from gdwm.config import load_config
from tests.gdwm.compare_runs import log_store

PAPER = Path(__file__).parents[2] / "conf" / "compare" / "references" / "nuinteract_paper.csv"
"""GaussianDWM++'s Tab. vqa-main-nuinteract as typed from the paper: 17 rows, values only."""
COLUMNS = ["BLEU", "ROUGE-L", "CIDEr", "2D mAP", "2D F1", "mIoU", "3D Pr", "3D mAP", "3D F1", "Acc", "Avg."]
# The paper's marks, read off its LaTeX (\textbf = best, \ul = second), column by column
PUBLISHED = {
    "BLEU": ("GaussianDWM++", "GaussianDWM"),
    "ROUGE-L": ("GaussianDWM++", "InternVL2-8B"),
    "CIDEr": ("GaussianDWM++", "InternVL2-8B"),
    "2D mAP": ("GaussianDWM++", "GaussianDWM"),
    "2D F1": ("GaussianDWM++", "GaussianDWM"),
    "mIoU": ("GaussianDWM++", "GaussianDWM"),
    "3D Pr": ("PETR", "CAPE"),
    "3D mAP": ("GaussianDWM++", "GaussianDWM"),
    "3D F1": ("GaussianDWM++", "GaussianDWM"),
    "Acc": ("DriveMonkey", "GaussianDWM++"),
    "Avg.": ("GaussianDWM++", "GaussianDWM"),
}
# The paper's Avg. column (– where a row reports only 3D grounding)
PUBLISHED_AVG = {
    "LLaVA1.5": "28.15", "MiniCPM-V 2": "23.41", "MiniCPM-V 2.6": "24.78", "InternVL1.5-2B": "43.25",
    "InternVL1.5-4B": "40.84", "Qwen2-VL-2B": "39.66", "Qwen2-VL-7B": "41.09", "InternVL2-1B": "41.71",
    "InternVL2-2B": "42.43", "InternVL2-4B": "42.64", "InternVL2-8B": "45.42", "DriveMonkey": "52.12",
    "BEVFormer": "–", "PETR": "–", "CAPE": "–", "GaussianDWM": "59.23", "GaussianDWM++": "62.71",
}  # fmt: skip


def layout(name: str = "nuinteract") -> LayoutConfig:
    return OmegaConf.to_object(load_config([f"compare={name}"]).compare)


def gdwm(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["compare", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def md_marks(md: str) -> tuple[dict[str, tuple[set[str], set[str]]], dict[str, list[str]]]:
    """Per metric column of a Markdown table: (bold rows, underlined rows), and the rows' cells as printed."""
    lines = [ln for ln in md.splitlines() if ln.startswith("| ")]
    head = [h.strip() for h in lines[0].strip("|").split("|")]
    cells = {}
    for ln in lines[2:]:
        parts = [c.strip() for c in re.split(r"(?<!\\)\|", ln.strip("|"))]
        cells[parts[0]] = parts
    first = head.index("RD&P BLEU ↑")
    marks = {}
    for k, name in enumerate(COLUMNS):
        col = first + k
        bold = {r for r, c in cells.items() if c[col].startswith("**")}
        under = {r for r, c in cells.items() if c[col].startswith("<u>")}
        marks[name] = (bold, under)
    plain = {r: [re.sub(r"\*\*|</?u>", "", x) for x in c[first:]] for r, c in cells.items()}
    return marks, plain


def test_the_one_average_rounds_the_printed_mean_half_up_exactly():
    minicpm = [47.92, 69.11, 70.20, 0.36, 0.49, 18.74, 1.97, 1.61, 0.93, 36.42]  # the paper's MiniCPM-V 2.6 row
    assert fmt(mean_of_printed(minicpm, 2), 2) == "24.78"  # 247.75 / 10 = 24.775 -> 24.78, half up
    # where a binary mean lands just under the tie, the exact one does not
    assert f"{sum([73.49, 54.16]) / 2!r}" == "63.824999999999996"
    assert fmt(mean_of_printed([73.49, 54.16], 2), 2) == "63.83"
    ten = [57.31, 0.63, 47.48, 1.16, 23.0, 10.43, 70.08, 36.39, 99.71, 64.96]  # exactly 41.115
    assert fmt(sum(ten) / 10, 2) == "41.11" and fmt(mean_of_printed(ten, 2), 2) == "41.12"
    assert mean_of_printed([-2.675, 3.0], 2) == pytest.approx(0.16)  # -2.68 (half up, away from 0) and 3.00


def test_an_average_column_is_the_mean_of_the_rows_printed_cells_with_the_seeds_spread():
    two = LayoutConfig(
        name="t",
        columns={"x/a": ColumnConfig(), "x/b": ColumnConfig(), "x/avg": ColumnConfig(mean_of=["x/a", "-x/b"])},
    )
    # per seed, the suite's average of the printed values: (1.00 - 1.00) / 2 = 0 and (1.01 - 1.00) / 2 = 0.005
    seeds = [{"x/a": 1.004, "x/b": 1.0, "x/avg": 0.0}, {"x/a": 1.006, "x/b": 1.0, "x/avg": 0.005}]
    trials = [Trial(f"t{k}", k, "FINISHED", m) for k, m in enumerate(seeds)]
    table = build_table([Row("r", "R", "FINISHED", "0", {}, trials=trials, planned=2)], two)
    assert [table.text(0, m) for m in ("x/a", "x/b")] == ["1.01 ± 0.00", "1.00 ± 0.00"]
    # the mean of the seeds' averages (0.0025) would print 0.00; the row's printed cells give (1.01 - 1.00) / 2
    avg = table.cell(0, "x/avg")
    assert (avg.mean, avg.std, avg.n) == (0.005, pytest.approx(0.005 / 2**0.5), 2)
    assert table.text(0, "x/avg") == "0.01 ± 0.00"
    partial = build_table([Row("r", "R", "FINISHED", "0", {}, trials=[Trial("t", 0, "FINISHED", {"x/avg": 3.0})])], two)
    assert partial.cell(0, "x/avg").mean == 3.0  # without its parts, a row keeps the average it logged


def test_a_published_table_through_gdwm_compare_gets_its_marks_and_averages(capsys, tmp_path):
    code, out, err = gdwm(
        capsys, f"workdir={tmp_path}", f"compare.references={PAPER}", f"args.out={tmp_path / 'out'}"
    )  # no store, no runs: a table of reported rows alone
    assert code == 0, err
    assert err == ""  # every published Avg. is the mean of its row's printed values
    md = (tmp_path / "out" / "nuinteract.md").read_text()
    marks, cells = md_marks(md)
    for name, (best, second) in PUBLISHED.items():
        assert marks[name] == ({best}, {second}), name
    assert {row: c[-1] for row, c in cells.items()} == PUBLISHED_AVG
    assert md.splitlines()[-3] == (
        "Bold: best; underlined: second. Marks by value in every column (reported values only); rows that print "
        "the same share. Cells: reported rows (with a source): the published value."
    )
    assert md.splitlines()[-1] == "Reported rows are copied from GaussianDWM++ Tab. vqa-main-nuinteract."
    assert "| MiniCPM-V 2.6 | MiniCPM (2024) | 47.92 |" in md
    # the same marks in LaTeX, CSV and HTML
    tex = (tmp_path / "out" / "nuinteract.tex").read_text()
    assert r"GaussianDWM++ & GaussianDWM++ (2026) & \textbf{69.81} & \textbf{81.75}" in tex
    assert r"PETR & PETR (2022) & -- & -- & -- & -- & -- & -- & \textbf{55.80} & 31.34" in tex
    rows = list(csv.DictReader(io.StringIO((tmp_path / "out" / "nuinteract.csv").read_text()), restkey="rest"))
    byrow = {r["row"]: r for r in rows if not r["row"].startswith("#")}
    assert byrow["MiniCPM-V 2.6"]["nuinteract/avg"] == "24.775" and byrow["MiniCPM-V 2.6"]["status"] == "reported"
    assert (byrow["DriveMonkey"]["nuinteract/plan_acc/mark"], byrow["CAPE"]["nuinteract/vg3d_pr/mark"]) == (
        "best",
        "second",
    )
    assert (byrow["CAPE"]["paper"], byrow["CAPE"]["year"], byrow["CAPE"]["run_id"]) == ("CAPE", "2023", "")
    html = (tmp_path / "out" / "nuinteract.html").read_text()
    assert "<strong>62.71</strong>" in html and "<u>59.23</u>" in html and '<tr class="reported">' in html
    # the terminal table, captured (not a terminal): marks as characters, nothing cut, and a legend that says so
    assert "62.71*" in out and "59.23†" in out and "82.64*" in out and "…" not in out
    flat = " ".join(out.split())
    assert (
        "* best; † second (after the value: bold and underline do not survive a log). Marks by value in every column "
        "(reported values only); rows that print the same share. Cells: reported rows (with a source): the published "
        "value. Reported rows are copied from GaussianDWM++ Tab. vqa-main-nuinteract."
    ) in flat


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return log_store(tmp_path_factory.mktemp("references"))


def test_the_published_values_logged_as_plain_runs_get_the_same_marks(capsys, store, tmp_path):
    # the reproduction: one run per published row, one metric per cell, one seed, no predictions
    b = store.backend()
    for ref in load_references(PAPER, layout()):
        run = b.create_run(ref.label, {"gdwm.kind": "run", "gdwm.row": ref.label, "gdwm.seed": "0", "paper": "1"})
        b.log_metrics(run, ref.values)
        b.end_run(run)
    args = ["args.filter=\"tags.paper = '1'\"", "args.formats=[markdown]", f"args.out={tmp_path}"]
    code, _, err = gdwm(capsys, f"workdir={store.workdir}", *args)
    assert code == 0, err
    md = (tmp_path / "nuinteract.md").read_text()
    marks, cells = md_marks(md)
    for name, (best, second) in PUBLISHED.items():
        assert marks[name] == ({best}, {second}), name
    assert {row: c[-1] for row, c in cells.items()} == PUBLISHED_AVG
    assert "Marks by value in every column (some row has neither per-sample data nor 2 seeds)" in md


def test_mixed_with_a_toy_sweep_toy_rows_by_significance_reported_rows_by_value(capsys, store, tmp_path):
    code, out, err = gdwm(
        capsys,
        f"workdir={store.workdir}",
        "args.sweep=abl",
        f"compare.references={PAPER}",
        "args.formats=[terminal,markdown]",
        f"args.out={tmp_path}",
    )
    assert code == 0, err
    md = (tmp_path / "nuinteract.md").read_text()
    marks, _ = md_marks(md)
    # BLEU: toy C 70.17 on top; GaussianDWM++ (reported, 69.81) next ends C's bold, so toy B (69.77), which Welch's
    # test cannot tell from C, is not bold: no row outranks a better value
    assert marks["BLEU"] == ({"C"}, {"GaussianDWM++"})
    # 2D mAP: toy B and D (48.50, not told apart) share the bold, then the reported 48.22 is second
    assert marks["2D mAP"] == ({"B", "D"}, {"GaussianDWM++"})
    # columns only reported rows fill: by value, as the paper
    assert marks["ROUGE-L"] == ({"GaussianDWM++"}, {"InternVL2-8B"})
    # Avg.: reported rows first (62.71, 59.23), then toy D 62.75 is on top: bold; 62.71 second
    assert marks["Avg."] == ({"D"}, {"GaussianDWM++"})
    legend = md.splitlines()[-3]
    assert legend.startswith(
        "Bold: best; underlined: second. Marks by significance in RD&P BLEU, 2D VG mAP, Plan Acc and Avg.: in value "
        "order, each row shares the mark of the row that opened it unless significantly worse than that row"
    )
    assert (
        "Marks by value in RD&P ROUGE-L, RD&P CIDEr, 2D VG F1, 2D VG mIoU, 3D VG Pr, 3D VG mAP and 3D VG F1 (" in legend
    )
    assert "Reported rows take part by value only: a test never extends a mark to or past them." in legend
    assert "reported rows (with a source): the published value" in legend
    assert "Welch's t-test over seeds; Holm over each column's" in legend
    # the terminal (captured) table: reported rows, a rule, then the sweep's rows; marks as characters
    lines = out.splitlines()
    llava = next(k for k, ln in enumerate(lines) if ln.startswith("│ LLaVA1.5"))
    a_row = next(k for k, ln in enumerate(lines) if ln.startswith("│ A "))
    assert llava < a_row and any(ln.startswith("├") for ln in lines[llava:a_row])
    assert "70.17*" in out and "…" not in out


def test_reported_rows_logged_as_runs_join_the_sweep_once(capsys, store, tmp_path):
    args = [f"workdir={store.workdir}", "args.sweep=abl", "args.formats=[csv]", f"args.out={tmp_path}"]
    code, out, err = gdwm(capsys, *args, f"compare.references={PAPER}", "args.log_references=true")
    assert code == 0, err
    assert f"logged 17 reported rows as runs tagged gdwm.kind=reference under sweep run {store.sweep_id}" in out
    code, out, _ = gdwm(capsys, *args, f"compare.references={PAPER}", "args.log_references=true")
    assert "logged 0 reported rows" in out  # the same rows are not logged twice
    rows = select(store.backend(), sweep="abl").rows  # without the file
    reported = [r for r in rows if r.reported]
    assert len(reported) == 17 and str(reported[0].source) == "LLaVA (2024)"
    assert reported[0].trials[0].metrics["nuinteract/rdp_bleu"] == 64.23
    code, _, err = gdwm(capsys, *args)
    table = list(csv.DictReader(io.StringIO((tmp_path / "nuinteract.csv").read_text())))
    assert [r["row"] for r in table[:2]] == ["LLaVA1.5", "MiniCPM-V 2"] and table[0]["status"] == "reported"
    assert next(r for r in table if r["row"] == "MiniCPM-V 2.6")["nuinteract/avg"] == "24.775"
    assert [r["row"] for r in table[17:23]] == ["A", "B", "C", "D", "E", "F"]


YAML = """\
- row: DriveMonkey
  paper: DriveMonkey
  table: Tab. 1
  year: 2025
  metrics:
    nuinteract/rdp_bleu: 67.50
    nuinteract/plan_acc: 82.64
- row: PETR
  paper: PETR
  year: 2022
  metrics: {nuinteract/vg3d_pr: 55.80, nuinteract/rdp_bleu: null}
"""


def test_yaml_references_read_as_the_csv(tmp_path):
    path = tmp_path / "refs.yaml"
    path.write_text(YAML)
    refs = load_references(path, layout())
    assert [(r.label, str(r.source), r.source.table, r.values, r.line) for r in refs] == [
        ("DriveMonkey", "DriveMonkey (2025)", "Tab. 1", {"nuinteract/rdp_bleu": 67.5, "nuinteract/plan_acc": 82.64}, 1),
        ("PETR", "PETR (2022)", "", {"nuinteract/vg3d_pr": 55.8}, 8),
    ]


HEADER = "row,paper,table,year,nuinteract/rdp_bleu,nuinteract/plan_acc\n"


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        (
            "refs.csv",
            "row,paper,nuinteract/bleu\nA,P,1.0\n",
            "refs.csv:1: field 'nuinteract/bleu': unknown metric 'nuinteract/bleu' for layout 'nuinteract' (its "
            "metrics: nuinteract/rdp_bleu, ",
        ),
        (
            "refs.csv",
            HEADER + "X,P,T,2024,1.0,2.0\nY,P,T,2024,6x.5,2.0\n",
            "refs.csv:3: field 'nuinteract/rdp_bleu': '6x.5' is not a number (leave the cell empty or '-' if missing)",
        ),
        ("refs.csv", HEADER + "X,P,T,2024,1,2\nY,P,T,2024,1,2\nX,P,T,2024,3,4\n",
         "refs.csv:4: field 'row': duplicate row label 'X' (first on line 2)"),
        ("refs.csv", HEADER + "X,,T,2024,1,2\n", "refs.csv:2: field 'paper': row 'X' needs its source paper"),
        ("refs.yaml", YAML.replace("nuinteract/plan_acc: 82.64", "nuinteract/plan: 82.64"),
         "refs.yaml:7: field 'nuinteract/plan': unknown metric 'nuinteract/plan' for layout 'nuinteract'"),
        ("refs.yaml", YAML.replace("55.80", "nan"), "refs.yaml:11: field 'nuinteract/vg3d_pr': 'nan' is not a number"),
        ("refs.yaml", YAML.replace("row: PETR", "row: DriveMonkey"),
         "refs.yaml:8: field 'row': duplicate row label 'DriveMonkey' (first on line 1)"),
        ("refs.yaml", YAML.replace("  year: 2022", "  yaer: 2022"),
         "refs.yaml:10: field 'yaer': unknown field (a row has row, paper, table, year, metrics)"),
        ("refs.txt", "", "refs.txt:0: field 'compare.references': a references file is .csv, .yaml or .yml"),
    ],
)  # fmt: skip
def test_a_bad_references_file_is_named_by_file_line_and_field(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ReferencesError) as e:
        load_references(path, layout())
    assert str(e.value).startswith(f"{path.parent}/{message}")


@pytest.mark.parametrize(
    ("name", "text", "line"),
    [("refs.csv", HEADER + "X,P,T,2024,1.0,n/a\n", "refs.csv:2: field 'nuinteract/plan_acc': 'n/a' is not a number"),
     ("refs.yaml", YAML.replace("nuinteract/plan_acc", "nuinteract/plan"), "refs.yaml:7: field 'nuinteract/plan'")],
)  # fmt: skip
def test_gdwm_compare_exits_2_on_a_bad_references_file(capsys, tmp_path, name, text, line):
    path = tmp_path / name
    path.write_text(text)
    code, out, err = gdwm(capsys, f"workdir={tmp_path}", f"compare.references={path}")
    assert (code, out) == (2, "")
    assert err.replace("\n", "").startswith(f"gdwm compare: {path.parent}/{line}")


def test_a_reported_label_clashing_with_a_sweep_row_exits_2(capsys, store, tmp_path):
    path = tmp_path / "refs.csv"
    path.write_text(HEADER + "Paper row,P,T,2024,1,2\nC,P,T,2024,1,2\n")
    code, out, err = gdwm(capsys, f"workdir={store.workdir}", "args.sweep=abl", f"compare.references={path}")
    assert code == 2 and out == ""
    assert (
        err.replace("\n", "") == f"gdwm compare: {path}:3: field 'row': label 'C' clashes with a row of args.sweep=abl"
    )


def test_a_published_average_that_is_not_the_mean_of_its_row_is_named(capsys, tmp_path):
    path = tmp_path / "refs.csv"
    shutil.copy(PAPER, path)
    path.write_text(path.read_text().replace("36.42,24.78", "36.42,24.77"))  # the binary-rounded Avg. of the issue
    code, _, err = gdwm(capsys, f"workdir={tmp_path}", f"compare.references={path}", "args.formats=[markdown]")
    assert code == 0
    assert err.replace("\n", "") == (
        f"gdwm compare: warning: {path}:4: field 'nuinteract/avg': Avg. 24.77 is not the mean of the row's printed "
        "values (24.78); the table shows 24.78"
    )
