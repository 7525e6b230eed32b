"""Test-only stages with the real pipeline's shape; behaviour injected through the GDWM_TEST_* environment
variables ``tests/gdwm/inject.py`` lists (executions logged, a worker killed, a scene failed, a stage held, memory
or disk filled)."""

from __future__ import annotations

import json
import math
import os
import signal
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gdwm.stage import StageContext, stage
from tests.gdwm.inject import _block, _inject, _once, _record, _test_dir


def _setup(cfg: dict) -> dict:
    # Stands in for a heavy model: counts how often actors load it.
    # "<pid> <actor id>": a restarted actor keeps its id in a new process, so a retried setup shows as a repeated id
    import ray

    with open(_test_dir() / "setups.log", "a") as f:
        f.write(f"{os.getpid()} {ray.get_runtime_context().get_actor_id()}\n")
    if os.environ.get("GDWM_TEST_FAIL") == "reconstruct:setup":
        os.environ["GDWM_TEST_MISSING_VARIABLE"]  # raises KeyError, as a stage missing its setting does
    return {"loaded_at": time.time()}


@stage("reconstruct", "1", config=["stage.toy_reconstruct"], per_scene=True, resources="cpu", setup=_setup)
def reconstruct(ctx: StageContext) -> dict:
    _record(ctx)
    _inject(ctx)
    assert ctx.state is not None
    seed = int.from_bytes(ctx.scene.encode()[-4:], "little")
    pts = np.random.default_rng(seed).normal(size=(64, 3)) * ctx.cfg("stage.toy_reconstruct")["scale"]
    np.save(ctx.out_dir / "points.npy", pts)
    ctx.tracker.log_metrics({"psnr": 20.0 + seed % 7}, step=0)
    return {"points": 64}


@stage("distill", "1", config=["stage.toy_distill"], upstream=["reconstruct"], per_scene=True, resources="gpu")
def distill(ctx: StageContext) -> None:
    _record(ctx)
    _inject(ctx)
    pts = np.load(ctx.upstream["reconstruct"].scenes[ctx.scene] / "points.npy")
    dim = ctx.cfg("stage.toy_distill")["dim"]
    np.save(ctx.out_dir / "features.npy", np.tanh(pts @ np.ones((3, dim))))


def _train_loop(s) -> None:
    # torch is imported where a stage uses it: the driver and the per-scene workers, which never do, are spared its
    # import (a second of CPU in each of a toy launch's processes)
    import torch

    state = s.restore()
    start = state["step"] + 1 if state else 0
    # on s.device, as a real loop: fake GPUs (cluster=sim without CUDA) must give a device tensors can move to
    w = (state["w"] if state else torch.zeros(4)).to(s.device)
    if s.rank == 0:
        (_test_dir() / f"device-{s.config['stage']}.txt").write_text(str(w.device))
    kill = os.environ.get("GDWM_TEST_KILL", "")
    for step in range(start, s.config["steps"]):
        w = w + s.config["target"]
        s.report(step, {"loss": float(1.0 / (step + 1)), "start": float(start)}, state={"step": step, "w": w.cpu()})
        if kill == f"{s.config['stage']}:step={step}" and _once(f"{s.config['stage']}-step"):
            os.kill(os.getpid(), signal.SIGKILL)
        if os.environ.get("GDWM_TEST_BLOCK") == f"{s.config['stage']}:step={step}":
            _block(s.config["stage"])


def _train_stage(ctx: StageContext, steps: int, target: float) -> None:
    _record(ctx)
    _inject(ctx)
    result = ctx.train(_train_loop, {"steps": steps, "target": target, "stage": ctx.name}, total_steps=steps)
    # as numpy: the evaluations read it without importing torch in their workers
    np.save(ctx.out_dir / WEIGHTS, result.state["w"].numpy())


WEIGHTS = "weights.npy"
"""A toy training stage's output: its final ``w`` (float32, 4 values)."""


def seed_noise(seed: int) -> float:
    """What a seed adds to every toy lora step: 0 for seed 0 (the numbers the tests were written with), about
    +-0.5 for others, so seeds of one row spread like a real trial's."""
    return 0.5 * math.sin(seed)


