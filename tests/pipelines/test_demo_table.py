"""`make demo`'s table shows learning: every metric column of the journal table is above 0 in some row (before the
instruction warm-up of the tiny LLM and grounding referents of at least one patch, 7 of 11 columns were 0.00 in every
row). The whole demo sweep, about 6 minutes on 2 cores: `make test-all`."""

from __future__ import annotations

import re

import pytest

from tests.pipelines.conftest import gdwm_cli

pytestmark = pytest.mark.slow

CELL = re.compile(r"^\**(?:<u>)?(-?\d+\.\d+) \[")


def test_every_metric_column_of_the_demo_table_learns(tmp_path):
    out = gdwm_cli(
        "sweep", "sweep=journal_ablation", "experiment=demo", f"workdir={tmp_path / 'w'}", timeout=3000
    ).stdout
    lines = [ln for ln in out.splitlines() if ln.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    metrics = [i for i, h in enumerate(header) if h.endswith(("↑", "↓"))]
    assert len(metrics) == 11, header
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]
    assert len(rows) == 5
    values = {header[i]: [float(CELL.match(r[i]).group(1)) for r in rows] for i in metrics}
    assert [h for h, v in values.items() if max(v) <= 0] == []
