"""The table's notes and title: official / approximate metrics and proxy data as the trials' evaluation stage runs
labelled them, the encoders each row used, in every format; values printed rounded half up."""

import pytest
from rich.console import Console

from gdwm.compare.layout import ColumnConfig, LayoutConfig
from gdwm.compare.render import to_csv, to_latex, to_markdown, to_rich
from gdwm.compare.report import html_report
from gdwm.compare.rounding import fmt, mean_of_printed, round_half_up
from gdwm.compare.runs import select
from gdwm.compare.table import build_table
from gdwm.tracking import TrackingBackend

ENCODERS = ["stage.distill.encoder", "stage.distill.feature_tokenizer"]
LAYOUT = LayoutConfig(
    name="nuinstruct",
    title="NuInstruct",
    columns={
        "nuinstruct/mae": ColumnConfig(header="MAE"),
        "nuinstruct/bleu": ColumnConfig(header="BLEU"),
        "nuinstruct/average_star": ColumnConfig(header="Average*"),
    },
    encoders=ENCODERS,
)
PROXY = "rows region_description stand in for NuInstruct's own data"
# row -> (encoder, feature tokenizer, metrics, the evaluation stage run's params)
ROWS = {
    "Distill ✗": (
        "langsplat_proxy",
        "clip3",
        {"nuinstruct/mae": 2.675, "nuinstruct/bleu": 30.0, "nuinstruct/average_star": 41.085},
        {"protocol/nuinstruct/mae": "approximate", "protocol/nuinstruct/bleu": "official",
         "protocol/nuinstruct/average_star": "approximate", "proxy/nuinstruct/bleu": PROXY},
    ),
    "Distill ✓": (
        "daisy",
        "foundation",
        {"nuinstruct/mae": 2.5, "nuinstruct/bleu": 31.0, "nuinstruct/average_star": 42.0},
        {"protocol/nuinstruct/mae": "approximate", "protocol/nuinstruct/bleu": "approximate",
         "protocol/nuinstruct/average_star": "approximate", "proxy/nuinstruct/bleu": PROXY},
    ),
}  # fmt: skip


def log_sweep(b: TrackingBackend, name: str, proxy: bool = True) -> None:
    """A sweep in the layout ``gdwm sweep`` writes: row runs, one trial each, linked to its evaluate_qa stage run."""
    sweep = b.create_run(f"sweep-{name}", {"gdwm.kind": "sweep", "gdwm.sweep": name})
    for i, (label, (encoder, tokenizer, metrics, params)) in enumerate(ROWS.items()):
        cfg = {"stage": {"distill": {"encoder": encoder, "feature_tokenizer": tokenizer}}}
        tags = {"gdwm.row": label, "gdwm.sweep": name}
        row = b.create_run(label, tags | {"gdwm.kind": "row", "gdwm.trial_index": str(i), "gdwm.seeds": "0"}, sweep)
        b.log_params(row, cfg)
        stage = b.create_run("evaluate_qa-x", {"gdwm.stage": "evaluate_qa", "gdwm.kind": "stage"}, sweep)
        b.log_params(stage, {k: v for k, v in params.items() if proxy or not k.startswith("proxy/")})
        b.end_run(stage)
        trial = b.create_run(f"{label}-0", tags | {"gdwm.kind": "trial", "gdwm.seed": "0"}, row)
        b.set_tags(trial, {"gdwm.stage_run.evaluate_qa": stage, "gdwm.stage_run.distill": row})
        b.log_params(trial, cfg)
        b.log_metrics(trial, metrics)
        b.end_run(trial)
        b.end_run(row)
    b.end_run(sweep)


@pytest.fixture(scope="module")
def backend(tmp_path_factory):
    d = tmp_path_factory.mktemp("notes")
    b = TrackingBackend(f"sqlite:///{d}/mlflow.db", "gdwm", str(d / "mlartifacts"))
    b.system_metrics_interval_s = 0
    log_sweep(b, "proxy")
    log_sweep(b, "real", proxy=False)
    return b


