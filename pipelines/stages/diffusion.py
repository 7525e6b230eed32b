"""diffusion_vae and diffusion (stage 3): the dual-condition RGB-D latent diffusion of the generation branch.

``diffusion_vae`` builds the model (tiny flavor: random UNet and VAE configs of the diffusers classes; full runs:
weights from ``model.diffusion.path``) and fits the tiny VAE to the training views, a cached upstream step of its
own. ``diffusion`` trains the UNet with v-prediction (Eq. L_gen) on shift, future and (unless
``stage.diffusion.weather_targets=false``, as the dual-condition table sets) weather targets: reference =
the clear view of frame f, low-level = frame f's reconstructed Gaussians projected into the target camera, C_L = the
LoRA'd LLM's hidden states for (Z_G, instruction). The held-out targets are the ``evaluate_gen`` stage's.

Output of ``diffusion``: the saved model (``unet/``, ``vae/``, ``rgbd.json``, ``null_token.pt``), ``metrics.json``,
registered in the model zoo as ``gdwm-unet``; a fitted tiny VAE (``vae/`` of ``diffusion_vae``) as ``gdwm-vae``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import cv2
import numpy as np
import ray.train
import torch

from gdwm.stage import StageContext, stage
from gdwm.training import TrainSession, warmup_cosine_lr
from model_zoo import registry
from model_zoo.diffusion.rgbd_dual import DiffusionConfig, RGBDDual
from model_zoo.diffusion.vpred import depth_to_rgb
from pipelines.data.reader import GSQADataset
from pipelines.generation.conditions import NoGaussiansInView
from pipelines.generation.config import VIEW_TARGETS, DiffusionStageConfig, VaeStageConfig
from pipelines.generation.samples import (
    KINDS,
    GenExample,
    GenTarget,
    build_example,
    enumerate_targets,
    frame_gaussians,
    stack,
)
from pipelines.understanding.data import FrameStore, QASample
from pipelines.understanding.model import load_world_model

MODEL = "model.diffusion"


def diffusion_config(ctx: StageContext) -> DiffusionConfig:
    c = dict(ctx.cfg(MODEL))
    for k in ("image_size", "unet_channels", "vae_channels"):
        c[k] = tuple(c[k])
    return DiffusionConfig(**c)


def zoo_variant(cfg: DiffusionConfig) -> str:
    """Model-zoo variant: the model, its flavor and the conditions on, e.g. ``rgbd_dual-tiny+low_level+high_level``."""
    conditions = [n for n in ("low_level", "high_level") if getattr(cfg, n)]
    return "+".join([f"{cfg.name}-tiny" if cfg.tiny else cfg.name, *conditions])


def split_scenes(ds: GSQADataset, available: set[str]) -> dict[str, list[str]]:
    """Scenes per QA split (the dataset's train/val assignment), restricted to those with reconstructions."""
    qa = ds.qa()
    out: dict[str, list[str]] = {"train": [], "val": []}
    for scene, split in sorted(set(zip(qa["scene_token"].to_pylist(), qa["split"].to_pylist(), strict=True))):
        if scene in available and split in out:
            out[split].append(scene)
    return out


@stage("diffusion_vae", "1", config=[MODEL, "stage.diffusion_vae"], upstream=["reconstruct"], resources="train",
       needs={"images": "fits the VAE to the camera images"})  # fmt: skip
def diffusion_vae(ctx: StageContext) -> dict:
    return fit_vae(ctx, training_views)


def training_views(ctx: StageContext, cfg: DiffusionConfig, vcfg: VaeStageConfig) -> torch.Tensor:
    """``[N, 3, H, W]`` in [0, 1]: up to ``views_per_scene`` random (frame, camera) views of each training scene, RGB
    and depth as pseudo-RGB."""
    ds = GSQADataset(ctx.data_root)
    scenes = split_scenes(ds, set(ctx.upstream["reconstruct"].scenes))["train"]
    rng = np.random.default_rng(vcfg.seed)
    hw = cfg.image_size
    images = []
    for sid in scenes:
        scene = ds.scene(sid)
        views = [(f, cam) for f in range(scene.num_frames) for cam in scene.cameras]
        for i in rng.permutation(len(views))[: vcfg.views_per_scene]:
            f, cam = views[i]
            frame = scene.frame(f)
            rgb = cv2.resize(frame.image(cam), (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
            depth = cv2.resize(frame.depth(cam), (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
            images.append(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0)
            images.append((depth_to_rgb(torch.from_numpy(depth)[None], cfg.max_depth)[0] + 1) / 2)
    return torch.stack(images)


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


def training_weathers(cfg: DiffusionStageConfig) -> list[str]:
    """The weather targets trained on: ``cfg.weathers``, or none with ``cfg.weather_targets`` off."""
    return list(cfg.weathers) if cfg.weather_targets else []


def build_examples(ds, targets: list[GenTarget], rec_dirs: dict[str, Path], hw) -> tuple[list[GenExample], int]:
    out, skipped, cache = [], 0, {}
    for t in targets:
        key = (t.scene, t.frame)
        if key not in cache:
            path = rec_dirs[t.scene] / "gaussians" / f"{t.frame:05d}.arrow"
            cache[key] = frame_gaussians(rec_dirs[t.scene], t.scene, t.frame) if path.is_file() else None
        if cache[key] is None:  # frame excluded by reconstruction QC
            skipped += 1
            continue
        try:
            out.append(build_example(ds, t, cache[key], hw))
        except NoGaussiansInView:  # nothing to condition on
            skipped += 1
    return out, skipped


def conditions_of(world, ds, distill_dirs, prompts: list[QASample], batch: int) -> list:
    """C_L of every prompt from the (frozen) world model, unpadded; Nones when the high-level condition is off."""
    if world is None:
        return [None] * len(prompts)
    store = FrameStore(ds, distill_dirs, world.comp.world.weather, world.comp.world.trajectory_frames)
    out = []
    for i in range(0, len(prompts), batch):
        chunk = prompts[i : i + batch]
        h, m = world.condition(chunk, store)
        out += [h[b, m[b]].cpu() for b in range(len(chunk))]
    return out


def pad_tokens(tokens: list[torch.Tensor | None]) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    if tokens[0] is None:
        return None, None
    n = max(len(t) for t in tokens)
    out = torch.zeros(len(tokens), n, tokens[0].shape[-1])
    mask = torch.zeros(len(tokens), n, dtype=torch.bool)
    for b, t in enumerate(tokens):
        out[b, : len(t)] = t
        mask[b, : len(t)] = True
    return out, mask


def train_loop(s: TrainSession) -> None:
    c = s.config
    cfg = DiffusionStageConfig(**c["train"])
    seed = c["seed"]  # the trial seed: batches, noise, CFG dropout
    data = torch.load(c["data"], map_location="cpu", weights_only=True)
    torch.manual_seed(seed)
    model = RGBDDual.from_pretrained(c["init_dir"])
    device = ray.train.torch.get_device() if s.world_size > 1 or torch.cuda.is_available() else torch.device("cpu")
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
                if p.grad is not None:
                    torch.distributed.all_reduce(p.grad, op=torch.distributed.ReduceOp.AVG)
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        last = step == cfg.steps - 1
        want_ckpt = s.should_checkpoint(step) or last
        if step % cfg.log_every == 0 or last or want_ckpt:
            state = None
            if want_ckpt:
                trainable = {n for n, p in model.named_parameters() if p.requires_grad}
                state = {
                    "step": step,
                    "model": {k: v.cpu() for k, v in model.state_dict().items() if k in trainable},
                    "optimizer": opt.state_dict(),
                }
            s.report(step, {**parts, "lr": opt.param_groups[0]["lr"]}, state=state)


def save_grid(path: Path, ex: GenExample, rgb: torch.Tensor) -> None:
    """reference | condition | generated | ground truth, one row."""
    tiles = [ex.ref_rgb, ex.cond_rgb, rgb.cpu(), ex.target_rgb]
    row = torch.cat([t.clamp(0, 1) for t in tiles], dim=2).permute(1, 2, 0).numpy()
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor((row * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))


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
    result = ctx.train(train_loop, loop_cfg)
    model = RGBDDual.from_pretrained(init)
    model.load_state_dict(result.state["model"], strict=False)
    model.eval()
    return model


@stage(
    "diffusion",
    "3",
    config=[MODEL, "stage.diffusion"],
    upstream=["diffusion_vae", "reconstruct", "lora", "distill"],
    resources="train",
    seeded=True,
    needs=VIEW_TARGETS,
)
def diffusion(ctx: StageContext) -> dict:
    mcfg = diffusion_config(ctx)
    cfg = DiffusionStageConfig(**ctx.cfg("stage.diffusion"))
    ds = GSQADataset(ctx.data_root)
    rec_dirs = dict(ctx.upstream["reconstruct"].scenes)
    splits = split_scenes(ds, set(rec_dirs))
    world = load_world_model(ctx.upstream["lora"].path).eval() if mcfg.high_level else None  # C_L, loaded once
    distill_dirs = dict(ctx.upstream["distill"].scenes)
    hw = mcfg.image_size

    train_targets = enumerate_targets(ds, splits["train"], cfg.cameras, cfg.shifts_m, cfg.horizons_s,
                                      training_weathers(cfg))  # fmt: skip
    examples, skipped = build_examples(ds, train_targets, rec_dirs, hw)
    if not examples:
        raise ValueError(f"diffusion: no training examples ({skipped} targets skipped) in scenes {splits['train']}")
    per_kind = {f"train_examples/{k}": float(sum(e.target.kind == k for e in examples)) for k in KINDS}
    ctx.tracker.log_metrics({"train_examples": float(len(examples)), "skipped_targets": float(skipped), **per_kind})
    c_L = conditions_of(world, ds, distill_dirs, [e.target.qa() for e in examples], cfg.batch_size)
    data = stack(examples)
    tokens, mask = pad_tokens(c_L)
    if tokens is not None:
        data |= {"c_L": tokens, "c_L_mask": mask}
    model = train_dual(ctx, mcfg, cfg, data)

    metrics: dict = {"train_examples": len(examples), **per_kind}
    model.save(ctx.out_dir)
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    ctx.register("gdwm-unet", ".", zoo_variant(mcfg))
    return metrics
