"""Training of the dual-condition RGB-D diffusion model, shared by the ``diffusion_vae`` / ``diffusion`` stages and
their world-record stand-ins (``pipelines.stages.world``): the model config, the tiny VAE's fit, and the UNet's
v-prediction training (Eq. L_gen) under Ray Train, whose loop draws batches that depend only on (seed, step), so a
resumed run continues where it stopped.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, replace

import torch

from gdwm.api import StageContext, TrainSession, warmup_cosine_lr
from model_zoo import registry
from model_zoo.diffusion.rgbd_dual import DiffusionConfig, RGBDDual
from pipelines.generation.config import DiffusionStageConfig, VaeStageConfig

MODEL = "model.diffusion"
"""The config subtree of the model (``conf/model/diffusion/*.yaml``)."""


def diffusion_config(ctx: StageContext) -> DiffusionConfig:
    c = dict(ctx.cfg(MODEL))
    for k in ("image_size", "unet_channels", "vae_channels"):
        c[k] = tuple(c[k])
    return DiffusionConfig(**c)


def zoo_variant(cfg: DiffusionConfig) -> str:
    """Model-zoo variant: the model, its flavor and the conditions on, e.g. ``rgbd_dual-tiny+low_level+high_level``."""
    conditions = [n for n in ("low_level", "high_level") if getattr(cfg, n)]
    return "+".join([f"{cfg.name}-tiny" if cfg.tiny else cfg.name, *conditions])


def fit_vae(
    ctx: StageContext, images_of: Callable[[StageContext, DiffusionConfig, VaeStageConfig], torch.Tensor]
) -> dict:
    """The ``diffusion_vae`` stages' body: build the model, fit the tiny flavor's VAE to ``images_of(ctx, cfg, vcfg)``
    (logged every 10 steps), save it, register the fitted VAE as ``gdwm-vae``."""
    cfg = diffusion_config(ctx)
    vcfg = VaeStageConfig(**ctx.cfg("stage.diffusion_vae"))
    model: RGBDDual = registry.build("diffusion", cfg.name, cfg)
    metrics: dict = {"vae_fitted": 0.0}
    if cfg.tiny and vcfg.steps > 0:
        images = images_of(ctx, cfg, vcfg)
        losses = model.fit_vae(images, steps=vcfg.steps, lr=vcfg.lr, seed=vcfg.seed)
        for step in range(0, len(losses), 10):
            ctx.tracker.log_metrics({"vae_loss": losses[step]}, step=step)
        metrics = {"vae_fitted": 1.0, "vae_loss_first": losses[0], "vae_loss_final": losses[-1], "images": len(images)}
    model.save(ctx.out_dir)
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    if metrics["vae_fitted"]:
        ctx.register("gdwm-vae", "vae", f"{cfg.name}-tiny")
    return metrics


def _checkpoint(model: RGBDDual, opt: torch.optim.Optimizer, step: int) -> dict:
    """What a resumed attempt restores: the trainable weights only (the frozen VAE comes from the init dir)."""
    trainable = {n for n, p in model.named_parameters() if p.requires_grad}
    return {
        "step": step,
        "model": {k: v.cpu() for k, v in model.state_dict().items() if k in trainable},
        "optimizer": opt.state_dict(),
    }


def train_loop(s: TrainSession) -> None:
    c = s.config
    cfg = DiffusionStageConfig(**c["train"])
    seed = c["seed"]  # the trial seed: batches, noise, CFG dropout
    data = torch.load(c["data"], map_location="cpu", weights_only=True)
    torch.manual_seed(seed)
    model = RGBDDual.from_pretrained(c["init_dir"])
    device = s.device
    model.to(device)
    params = model.trainable_parameters()
    opt = torch.optim.AdamW(params, lr=cfg.lr)
    start = 0
    state = s.restore()
    if state is not None:
        model.load_state_dict(state["model"], strict=False)
        opt.load_state_dict(state["optimizer"])
        start = int(state["step"]) + 1
    n = len(data["target_rgb"])
    for step in range(start, cfg.steps):
        for group in opt.param_groups:
            group["lr"] = warmup_cosine_lr(step, cfg.lr, cfg.warmup_steps, cfg.steps)
        gen = torch.Generator().manual_seed(seed * 1_000_003 + step)
        idx = torch.randint(n, (cfg.batch_size * s.world_size,), generator=gen)
        idx = idx[s.rank * cfg.batch_size : (s.rank + 1) * cfg.batch_size]
        b = {k: v[idx].to(device) for k, v in data.items() if k not in ("c_L", "c_L_mask")}
        c_L = data["c_L"][idx].to(device) if "c_L" in data else None
        c_L_mask = data["c_L_mask"][idx].to(device) if "c_L_mask" in data else None
        model.train()
        loss, parts = model.loss(
            b["target_rgb"], b["target_depth"], b["ref_rgb"], b["ref_depth"],
            b["cond_rgb"], b["cond_depth"], b["cond_mask"], c_L, c_L_mask, generator=gen,
        )  # fmt: skip
        if not torch.isfinite(loss):
            raise FloatingPointError(f"diffusion: L_gen is {loss.item()} at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if s.world_size > 1:  # average gradients across workers (the model's objective is not its forward())
            for p in params:
                if p.grad is not None:  # a sum, then / world size: gloo (CPU groups) has no AVG reduction
                    torch.distributed.all_reduce(p.grad, op=torch.distributed.ReduceOp.SUM)
                    p.grad /= s.world_size
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        last = step == cfg.steps - 1
        want_ckpt = s.should_checkpoint(step) or last
        if step % cfg.log_every == 0 or last or want_ckpt:
            state = _checkpoint(model, opt, step) if want_ckpt else None
            s.report(step, {**parts, "lr": opt.param_groups[0]["lr"]}, state=state)


def train_dual(ctx: StageContext, mcfg: DiffusionConfig, cfg: DiffusionStageConfig, data: dict) -> RGBDDual:
    """Stacked examples (``stack``, C_L added) -> the dual-condition model trained under Ray Train: the examples saved
    for the workers, the initial model (``diffusion_vae``'s with ``mcfg``'s switches, kept for a resumed attempt),
    and the trained state loaded back, in eval mode. Shared by ``diffusion`` and the world-record stage."""
    data_path = ctx.checkpoint_dir / "examples.pt"
    data_path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(data, data_path)

    init = ctx.checkpoint_dir / "init"
    if not (init / "rgbd.json").is_file():
        model = RGBDDual.from_pretrained(ctx.upstream["diffusion_vae"].path)
        model.cfg = replace(model.cfg, low_level=mcfg.low_level, high_level=mcfg.high_level,
                            cond_dropout=mcfg.cond_dropout, guidance_scale=mcfg.guidance_scale,
                            sample_steps=mcfg.sample_steps)  # fmt: skip
        model.save(init)
    loop_cfg = {"init_dir": str(init), "data": str(data_path), "train": asdict(cfg), "seed": ctx.seed}
    result = ctx.train(train_loop, loop_cfg, total_steps=cfg.steps)
    model = RGBDDual.from_pretrained(init)
    model.load_state_dict(result.state["model"], strict=False)
    model.eval()
    return model
