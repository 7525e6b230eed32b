"""Orchestration overhead: a platform stage vs a bare Ray task; a cached 5-trial x 6-stage re-run vs Ray Tune.

Both sides run in the same Ray session, side by side, medians over repeats.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import ray
from ray import tune

from benchmarks.common import Result, median_time
from gdwm.config import TrackingConfig, load_config
from gdwm.executor import RunEnv, run_stage
from gdwm.runner import run_pipeline
from gdwm.tracking import open_tracking
from tests.gdwm.toydata import make_dataset

CONF = Path(__file__).resolve().parent / "conf"


@ray.remote
def _bare_noop(i: int) -> int:
    return i


def bench_stage_overhead(tmp: Path, meta: dict, n: int) -> list[Result]:
    from benchmarks.noop_stages import s1

    tracking = TrackingConfig(uri=f"sqlite:///{tmp}/mlflow-overhead.db", artifact_location=str(tmp / "art"))
    sink, close = open_tracking(tracking)
    try:
        env = RunEnv(
            cache_uri=str(tmp / "cache-overhead"),
            data_root=str(tmp / "ds"),
            data_fingerprint=meta["fingerprint"],
            scenes=tuple(meta["scenes"]),
            checkpoint_root=str(tmp / "ckpt"),
            sink=sink,
            parent_run_id=None,
            progress=None,
            resources={"cpu": {"num_cpus": 1, "num_gpus": 0, "num_workers": 1}},
        )
        counter = iter(range(10**6))

        def platform_miss():
            i = next(counter)
            ray.get(run_stage.options(num_cpus=1).remote(s1, {"stage.s1": {"i": i}}, env))

        def platform_hit():
            ray.get(run_stage.options(num_cpus=1).remote(s1, {"stage.s1": {"i": 0}}, env))

        t_bare, _ = median_time(lambda: ray.get(_bare_noop.options(num_cpus=1).remote(1)), n, warmup=3)
        t_miss, _ = median_time(platform_miss, n, warmup=2)
        t_hit, _ = median_time(platform_hit, n, warmup=2)
    finally:
        close()
    detail = f"median of {n} no-op stages; sqlite store via the tracking actor"
    return [
        Result("orchestration", "bare Ray task", t_bare * 1e3, "ms", detail=detail),
        Result("orchestration", "stage executed (lookup+run+track+publish)", t_miss * 1e3, "ms", detail=detail),
        Result(
            "orchestration",
            "platform overhead per executed stage",
            (t_miss - t_bare) * 1e3,
            "ms",
            50.0,
            "<=",
            "executed stage minus bare task",
        ),
        Result(
            "orchestration",
            "platform overhead per cached stage",
            (t_hit - t_bare) * 1e3,
            "ms",
            50.0,
            "<=",
            "cache hit (verified) minus bare task",
        ),
    ]


def _tune_noop(config: dict) -> dict:
    return {"score": config["x"]}


def bench_cached_rerun_vs_tune(tmp: Path, repeats: int) -> list[Result]:
    trials = [
        load_config(
            [
                "pipeline=noop6",
                f"workdir={tmp}/work",
                f"data.root={tmp}/ds",
                *(f"+stage.s{k}.x=0" for k in (1, 2, 3, 5, 6)),
                f"+stage.s4.x={t}",
                "run.live=false",
            ]
        )
        for t in range(5)
    ]
    for cfg in trials:  # populate the cache: 3 shared stages + 5 x 3 trial stages
        summary = run_pipeline(cfg, live=False)
        assert summary.ok, summary.failed

    def platform():
        for cfg in trials:
            run_pipeline(cfg, live=False)

    def tuner():
        tune.Tuner(
            _tune_noop,
            param_space={"x": tune.grid_search(list(range(5)))},
            run_config=tune.RunConfig(storage_path=str(tmp / "tune"), verbose=0),
        ).fit()

    t_gdwm, _ = median_time(platform, repeats, warmup=1)
    t_tune, _ = median_time(tuner, repeats, warmup=1)
    return [
        Result("orchestration", "cached re-run, 5 trials x 6 stages (gdwm)", t_gdwm, "s"),
        Result("orchestration", "Ray Tune grid, 5 no-op trials", t_tune, "s"),
        Result(
            "orchestration",
            "Tune / cached gdwm re-run (speed-up)",
            t_tune / t_gdwm,
            "x",
            2.0,
            ">=",
            f"median of {repeats}, same Ray session",
        ),
    ]


def run(quick: bool = False) -> list[Result]:
    os.environ["GDWM_CONF_PATH"] = str(CONF)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        meta = json.loads((make_dataset(tmp / "ds", scenes=1) / "dataset.json").read_text())
        started = not ray.is_initialized()
        if started:
            ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        try:
            out = bench_stage_overhead(tmp, meta, 10 if quick else 20)
            out += bench_cached_rerun_vs_tune(tmp, 2 if quick else 3)
        finally:
            if started:
                ray.shutdown()
    return out
