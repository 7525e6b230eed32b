"""`make demo`'s table shows learning: every metric column of the journal table is above 0 in some row (before the
instruction warm-up of the tiny LLM and grounding referents of at least one patch, the README's table had 2D VG mAP,
2D VG F1 and Plan Acc at 0.00 in every row, and the issue's run 7 of the 11 columns). The whole demo sweep
(``demo_sweep``, tests/pipelines/conftest.py): five trials, 5-10 minutes on 2 cores."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytestmark = [pytest.mark.heavy(6), pytest.mark.timeout(3000)]

CELL = re.compile(r"^\**(?:<u>)?(-?\d+\.\d+) \[")


def metric_columns(report: Path) -> dict[str, list[float]]:
    """Header -> the rows' values of every metric column (cells "value [low, high]", marked or not) of a markdown
    report table."""
    lines = [ln for ln in report.read_text().splitlines() if ln.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]
    return {h: [float(CELL.match(r[i]).group(1)) for r in rows] for i, h in enumerate(header) if h.endswith(("↑", "↓"))}


def test_every_metric_column_of_the_demo_table_learns(demo_sweep):
    assert "sweep: 5 trials" in demo_sweep.stdout
    columns = metric_columns(demo_sweep.work / "reports" / "journal_ablation" / "nuinteract.md")
    assert len(columns) == 11 and {len(v) for v in columns.values()} == {5}
    assert [h for h, v in columns.items() if max(v) <= 0] == []
