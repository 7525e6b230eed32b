"""Light test stages (no torch, a few file writes each) with a sweep's shape: ``prep`` shared by every trial, ``fit``
and ``score`` per trial. Many drivers on one store (tests/gdwm/test_team_store.py) start their workers fast with them.
Failure injection as in tests/gdwm/stages.py (``tests/gdwm/inject.py``)."""

from __future__ import annotations

import json

from gdwm.stage import StageContext, stage
from tests.gdwm.inject import _inject, _record


def light_value(x: int, seed: int) -> float:
    """What ``score`` reports for a trial: a function of its row's ``x`` and its seed only."""
    return 10.0 * x + seed / 4


@stage("prep", "1", config=["stage.light_prep"])
def prep(ctx: StageContext) -> None:
    _record(ctx)
    _inject(ctx)
    (ctx.out_dir / "prep.txt").write_text(str(ctx.cfg("stage.light_prep")["base"]))


@stage("fit", "1", config=["stage.light_fit"], upstream=["prep"], seeded=True)
def fit(ctx: StageContext) -> None:
    _record(ctx)
    _inject(ctx)
    x = int(ctx.cfg("stage.light_fit")["x"])
    (ctx.out_dir / "fit.json").write_text(json.dumps({"value": light_value(x, ctx.seed)}))
    ctx.tracker.log_metrics({"loss": 1.0 / (1 + x)}, step=0)


@stage("score", "1", config=["stage.light_score"], upstream=["fit"], evaluation=True)
def score(ctx: StageContext) -> dict:
    _record(ctx)
    _inject(ctx)
    value = json.loads((ctx.upstream["fit"].path / "fit.json").read_text())["value"]
    return {"acc": value, "nuinteract/plan_acc": value}
