"""The environment record a launch computes once (``gdwm.environment``): its cost next to composing the launch's
config, which every launch pays too, and the cost of writing it (the record, the tags, each trial's config.yaml) to a
local sqlite store for a 5-trial launch.

Target: the record costs at most half of composing the config (measured side by side in this run), so recording
where a run ran never shows in a launch's start-up.
"""

from __future__ import annotations

import tempfile

from benchmarks.common import Result, median_time
from gdwm.config import load_config
from gdwm.environment.record import collect
from gdwm.environment.runs import log_launch

TARGET_RATIO = 0.5


def run(quick: bool = False) -> list[Result]:
    import torch  # a launch has imported it (gdwm.training) before it records: not part of the record's cost

    assert torch.__version__
    repeats = 3 if quick else 10
    t_record, _ = median_time(collect, repeats, warmup=1)
    t_config, _ = median_time(lambda: load_config(["experiment=demo"]), repeats, warmup=1)
    t_log = _log_launch(repeats)
    n = len(collect()["distributions"])
    return [
        Result(
            "environment",
            "record (collect once per launch)",
            t_record * 1e3,
            "ms",
            detail=f"{n} distributions, git state, torch build, median of {repeats}",
        ),
        Result("environment", "compose the launch's config (experiment=demo)", t_config * 1e3, "ms"),
        Result(
            "environment", "record / compose", t_record / t_config, "x", TARGET_RATIO, "<=", "side by side in this run"
        ),
        Result(
            "environment",
            "write it for a 5-trial launch (sqlite, in-process)",
            t_log * 1e3,
            "ms",
            detail="environment/<digest>.json, tags on 11 runs, 5 config.yaml",
        ),
    ]


def _log_launch(repeats: int) -> float:
    from gdwm.plan import PlanRow, Row, Trial
    from gdwm.tracking import TrackingBackend, TrackingClient

    cfg = load_config(["experiment=demo"])
    with tempfile.TemporaryDirectory() as tmp:
        backend = TrackingBackend(f"sqlite:///{tmp}/mlflow.db", "gdwm", f"{tmp}/art")
        tracking = TrackingClient(backend)
        parent = backend.create_run("sweep", {"gdwm.kind": "sweep"})
        trials = []
        for i in range(5):
            row = Row(i, f"row {i}", {}, [], [0], run_id=backend.create_run(f"row {i}", {}, parent))
            t = Trial(row, 0, cfg=cfg, plan=[PlanRow("lora", None, "k", "to run", "train")])
            t.run_id = backend.create_run(f"trial {i}", {}, row.run_id)
            trials.append(t)
        seconds, _ = median_time(lambda: log_launch(tracking, cfg, parent, trials), repeats, warmup=1)
        backend.close()
    return seconds