@stage("tokenizer", "1", config=["stage.toy_tokenizer"], upstream=["distill"], resources="train", seeded=True)
def tokenizer(ctx: StageContext) -> None:
    if "token" in ctx.cfg("stage.toy_tokenizer"):  # a secret from the environment reaches the stage as it is
        (_test_dir() / "token-seen").write_text(ctx.cfg("stage.toy_tokenizer")["token"])
    n = sum(np.load(p / "features.npy").size for p in ctx.upstream["distill"].scenes.values())
    _train_stage(ctx, ctx.cfg("stage.toy_tokenizer")["steps"], float(n % 5))


@stage("lora", "1", config=["stage.toy_lora"], upstream=["tokenizer"], resources="train", seeded=True)
def lora(ctx: StageContext) -> None:
    if ctx.cfg("stage.toy_lora")["rank"] < 0:
        raise ValueError(f"stage.toy_lora.rank must be >= 0, got {ctx.cfg('stage.toy_lora')['rank']}")
    rank = float(ctx.cfg("stage.toy_lora")["rank"])
    _train_stage(ctx, ctx.cfg("stage.toy_lora")["steps"], rank + seed_noise(ctx.seed))


OFFSETS = [-2.0, -1.0, 0.0, 1.0, 2.0] * 8
"""Per-sample deviations of the toy's held-out samples from the model's accuracy: they sum to exactly 0."""


def score_toy(table: pa.Table, wanted=None) -> dict[str, float]:
    """The toy's metrics of any subset of its per-sample table (the scorer gdwm compare and regress resample)."""
    acc = float(np.mean(table["value"].to_numpy()))
    return {"acc": acc, "nuinteract/plan_acc": acc, "nuinstruct/mae": 100 / (1 + acc)}


@stage("evaluate_qa", "1", config=["stage.toy_evaluate_qa"], upstream=["lora"], resources="eval", evaluation=True,
       samples="predictions.parquet", score=score_toy)  # fmt: skip
def evaluate_qa(ctx: StageContext) -> dict:
    _record(ctx)
    _inject(ctx)
    w = np.load(ctx.upstream["lora"].path / WEIGHTS)
    acc = float(w.sum())
    table = pa.table({"sample_id": [f"s{i:02d}" for i in range(len(OFFSETS))], "value": [acc + o for o in OFFSETS]})
    pq.write_table(table, ctx.out_dir / "predictions.parquet")
    metrics = score_toy(table, None)
    ctx.tracker.log_metrics(metrics)
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics))
    return metrics


@stage("diffusion", "1", config=["stage.toy_diffusion"], upstream=["lora"], resources="train")
def diffusion(ctx: StageContext) -> None:
    _train_stage(ctx, ctx.cfg("stage.toy_diffusion")["steps"], 0.5)


@stage("evaluate_gen", "1", config=["stage.toy_evaluate_gen"], upstream=["diffusion"], resources="eval",
       evaluation=True)  # fmt: skip
def evaluate_gen(ctx: StageContext) -> dict:
    _record(ctx)
    _inject(ctx)
    w = np.load(ctx.upstream["diffusion"].path / WEIGHTS)
    (ctx.out_dir / "metrics.json").write_text(json.dumps({"psnr": float(w.mean())}))
    return {"psnr": float(w.mean())}


@stage("lora", "1", config=["stage.toy_lora"], upstream=["tokenizer"], resources="train", seeded=True,
       libraries=["toylib"])  # fmt: skip
def lora_toylib(ctx: StageContext) -> None:
    """The toy lora whose numbers depend on a library's version, as a real library upgrade's would: the rank is
    scaled by the major version of ``toylib``, a fake distribution (a dist-info only) that
    tests/gdwm/test_reproduce.py puts on PYTHONPATH; pipeline ``toy_lib``."""
    from importlib.metadata import version

    rank = float(ctx.cfg("stage.toy_lora")["rank"]) * int(version("toylib").split(".")[0])
    _train_stage(ctx, ctx.cfg("stage.toy_lora")["steps"], rank + seed_noise(ctx.seed))


@stage("scene_pid", "1", config=["stage.scene_pid"], per_scene=True, resources="cpu")
def scene_pid(ctx: StageContext) -> None:
    """Writes which process handled the scene (tests/gdwm/test_executor.py: who in a pool did the work)."""
    (ctx.out_dir / "pid.txt").write_text(str(os.getpid()))
