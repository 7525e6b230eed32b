"""The dashboard in headless Chromium against real stores, each test saving a screenshot of the page it checks.

One toy store serves the module (the cheapest way to see everything): ``sweep=toy_grid`` (2 rows x 2 LoRA ranks, the
negative rank fails at lora) is launched in the background with reconstruct held (``GDWM_TEST_BLOCK``); the
dashboard opens on it while no trial is done, the stage is released, and the page is watched, never reloaded, until
the sweep ends and its table is computed. Three ``gdwm regress benchmark=toy_nightly`` runs then go into the same
workdir. Screenshots: ``<pytest tmp>/ui-shots/*.png`` (the path is printed).
"""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gdwm.compare.rounding import fmt
from tests.gdwm.test_run import Toy
from tests.gdwm.ui.dash import browser, dashboard, env

TRIALS = 4  # toy_grid: short/long x rank 3/-1
# The module's store is a real toy sweep, its table a real bootstrap and three real regressions: on 2 loaded cores
# its setup alone can pass the suite's 600 s per test.
pytestmark = [pytest.mark.timeout(2400), pytest.mark.heavy(2.5)]


def _wait_file(path: Path, proc: subprocess.Popen, timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if proc.poll() is not None:
            pytest.fail(f"the sweep exited {proc.returncode} before {path.name}: {proc.stderr.read()[-3000:]}")
        assert time.monotonic() < deadline, f"{path} did not appear within {timeout_s} s"
        time.sleep(0.2)


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("ui-shots")
    print(f"screenshots: {d}")
    return d


@pytest.fixture(scope="module")
def live(tmp_path_factory, shots):
    """The toy_grid sweep watched live from the dashboard: what the page showed, in order, and the open page."""
    toy = Toy(tmp_path_factory.mktemp("grid"))
    args = [
        sys.executable,
        "-m",
        "gdwm",
        "sweep",
        "sweep=toy_grid",
        f"workdir={toy.work}",
        f"data.root={toy.data}",
        "run.snapshot_s=1",
    ]
    sweep = subprocess.Popen(
        args,
        env=env(GDWM_TEST_DIR=str(toy.root), GDWM_TEST_BLOCK="reconstruct"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    seen: dict = {"done": []}
    try:
        _wait_file(toy.root / "blocked-reconstruct", sweep)
        with dashboard(f"workdir={toy.work}") as dash, browser() as page:
            page.goto(dash.url)
            seen["first"] = page.inner_text("#trials-done")
            page.screenshot(path=shots / "live-0-held.png", full_page=True)
            page.evaluate("window.__notReloaded = true")
            (toy.root / "release").touch()
            states: set[str] = set()
            deadline = time.monotonic() + 600
            while True:  # the page updates itself: read what it shows, never reload it
                done = page.inner_text("#trials-done")
                if not seen["done"] or seen["done"][-1] != done:
                    seen["done"].append(done)
                states |= set(page.eval_on_selector_all("#trial-grid td.cell", "tds => tds.map(t => t.dataset.state)"))
                if "failed" in states and "screenshot-failed" not in seen:
                    seen["screenshot-failed"] = True
                    page.screenshot(path=shots / "live-1-failed.png", full_page=True)
                if done == f"2/{TRIALS}" and sweep.poll() is not None:
                    break
                assert time.monotonic() < deadline, f"the page still shows {done} trials done"
                page.wait_for_timeout(500)
            seen["states"] = states
            seen["sweep_rc"] = sweep.returncode
            # the final table, computed by compare's code once every trial has finished (not one of the tables of
            # the trials finished so far, which the page shows "updating" meanwhile)
            page.wait_for_function(
                "document.querySelector('#results') && !document.querySelector('#table-status')", timeout=900_000
            )
            seen["reloaded"] = not page.evaluate("window.__notReloaded === true")
            page.screenshot(path=shots / "live-2-table.png", full_page=True)
            yield {"toy": toy, "dash": dash, "page": page, "seen": seen}
    finally:
        if sweep.poll() is None:
            sweep.kill()


def test_trials_done_rise_without_a_reload_then_the_table(live):
    seen = live["seen"]
    assert seen["first"] == f"0/{TRIALS}"  # reconstruct held: nothing is done
    assert seen["done"][0] == f"0/{TRIALS}" and seen["done"][-1] == f"2/{TRIALS}"
    assert [int(d.split("/")[0]) for d in seen["done"]] == sorted(int(d.split("/")[0]) for d in seen["done"])
    assert seen["reloaded"] is False
    assert {"failed", "blocked", "done"} <= seen["states"]
    assert live["page"].inner_text("#trials-failed") == "2"
    assert seen["sweep_rc"] == 1  # a failed trial makes the sweep exit 1


def test_a_failing_trial_shows_its_one_line_cause_and_blocked_downstream(live, shots):
    page = live["page"]
    causes = page.eval_on_selector_all("#failures .cause", "els => els.map(e => e.innerText)")
    assert causes and all(
        c == "stage 'lora' failed: ValueError: stage.toy_lora.rank must be >= 0, got -1" for c in causes
    )
    assert all("\n" not in c for c in causes)
    rows = page.eval_on_selector_all(
        "#trial-grid tbody tr",
        "trs => trs.map(tr => [tr.dataset.trial, Object.fromEntries([...tr.querySelectorAll('td.cell')]"
        ".map(td => [td.dataset.stage, td.dataset.state]))])",
    )
    bad = {label: cells for label, cells in rows if "rank=-1" in label}
    assert len(bad) == 2
    for cells in bad.values():
        assert cells["lora"] == "failed" and cells["evaluate_qa"] == "blocked"
    good = {label: cells for label, cells in rows if "rank=3" in label}
    assert all(c["evaluate_qa"] == "done" for c in good.values()) and len(good) == 2
    page.locator("#progress").screenshot(path=shots / "failure-cause.png")


def _expected(row: dict[str, str], metric: str, failed: bool) -> str:
    mean = row[metric]
    if not mean:
        return "–"
    text = fmt(float(mean), 2)
    if failed:
        return text
    if row[f"{metric}/std"]:
        text += f" ± {fmt(float(row[f'{metric}/std']), 2)}"
    elif row[f"{metric}/ci_low"] and row[f"{metric}/ci_high"]:
        text += f" [{fmt(float(row[f'{metric}/ci_low']), 2)}, {fmt(float(row[f'{metric}/ci_high']), 2)}]"
    return text


def _check_table(page, csv_path: Path) -> int:
    """The page's table against ``gdwm compare``'s CSV: every value with its interval, and every mark; returns the
    number of marks seen."""
    text = csv_path.read_text()
    rows = list(csv.DictReader(io.StringIO("".join(ln for ln in text.splitlines(True) if not ln.startswith("#")))))
    metrics = [k for k in rows[0] if "/" in k and k.rsplit("/", 1)[1] not in ("std", "n", "ci_low", "ci_high", "mark")]
    shown = page.eval_on_selector_all(
        "#results tbody tr",
        "trs => trs.map(tr => [tr.dataset.row, Object.fromEntries([...tr.querySelectorAll('td.num')]"
        ".map(td => [td.dataset.metric, [td.innerText.replace(/\\s+/g, ' ').trim(), td.dataset.mark]]))])",
    )
    assert [label for label, _ in shown] == [r["row"] for r in rows]
    compared = 0
    for (label, cells), row in zip(shown, rows, strict=True):
        failed = row["status"] == "FAILED"
        for m in metrics:
            assert m in cells, (label, m)
            assert cells[m] == [_expected(row, m, failed), row[f"{m}/mark"]], (label, m)
            compared += 1
    assert compared == len(rows) * len(metrics) and any(row[m] for row in rows for m in metrics)
    legend = page.inner_text("#legend")
    caption = [ln[2:] for ln in text.splitlines() if ln.startswith("# ")]
    assert caption and all(line in legend for line in caption)
    return sum(bool(mark) for _, cells in shown for _, mark in cells.values())


def _current_table(page, url: str) -> None:
    page.goto(url)
    page.wait_for_function(
        "document.querySelector('#results') && !document.querySelector('#table-status')", timeout=900_000
    )


def test_the_table_equals_gdwm_compares_csv_cell_for_cell(live, shots):
    """The CSVs ``gdwm sweep`` wrote at its end with ``gdwm compare``: toy_grid's (two failed rows, two equal live
    ones: no mark), then toy_ablation's (three ranks: marks), swept into the same store."""
    page, toy = live["page"], live["toy"]
    assert _check_table(page, toy.work / "reports" / "toy_grid" / "nuinteract.csv") == 0
    page.locator("#results-section").screenshot(path=shots / "table-grid.png")
    r = subprocess.run([sys.executable, "-m", "gdwm", "sweep", "sweep=toy_ablation", f"workdir={toy.work}",
                        f"data.root={toy.data}"], env=env(GDWM_TEST_DIR=str(toy.root)), capture_output=True,
                       text=True, timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    page.goto(live["dash"].base + "/")
    href = page.get_attribute("#list-sweep a:text('toy_ablation')", "href")
    _current_table(page, live["dash"].base + href)
    assert _check_table(page, toy.work / "reports" / "toy_ablation" / "nuinteract.csv") >= 1
    # at 1280 px the row labels stay at the left edge and the key metric at the right edge, scrolled or not
    for scroll in ("0", "1e6"):
        page.evaluate(f"document.querySelector('.tablewrap').scrollLeft = {scroll}")
        edges = page.evaluate(
            "() => [...document.querySelectorAll('#results tbody tr')].map(tr => [tr.querySelector('.pin-left')"
            ".getBoundingClientRect().left, tr.querySelector('td.pin-right').getBoundingClientRect().right])"
        )
        assert all(0 <= left < 40 and 1200 < right <= 1280 for left, right in edges), (scroll, edges)
    page.locator("#results-section").screenshot(path=shots / "table-ablation.png")
    _current_table(page, live["dash"].url)  # back to toy_grid for the tests after


def test_downloads_are_compares_outputs(live):
    page, toy = live["page"], live["toy"]
    base = live["dash"].base
    sweep_id = live["dash"].url.rsplit("/", 1)[1]
    got = page.request.get(f"{base}/sweeps/{sweep_id}/download/md")
    assert got.status == 200 and got.text() == (toy.work / "reports" / "toy_grid" / "nuinteract.md").read_text()
    csv_text = page.request.get(f"{base}/sweeps/{sweep_id}/download/csv").text()
    assert csv_text == (toy.work / "reports" / "toy_grid" / "nuinteract.csv").read_text()


def test_home_lists_the_sweep_newest_first(live, shots):
    page = live["page"]
    page.goto(live["dash"].base + "/")
    rows = page.eval_on_selector_all("#list-sweep tbody tr", "trs => trs.map(tr => tr.innerText)")
    assert [r.split("\t")[0] for r in rows] == ["toy_ablation", "toy_grid"]  # newest first
    assert f"2/{TRIALS} (2 failed)" in rows[1] and "3/3" in rows[0]
    page.fill("input[name=q]", "nothing-like-it")
    page.click("button[type=submit]")
    assert page.eval_on_selector_all("#list-sweep tbody tr", "trs => trs.length") == 0
    page.goto(live["dash"].base + "/")
    page.screenshot(path=shots / "home.png", full_page=True)


def test_a_trial_page_says_how_and_why_each_stage_ran(live, shots):
    page = live["page"]
    page.goto(live["dash"].base + "/")
    page.goto(live["dash"].url)
    page.click("#trial-grid a:text('long, stage.toy_lora.rank=3')")
    page.wait_for_selector("#stages")
    assert page.inner_text("#trial-name") == "long, stage.toy_lora.rank=3"
    how = dict(page.eval_on_selector_all("#stages tbody tr", "trs => trs.map(tr => [tr.dataset.stage,"
                                         " tr.querySelector('.badge').innerText])"))  # fmt: skip
    assert how == {"reconstruct": "shared", "distill": "shared", "tokenizer": "done", "lora": "done",
                   "evaluate_qa": "done"}  # fmt: skip
    # why it ran, in the dry run's words, from the cache's manifests (a worker process answers)
    page.wait_for_function("[...document.querySelectorAll('td.why')].every(td => td.innerText.trim() !== '…')",
                           timeout=300_000)  # fmt: skip
    why = dict(page.eval_on_selector_all("td.why", "tds => tds.map(td => [td.dataset.stage, td.innerText])"))
    # against the short row's tokenizer where that entry came first (the two run side by side)
    assert why["tokenizer"] in (
        "config: stage.toy_tokenizer.steps 2 -> 4",
        "first computation (no earlier entry of the stage)",
    )
    assert all(why[s] and "no cache entry" not in why[s] for s in ("tokenizer", "lora", "evaluate_qa"))
    diff = page.eval_on_selector_all("#diff tbody tr", "trs => trs.map(tr => tr.cells[0].innerText)")
    assert "stage.toy_tokenizer.steps" in diff
    page.screenshot(path=shots / "trial.png", full_page=True)


def test_regressions_show_each_check_over_three_runs_with_baseline_and_band(live, shots):
    toy = live["toy"]
    base = [
        sys.executable,
        "-m",
        "gdwm",
        "regress",
        "benchmark=toy_nightly",
        f"workdir={toy.work}",
        f"data.root={toy.data}",
    ]
    for extra in (["--set-baseline"], [], ["experiment=toy", "stage.toy_lora.rank=1"]):  # the last one regresses
        r = subprocess.run(
            [*base, *extra], env=env(GDWM_TEST_DIR=str(toy.root)), capture_output=True, text=True, timeout=600
        )
        assert r.returncode in (0, 1), r.stderr[-3000:]
    page = live["page"]
    page.goto(live["dash"].base + "/regressions")
    page.wait_for_function("document.querySelectorAll('.chart.trend .main-svg').length >= 2")
    charts = page.eval_on_selector_all(
        ".chart.trend",
        "els => els.map(e => [e.dataset.metric, e.data[0].y.length, e.layout.shapes.length,"
        " e.data[0].marker.line.width.filter(w => w > 0).length])",
    )
    assert sorted(m for m, *_ in charts) == ["nuinstruct/mae", "nuinteract/plan_acc"]
    for metric, points, shapes, ringed in charts:
        assert points == 3, metric  # three runs
        assert shapes == 2, metric  # the baseline line and its tolerance band
        assert ringed == 1, metric  # the baseline run
    verdicts = page.eval_on_selector_all("#verdicts-toy_nightly tbody tr", "trs => trs.map(tr => tr.className)")
    assert verdicts == ["fail", "", ""]  # newest first: the planted regression stands out
    crosses = page.eval_on_selector_all(
        ".chart.trend", "els => els.map(e => e.data[0].marker.symbol.filter(s => s === 'x').length)"
    )
    assert max(crosses) == 1  # its failed check, a red cross on the newest point
    figure = json.loads(page.get_attribute(".chart.trend", "data-figure"))
    assert figure["layout"]["shapes"][1]["type"] == "rect"
    page.screenshot(path=shots / "regressions.png", full_page=True)