@pytest.fixture(scope="module")
def table(backend):
    return build_table(select(backend, sweep="proxy").rows, LAYOUT)


NOTES = [
    "Metrics. Approximate: MAE, Average*. Official in some trials, approximate in others: BLEU.",
    f"Proxy: BLEU: {PROXY}.",
    "Encoders (stage.distill.encoder, stage.distill.feature_tokenizer): Distill ✗ → langsplat_proxy, clip3; "
    "Distill ✓ → daisy, foundation.",
]


def test_rounding_is_half_up_on_the_printed_digits():
    values = [7.66, 27.14, 72.96, 56.58]  # their mean is 41.085 exactly
    assert f"{sum(values) / 4:.2f}" == "41.08"  # Python's float sum and rounding
    assert mean_of_printed(values, 2) == 41.085 and fmt(mean_of_printed(values, 2), 2) == "41.09"
    assert mean_of_printed([41.084, 41.086], 2) == 41.085  # the printed 41.08 and 41.09
    assert (round(2.675, 2), round_half_up(2.675, 2), fmt(-2.675, 2), fmt(0.125, 2, sign=True)) == (
        2.67, 2.68, "-2.68", "+0.13"
    )  # fmt: skip
    assert fmt(float("nan"), 2) == "nan"


def test_notes_come_from_the_evaluation_runs_and_the_params(table, backend):
    assert table.title == "NuInstruct (proxy)"
    assert table.notes == NOTES
    rows = select(backend, sweep="proxy").rows
    assert rows[0].trials[0].labels == {"nuinstruct/mae": "approximate", "nuinstruct/bleu": "official",
                                        "nuinstruct/average_star": "approximate"}  # fmt: skip
    assert table.text(0, "nuinstruct/mae") == "2.68" and table.text(0, "nuinstruct/average_star") == "41.09"


def test_no_proxy_in_title_or_caption_without_proxy_data(backend):
    real = build_table(select(backend, sweep="real").rows, LAYOUT)
    assert real.title == "NuInstruct"
    assert not any(line.startswith("Proxy") for line in real.caption)
    assert "(proxy)" not in to_markdown(real) and "(proxy)" not in to_latex(real)
    assert real.notes[0] == NOTES[0] and real.notes[1] == NOTES[2]


def test_every_format_prints_the_notes(table):
    md = to_markdown(table).splitlines()
    assert md[0] == "**NuInstruct (proxy)**"
    assert md[-5:] == [NOTES[0], "", NOTES[1], "", NOTES[2]]
    # one seed each, no per-sample data: no test can tell them apart, so marks go by value (auto)
    assert "| Distill ✗ | <u>2.68</u> | <u>30.00</u> | <u>41.09</u> |" in md
    tex = to_latex(table)
    assert "% NuInstruct (proxy) (needs \\usepackage{booktabs})" in tex
    assert f"% Note: {NOTES[1]}" in tex
    caption = tex.splitlines()[-1]
    assert (
        caption.startswith("% \\caption{NuInstruct (proxy). ")
        and "Distill ✗ $\\rightarrow$ langsplat\\_proxy" in caption
    )
    assert to_csv(table).splitlines()[-3:] == [f"# {n}" for n in NOTES]
    console = Console(record=True, width=400)
    console.print(to_rich(table))
    text = " ".join(console.export_text().split())  # rich wraps the caption to the table's width
    assert "NuInstruct (proxy)" in text and all(n in text for n in NOTES)
    html = html_report(table, 0, {}, "http://ui", "args.sweep=proxy", "sqlite:///x")
    assert "<title>NuInstruct (proxy)</title>" in html and "<h1>NuInstruct (proxy)</h1>" in html
    assert '<ul class="legend" id="notes"><li>Metrics. Approximate: MAE, Average*. Official in some trials' in html
    assert "<li>Encoders (stage.distill.encoder, stage.distill.feature_tokenizer): Distill ✗ → langsplat_proxy" in html
    assert "<li>Proxy: BLEU: rows region_description stand in for NuInstruct&#x27;s own data.</li>" in html
