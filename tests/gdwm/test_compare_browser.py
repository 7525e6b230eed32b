"""The HTML report of ``gdwm compare`` in headless Chromium (from disk): the table renders with its cells' uncertainty,
its marks, its reported rows and its legend, and every plot loads. Skips when Debian's chromium or the playwright
package is missing."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.gdwm.compare_runs import log_store

CHROMIUM = "/usr/bin/chromium" if Path("/usr/bin/chromium").is_file() else shutil.which("chromium")
playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e '.[dev]')")
if CHROMIUM is None:
    pytest.skip("chromium is not installed (apt-get install chromium)", allow_module_level=True)


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    store = log_store(tmp_path_factory.mktemp("browser"))
    paper = Path(__file__).parents[2] / "conf" / "compare" / "references" / "nuinteract_paper.csv"
    lines = paper.read_text().splitlines()
    refs = store.workdir / "refs.csv"
    refs.write_text("\n".join([lines[0], lines[12], lines[-1]]) + "\n")  # DriveMonkey and GaussianDWM++
    r = subprocess.run(
        [sys.executable, "-m", "gdwm", "compare", f"workdir={store.workdir}", "args.sweep=abl", "args.formats=[html]",
         f"compare.references={refs}"],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    return store.workdir / "reports" / "abl" / "nuinteract.html"


def test_report_renders_table_and_loads_every_plot(report):
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(headless=True, executable_path=CHROMIUM)
        page = browser.new_page()
        page.goto(report.as_uri())
        rows = page.eval_on_selector_all(
            "#results tbody tr", "trs => trs.map(tr => [...tr.cells].map(td => td.innerText.trim()))"
        )
        bold = page.eval_on_selector_all("#results strong", "els => els.map(e => e.innerText)")
        underlined = page.eval_on_selector_all("#results u", "els => els.map(e => e.innerText)")
        images = page.eval_on_selector_all(
            "img", "imgs => imgs.map(i => [i.complete, i.naturalWidth, i.naturalHeight])"
        )
        links = page.eval_on_selector_all("#results tbody a", "as => as.map(a => a.href)")
        legend = page.inner_text("#legend")
        reported = page.eval_on_selector_all("#results tr.reported", "trs => trs.map(tr => tr.cells[0].innerText)")
        style = page.eval_on_selector("#results tr.block-end td", "td => getComputedStyle(td).borderBottomWidth")
        page.screenshot(path=str(report.parent / "report.png"), full_page=True)
        browser.close()
    assert [r[0] for r in rows] == ["DriveMonkey", "GaussianDWM++", "A", "B", "C", "D", "E", "F"]
    assert reported == ["DriveMonkey", "GaussianDWM++"] and style == "2px"  # a rule under the reported block
    # row, two factors, source, 11 NuInteract columns, note
    assert rows[1][:5] == ["GaussianDWM++", "", "", "GaussianDWM++ (2026)", "69.81"] and len(rows[1]) == 16
    assert rows[4][:5] == ["C", "Driving-Aware", "KL", "", "70.17 ± 0.75"]
    assert rows[4][7] == "–"  # C logged no 2D mAP
    assert rows[5][7] == "48.50 ± 1.41 (n=2)"  # D: 2 of 3 seeds finished
    assert rows[6][-1] == "failed at lora: RuntimeError: CUDA out of memory"
    # toy rows by significance, reported rows by value; GaussianDWM++ (reported) sits between C and B in BLEU
    assert sorted(bold) == [
        "35.13", "41.92", "48.50 ± 0.50", "48.50 ± 1.41 (n=2)", "53.32", "57.19", "62.75 ± 0.07 (n=2)", "70.17 ± 0.75",
        "77.83", "80.42", "81.75", "82.64",
    ]  # fmt: skip
    assert sorted(underlined) == [
        "20.86", "24.02", "34.53", "48.22", "51.90", "59.36", "62.71", "69.81", "79.79", "81.15", "81.52"
    ]  # fmt: skip
    assert "69.77 ± 0.75" not in bold + underlined  # below the reported 69.81: it cannot share C's bold
    assert legend.startswith("Bold: best; underlined: second. Marks by significance in RD&P BLEU, 2D VG mAP, ")
    assert "Reported rows take part by value only" in legend and "(n=k): k of 3 seeds finished." in legend
    assert len(images) == 4  # radar, bars, deltas, training curves
    assert all(complete and w > 0 and h > 0 for complete, w, h in images), images
    assert all(href.startswith("http://127.0.0.1:5001/#/experiments/") for href in links) and len(links) == 6
