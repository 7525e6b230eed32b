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

import torch

from gdwm.api import StageContext, stage
from model_zoo.diffusion.rgbd_dual import DiffusionConfig
from pipelines.data.reader import GSQADataset
from pipelines.generation.config import VIEW_TARGETS, DiffusionStageConfig, VaeStageConfig
from pipelines.generation.examples import (
    build_examples,
    camera_views,
    conditions_of,
    pad_tokens,
    split_scenes,
    training_weathers,
)
from pipelines.generation.samples import KINDS, enumerate_targets, stack
from pipelines.generation.train import MODEL, diffusion_config, fit_vae, train_dual, zoo_variant
from pipelines.understanding.model import load_world_model


@stage("diffusion_vae", "1", config=[MODEL, "stage.diffusion_vae"], upstream=["reconstruct"], resources="train",
       needs={"images": "fits the VAE to the camera images"})  # fmt: skip
def diffusion_vae(ctx: StageContext) -> dict:
    return fit_vae(ctx, training_views)


def training_views(ctx: StageContext, cfg: DiffusionConfig, vcfg: VaeStageConfig) -> torch.Tensor:
    """The VAE's images: random views of each training scene (``camera_views``)."""
    ds = GSQADataset(ctx.data_root)
    scenes = split_scenes(ds, set(ctx.upstream["reconstruct"].scenes))["train"]
    return camera_views(ds, scenes, cfg.image_size, cfg.max_depth, vcfg.views_per_scene, vcfg.seed)


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
