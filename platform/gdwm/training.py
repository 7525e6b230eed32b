"""Training stages on Ray Train: ScalingConfig from the cluster config, checkpoints, resume.

A stage calls ``ctx.train(loop, config)``; ``loop(session)`` runs on every worker::

    def loop(s: TrainSession):
        state = s.restore()                       # None on a fresh start
        step = state["step"] + 1 if state else 0
        for step in range(step, s.config["steps"]):
            ...
            s.report(step, {"loss": loss}, state={"step": step, "model": model.state_dict()})

With ``num_workers >= 1`` Ray Train runs a real worker group and ``FailureConfig(max_failures)``
restarts it; ``num_workers = 0`` runs the loop in-process (no start-up cost). Either way rank 0
also persists every reported checkpoint under the stage's checkpoint dir before reporting it,
and ``restore`` reads that first, so a restarted worker or a re-run resumes from the newest one.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray.train
import torch
from ray.train import Checkpoint, FailureConfig, RunConfig, ScalingConfig
from ray.train.torch import TorchTrainer

from gdwm.determinism import stage_start

STATE_FILE = "state.pt"


@dataclass
class TrainSession:
    """What the loop sees on each worker."""

    config: dict
    tracker: Any
    local_ckpt_dir: str
    """Where gdwm persists every reported checkpoint itself (shared storage on a cluster)."""
    checkpoint_every: int

    @property
    def rank(self) -> int:
        return ray.train.get_context().get_world_rank()

    @property
    def world_size(self) -> int:
        return ray.train.get_context().get_world_size()

    def restore(self) -> dict | None:
        """The last reported state (tensors and plain values), loaded with weights_only=True.

        gdwm's own copy comes first: Ray Train registers a reported checkpoint only when its controller next polls
        the worker, so a worker killed right after ``report`` can take its newest checkpoints with it.
        """
        latest = latest_local_checkpoint(self.local_ckpt_dir)
        if latest is not None:
            return torch.load(latest / STATE_FILE, map_location="cpu", weights_only=True)
        ckpt = ray.train.get_checkpoint()
        if ckpt is not None:
            with ckpt.as_directory() as d:
                return torch.load(Path(d) / STATE_FILE, map_location="cpu", weights_only=True)
        return None

    def should_checkpoint(self, step: int) -> bool:
        return self.checkpoint_every > 0 and (step + 1) % self.checkpoint_every == 0

    def report(self, step: int, metrics: Mapping[str, float], state: dict | None = None) -> None:
        """Log metrics at ``step`` (rank 0) and, with ``state``, report a checkpoint."""
        metrics = {k: float(v) for k, v in metrics.items()}
        if self.rank == 0 and self.tracker is not None:
            self.tracker.log_metrics(metrics, step=step)
        if state is None:
            ray.train.report({**metrics, "step": step})
            return
        with tempfile.TemporaryDirectory() as d:
            if self.rank == 0:
                torch.save(state, Path(d) / STATE_FILE)
                # Persisted synchronously before Ray hears of it (see restore); in-process mode Ray keeps no copy.
                _persist_local(Path(d), Path(self.local_ckpt_dir), step)
            ckpt = Checkpoint.from_directory(d) if self.rank == 0 else None
            ray.train.report({**metrics, "step": step}, checkpoint=ckpt)


def warmup_cosine_lr(step: int, base_lr: float, warmup_steps: int, total_steps: int, floor: float = 0.1) -> float:
    """Linear warm-up over ``warmup_steps``, then cosine decay to ``floor * base_lr`` at ``total_steps``."""
    if warmup_steps and step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    return base_lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress)))


def latest_local_checkpoint(root: str | None) -> Path | None:
    if root is None or not Path(root).is_dir():
        return None
    done = sorted(p for p in Path(root).glob("step_*") if (p / STATE_FILE).is_file())
    return done[-1] if done else None


def _persist_local(src: Path, root: Path, step: int) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tmp-"))
    shutil.copytree(src, tmp, dirs_exist_ok=True)
    final = root / f"step_{step:09d}"
    if final.exists():
        shutil.rmtree(final)
    tmp.rename(final)
    return final


def _worker_entry(payload: dict) -> None:
    loop: Callable[[TrainSession], None] = payload["loop"]
    # a worker process of Ray Train's group starts from the same state as the stage task did (gdwm.determinism)
    stage_start(payload["seed"], payload["num_cpus"], payload["deterministic"])
    if payload.get("tracker") is not None and ray.train.get_context().get_world_rank() == 0:
        payload["tracker"].log_text(f"world_size={ray.train.get_context().get_world_size()}", "train/world.txt")
    loop(TrainSession(payload["config"], payload["tracker"], payload["local_ckpt_dir"], payload["checkpoint_every"]))
    if payload.get("tracker") is not None and ray.train.get_context().get_world_rank() == 0:
        payload["tracker"].flush()


def fit(ctx, loop: Callable[[TrainSession], None], loop_config: dict) -> TrainResult:
    res = ctx.resources
    workers = int(res.get("num_workers", 1))
    gpus = float(res.get("num_gpus", 0))
    settings = ctx.train_settings
    local = workers == 0
    payload = {
        "loop": loop,
        "config": loop_config,
        "tracker": ctx.tracker,
        "local_ckpt_dir": str(ctx.checkpoint_dir / "steps"),
        "checkpoint_every": int(settings.get("checkpoint_every", 1)),
        "seed": ctx.seed or 0,
        "num_cpus": float(res.get("num_cpus", 1)),
        "deterministic": ctx.deterministic,
    }
    scaling = ScalingConfig(
        num_workers=workers,
        use_gpu=gpus > 0,
        resources_per_worker=None
        if local
        else {"CPU": float(res.get("num_cpus", 1)), **({"GPU": gpus} if gpus else {})},
    )
    run = RunConfig(
        name=f"train-{ctx.key[:16]}",
        storage_path=str(ctx.checkpoint_dir),
        failure_config=FailureConfig(max_failures=int(settings.get("max_failures", 2))),
    )
    trainer = TorchTrainer(_worker_entry, train_loop_config=payload, scaling_config=scaling, run_config=run)
    result = trainer.fit()
    return TrainResult(_final_state(result, payload["local_ckpt_dir"]), dict(result.metrics or {}))


@dataclass
class TrainResult:
    state: dict | None
    """The last reported state (None if the loop never reported one)."""
    metrics: dict


def _final_state(result: ray.train.Result, local_dir: str) -> dict | None:
    """The last reported state: gdwm's own copy (always written, also when the loop had nothing left to do)."""
    latest = latest_local_checkpoint(local_dir)
    if latest is not None:
        return torch.load(latest / STATE_FILE, map_location="cpu", weights_only=True)
    if result.checkpoint is not None:
        with result.checkpoint.as_directory() as d:
            return torch.load(Path(d) / STATE_FILE, map_location="cpu", weights_only=True)
    return None
