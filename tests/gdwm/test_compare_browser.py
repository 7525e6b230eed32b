"""The HTML report of ``gdwm compare`` in headless Chromium (from disk): the table renders with its cells' uncertainty,
its marks and its legend, and every plot loads. Skips when Debian's chromium or the playwright package is missing."""

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
    r = subprocess.run(
        [sys.executable, "-m", "gdwm", "compare", f"workdir={store.workdir}", "args.sweep=abl", "args.formats=[html]"],
        capture_output=True,
        text=True,
    )
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
        browser.close()
    assert [r[0] for r in rows] == ["A", "B", "C", "D", "E", "F"]
    # row, two factors, 11 NuInteract columns, note
    assert rows[2][:4] == ["C", "Driving-Aware", "KL", "70.17 ± 0.75"] and len(rows[2]) == 15
    assert rows[2][6] == "–"  # C logged no 2D mAP
    assert rows[3][6] == "48.50 ± 1.41 (n=2)"  # D: 2 of 3 seeds finished
    assert rows[4][-1] == "failed at lora: RuntimeError: CUDA out of memory"
    assert sorted(bold) == ["48.50 ± 0.50", "48.50 ± 1.41 (n=2)", "62.75 ± 0.07 (n=2)", "69.77 ± 0.75", "70.17 ± 0.75"]
    assert sorted(underlined) == ["35.00 ± 1.00", "61.23 ± 0.25", "61.43 ± 0.15", "65.30 ± 0.42 (n=2)"]
    assert legend.startswith("Bold: best; underlined: second. Rows whose difference is not significant share a mark")
    assert "(Welch's t-test over seeds, α = 0.05)" in legend and "(n=k): k of 3 seeds finished." in legend
    assert len(images) == 4  # radar, bars, deltas, training curves
    assert all(complete and w > 0 and h > 0 for complete, w, h in images), images
    assert all(href.startswith("http://127.0.0.1:5001/#/experiments/") for href in links) and len(links) == 6
