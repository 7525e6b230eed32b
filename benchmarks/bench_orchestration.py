"""Orchestration overhead: a platform stage vs a bare Ray task; the same stage with its cache on S3 (a loopback moto
server, real HTTP through pyarrow's S3FileSystem) vs a local disk; a cached 5-trial x 6-stage re-run vs Ray Tune.

Both sides run in the same Ray session, side by side, medians over repeats.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import tempfile
from collections.abc import Iterator
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


@contextlib.contextmanager
def moto_s3(bucket: str) -> Iterator[str]:
    """A moto S3 server on 127.0.0.1 holding ``bucket``; yields its ``host:port``."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        boto3.client("s3", endpoint_url=f"http://{host}:{port}", region_name="us-east-1", **S3_KEYS).create_bucket(
            Bucket=bucket
        )
        yield f"{host}:{port}"
    finally:
        server.stop()


S3_KEYS = {"aws_access_key_id": "bench", "aws_secret_access_key": "bench-not-a-secret"}
"""moto accepts any key; the stage tasks get them as the environment variables pyarrow reads."""


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
        # Both caches run on workers of the same runtime env: the S3 side needs its keys there.
        worker_env = {
            "AWS_ACCESS_KEY_ID": S3_KEYS["aws_access_key_id"],
            "AWS_SECRET_ACCESS_KEY": S3_KEYS["aws_secret_access_key"],
            "GDWM_LOCAL_CACHE": str(tmp / "local-copies"),
        }
        opts = {"num_cpus": 1, "runtime_env": {"env_vars": worker_env}}
        counter = iter(range(10**6))

        def platform_miss(env: RunEnv):
            i = next(counter)
            ray.get(run_stage.options(**opts).remote(s1, {"stage.s1": {"i": i}}, env))

        def platform_hit(env: RunEnv):
            ray.get(run_stage.options(**opts).remote(s1, {"stage.s1": {"i": 0}}, env))

        t_bare, _ = median_time(lambda: ray.get(_bare_noop.options(**opts).remote(1)), n, warmup=3)
        t_miss, _ = median_time(lambda: platform_miss(env), n, warmup=2)
        t_hit, _ = median_time(lambda: platform_hit(env), n, warmup=2)
        with moto_s3("gdwm") as endpoint:
            s3_env = dataclasses.replace(env, cache_uri=f"s3://gdwm/cache?endpoint_override={endpoint}&scheme=http")
            t_miss_s3, _ = median_time(lambda: platform_miss(s3_env), n, warmup=2)
            t_hit_s3, _ = median_time(lambda: platform_hit(s3_env), n, warmup=2)
    finally:
        close()
    detail = f"median of {n} no-op stages; sqlite store via the tracking actor"
    s3_detail = f"median of {n}, same stage and session; moto server mode on 127.0.0.1, pyarrow S3FileSystem"
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
        Result("orchestration", "stage executed, cache on S3 (moto)", t_miss_s3 * 1e3, "ms", detail=s3_detail),
        Result("orchestration", "stage cached, cache on S3 (moto)", t_hit_s3 * 1e3, "ms", detail=s3_detail),
        Result("orchestration", "executed stage: S3 / local cache", t_miss_s3 / t_miss, "x", detail=s3_detail),
        Result("orchestration", "cached stage: S3 / local cache", t_hit_s3 / t_hit, "x", detail=s3_detail),
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
            ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
        try:
            out = bench_stage_overhead(tmp, meta, 10 if quick else 20)
            out += bench_cached_rerun_vs_tune(tmp, 2 if quick else 3)
        finally:
            if started:
                ray.shutdown()
    return out
