"""The training loop of the tokenizer and lora stages, run by Ray Train on every worker (``ctx.train``).

DDP through ``ray.train.torch.prepare_model`` on more than one worker, bf16 autocast on CUDA; the loop draws
task-aware batches that depend only on (seed, step), so a resumed run continues exactly where it stopped.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import ray.train
import ray.train.torch
import torch

from gdwm.api import TrainSession, warmup_cosine_lr
from pipelines.data.reader import GSQADataset
from pipelines.understanding.config import LoraStageConfig, TrainConfig
from pipelines.understanding.data import FrameStore, QASample, TaskSampler, row_samples
from pipelines.understanding.infer import predict
from pipelines.understanding.model import WorldModel, autocast, load_world_model

log = logging.getLogger(__name__)


def open_model(init_dir: Path, cfg: TrainConfig) -> WorldModel:
    """The model a stage starts from: its init dir, plus LoRA for the lora stage (``cfg`` a ``LoraStageConfig``)."""
    model = load_world_model(init_dir)
    model.freeze_llm()
    if isinstance(cfg, LoraStageConfig):
        model.add_lora(cfg)
        model.freeze_llm()
    return model


def train_loop(s: TrainSession) -> None:
    c = s.config
    cfg: TrainConfig = c["train"]  # the stage's config object (``run_training``)
    torch.manual_seed(c["seed"])  # the trial seed: LoRA init, dropout
    model = open_model(Path(c["init_dir"]), cfg)
    device = s.device
    ds = GSQADataset(c["data_root"])
    scene_dirs = {k: Path(v) for k, v in c["scene_dirs"].items()}
    samples, _ = row_samples(ds, "train", scene_dirs)
    store = FrameStore(ds, scene_dirs, model.comp.world.weather, model.comp.world.trajectory_frames)
    sampler = TaskSampler(samples, cfg.task_alpha, c["seed"])
    params = model.trainable_parameters()
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = 0
    state = s.restore()
    if state is not None:
        model.load_adapter_state(state["adapter"])
        if state.get("lora"):
            model.load_lora_state(state["lora"])
        opt.load_state_dict(state["optimizer"])
        start = int(state["step"]) + 1
    model.to(device)
    # move_to_device=device: Ray's own choice is cuda:N on fake GPUs (cluster=sim without CUDA)
    unused = {"find_unused_parameters": True}
    ddp = (
        ray.train.torch.prepare_model(model, move_to_device=device, parallel_strategy_kwargs=unused)
        if s.world_size > 1
        else model
    )
    rank_share = cfg.batch_size
    for step in range(start, cfg.steps):
        for group in opt.param_groups:
            group["lr"] = warmup_cosine_lr(step, cfg.lr, cfg.warmup_steps, cfg.steps)
        idx = sampler.batch(step, rank_share * s.world_size)[s.rank * rank_share : (s.rank + 1) * rank_share]
        batch = [samples[i] for i in idx]
        model.train()
        with autocast(device):
            loss, parts = ddp(batch, store, step)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"{c['stage']}: loss is {loss.item()} at step {step} (samples {[b.sample_id for b in batch]})"
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip > 0:
            parts["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip))
        opt.step()
        last = step == cfg.steps - 1
        metrics = {**parts, "lr": opt.param_groups[0]["lr"]} if step % cfg.log_every == 0 or last else {}
        want_ckpt = s.should_checkpoint(step) or last
        if metrics or want_ckpt:
            state = None
            if want_ckpt:
                state = {
                    "step": step,
                    "adapter": model.adapter_state(),
                    "lora": model.lora_state(),
                    "optimizer": opt.state_dict(),
                }
            s.report(step, metrics or {"loss": parts["loss"]}, state=state)


def evaluate(model: WorldModel, samples: Sequence[QASample], store: FrameStore, cfg: TrainConfig) -> dict:
    """Held-out LM loss and greedy answers on up to ``cfg.eval_samples`` samples (a training monitor; the benchmark
    metrics are the evaluate stage's)."""
    take = list(samples)[: cfg.eval_samples]
    if not take:
        return {"metrics": {}, "predictions": None}
    model.eval()
    total = 0.0
    with torch.no_grad():
        for i in range(0, len(take), cfg.batch_size):
            batch = take[i : i + cfg.batch_size]
            total += model(batch, store, 10**9)[1]["loss_lm"] * len(batch)
    table = predict(model, take, store, cfg.batch_size, cfg.max_new_tokens)
    preds, refs = table["prediction"].to_pylist(), table["answer"].to_pylist()
    exact = [p.strip() == r.strip() for p, r in zip(preds, refs, strict=True)]
    f1 = [token_f1(p, r) for p, r in zip(preds, refs, strict=True)]
    return {
        "metrics": {
            "val/loss_lm": total / len(take),
            "val/exact_match": 100.0 * sum(exact) / len(take),
            "val/token_f1": 100.0 * sum(f1) / len(take),
        },
        "predictions": table,
    }


def token_f1(pred: str, ref: str) -> float:
    """Whitespace-token F1 (SQuAD style): a coarse held-out monitor, not a benchmark metric."""
    p, r = pred.split(), ref.split()
    if not p or not r:
        return float(p == r)
    common = sum(min(p.count(t), r.count(t)) for t in set(p))
    if common == 0:
        return 0.0
    prec, rec = common / len(p), common / len(r)
    return 2 * prec * rec / (prec + rec)
