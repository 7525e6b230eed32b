"""The generation branch on the GaussianDWM release's world samples (a dataset with Gaussians and ``world.parquet``
but no cameras, LiDAR or scene images), bound by a pipeline config under the names the rest of the DAG uses:

- ``diffusion_vae`` = ``world_vae``: as ``pipelines.stages.diffusion.diffusion_vae``, the tiny VAE fitted to the
  training world samples' reference views and ground-truth frames and depths (``world.vae_images``); no upstream.
- ``diffusion`` = ``world_diffusion``: as ``diffusion``, the UNet with v-prediction (Eq. L_gen), on one example per
  frame of every training world sample (``pipelines.generation.world``: the release's pseudo RGB-D frames are the
  low-level conditions, C_L the LoRA'd LLM's hidden states for the sample's instruction over its frame's Gaussians).
  Samples without ground-truth frames or depth are skipped and counted. Of ``stage.diffusion`` only the optimiser
  settings apply: a world sample fixes its own targets (``cameras``, ``shifts_m``, ``horizons_s``, ``weathers`` unused).
- ``evaluate_gen`` = ``world_evaluate_gen``: every frame of the val world samples with ground truth, generated and
  scored with ``metrics.score_views`` as ``gen/world/<metric>``; what needs cameras is listed as not computed in
  ``protocol.json`` (``NOT_COMPUTED``).

Outputs as the stages they stand in for: ``diffusion_vae``: the model and ``metrics.json`` (``gdwm-vae`` when
fitted); ``diffusion``: the saved model (``unet/``, ``vae/``, ``rgbd.json``, ``null_token.pt``) and ``metrics.json``
(``gdwm-unet``); ``evaluate_gen``: ``metrics.json``, ``protocol.json`` and ``samples/world/<sample>_<t>.png``
(reference | condition | generated | ground truth).
"""

from __future__ import annotations

import json
import math
import re
import warnings
from dataclasses import asdict

import torch

from gdwm.api import StageContext, stage
from model_zoo.diffusion.rgbd_dual import DiffusionConfig, RGBDDual
from pipelines.data.reader import GSQADataset
from pipelines.evaluate.config import EvaluateGenConfig
from pipelines.generation.config import DiffusionStageConfig, VaeStageConfig
from pipelines.generation.examples import pad_tokens, save_grid
from pipelines.generation.samples import stack
from pipelines.generation.train import MODEL, diffusion_config, fit_vae, train_dual, zoo_variant
from pipelines.generation.world import KIND, clip_conditions, split_samples, vae_images, world_clips
from pipelines.understanding.model import load_world_model

NOT_COMPUTED = {
    "gen/shift_<m>m, gen/shift_pm<m>m": "need a camera rig to project the Gaussians into a laterally shifted camera "
    "and ground truth re-rendered there; the release has no cameras",
    "gen/future_<s>s": "need camera intrinsics, extrinsics and ego poses to project the Gaussians into the future "
    "camera; the release's own future frames (its pseudo RGB-D conditions) are scored as gen/world instead",
    "gen/future_pred_<s>s": "need a camera rig to place the camera on the LLM-predicted pose",
    "gen/weather_<w>": "need weather variants of the camera images",
}
"""Metrics of ``evaluate_gen`` that need cameras, and why they are not computed on release data."""
UNUSED_EVAL_CONFIG = ("cameras", "shifts_m", "horizons_s", "future_poses", "frames")
"""``stage.evaluate_gen`` fields that choose camera targets: a world sample fixes its own frames."""


def _skipped(skipped: dict, split: str) -> dict[str, float]:
    return {f"count/skipped/{split}/{k}": float(v) for k, v in sorted(skipped.items())}


@stage("diffusion_vae", "1", config=[MODEL, "stage.diffusion_vae"], resources="train",
       needs={"world": "fits the VAE to the world samples' reference views and ground-truth frames"})  # fmt: skip
def world_vae(ctx: StageContext) -> dict:
    return fit_vae(ctx, _world_views)


def _world_views(ctx: StageContext, cfg: DiffusionConfig, vcfg: VaeStageConfig) -> torch.Tensor:
    samples = split_samples(GSQADataset(ctx.data_root), "train")
    # a world sample is one scene clip: views_per_scene caps the frames drawn from each
    return vae_images(samples, cfg.image_size, cfg.max_depth, vcfg.views_per_scene, vcfg.seed)


@stage("diffusion", "1", config=[MODEL, "stage.diffusion"], upstream=["diffusion_vae", "lora", "distill"],
       resources="train", seeded=True,
       needs={"world": "trains on the world samples' pseudo RGB-D frames and ground truth"})  # fmt: skip
def world_diffusion(ctx: StageContext) -> dict:
    mcfg = diffusion_config(ctx)
    cfg = DiffusionStageConfig(**ctx.cfg("stage.diffusion"))
    ds = GSQADataset(ctx.data_root)
    distill_dirs = dict(ctx.upstream["distill"].scenes)
    clips, skipped = world_clips(ds, "train", distill_dirs, mcfg.image_size, need_depth=True)
    if not clips:
        raise ValueError(
            f"diffusion: no training world samples in {ds.root} have ground-truth frames, depth and Gaussians "
            f"(skipped: {dict(skipped)})"
        )
    examples = [e for c in clips for e in c.examples]
    counts = {"train_examples": float(len(examples)), f"train_examples/{KIND}": float(len(examples)),
              "train_samples": float(len(clips)), **_skipped(skipped, "train")}  # fmt: skip
    ctx.tracker.log_metrics(counts)
    world = load_world_model(ctx.upstream["lora"].path).eval() if mcfg.high_level else None  # C_L, loaded once
    data = stack(examples)
    tokens, mask = pad_tokens(clip_conditions(world, ds, distill_dirs, clips, cfg.batch_size))
    if tokens is not None:
        data |= {"c_L": tokens, "c_L_mask": mask}
    model = train_dual(ctx, mcfg, cfg, data)

    metrics = {k: int(v) for k, v in counts.items()}
    model.save(ctx.out_dir)
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    ctx.register("gdwm-unet", ".", zoo_variant(mcfg))
    return metrics


def _file_name(sample_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", sample_id)


@stage("evaluate_gen", "1", config=["stage.evaluate_gen"], upstream=["diffusion", "lora", "distill"],
       resources="eval", evaluation=True, seeded=True, needs={"world": "scores the val world samples"})  # fmt: skip
def world_evaluate_gen(ctx: StageContext) -> dict:
    from pipelines.generation.frechet import build_extractor, build_video_extractor, label
    from pipelines.generation.metrics import PROTOCOL, score_views

    cfg = EvaluateGenConfig(**ctx.cfg("stage.evaluate_gen"))
    extractor = build_extractor(cfg.fd_extractor, cfg.fd_weights)  # a missing weight file fails before sampling
    video = build_video_extractor(cfg.fvd_weights)
    model = RGBDDual.from_pretrained(ctx.upstream["diffusion"].path).eval()
    ds = GSQADataset(ctx.data_root)
    distill_dirs = dict(ctx.upstream["distill"].scenes)
    clips, skipped = world_clips(ds, "val", distill_dirs, model.cfg.image_size, need_depth=False)
    if not clips:
        raise ValueError(f"evaluate_gen: no val world samples in {ds.root} to score (skipped: {dict(skipped)})")
    world = load_world_model(ctx.upstream["lora"].path).eval() if model.cfg.high_level else None
    held = [e for c in clips for e in c.examples]
    c_L = clip_conditions(world, ds, distill_dirs, clips, cfg.batch_size)
    scored = []
    for i in range(0, len(held), cfg.batch_size):
        chunk = held[i : i + cfg.batch_size]
        b = stack(chunk)
        tok, m = pad_tokens(c_L[i : i + cfg.batch_size])
        gen = torch.Generator().manual_seed(ctx.seed * 1_000_003 + i)  # the trial seed's sampling noise
        with torch.no_grad():
            rgb, depth = model.sample(b["ref_rgb"], b["ref_depth"], b["cond_rgb"], b["cond_depth"], b["cond_mask"],
                                      tok, m, generator=gen)  # fmt: skip
        for j, ex in enumerate(chunk):
            scored.append((ex, rgb[j].cpu(), depth[j].cpu()))
            t = ex.target
            save_grid(ctx.out_dir / f"samples/{KIND}/{_file_name(t.sample_id)}_{t.index:03d}.png", ex, rgb[j])
        ctx.progress(min(i + cfg.batch_size, len(held)), len(held), "generating")
    with warnings.catch_warnings():  # no ground-truth depth in any view: NaN, dropped and listed below
        warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
        raw = score_views(scored, model.cfg.max_depth, extractor, video, cfg.fvd_clip_frames)
    metrics = {k: v for k, v in raw.items() if math.isfinite(v)}
    no_depth = sum(not c.sample.row["gt_depth"] for c in clips)
    metrics |= {"count/heldout_views": float(len(held)), "count/heldout_samples": float(len(clips)),
                "count/samples_without_gt_depth": float(no_depth), **_skipped(skipped, "val")}  # fmt: skip
    not_computed = dict(NOT_COMPUTED)
    for name, why in (
        (f"gen/{KIND}/depth_absrel, depth_rmse", "no val world sample has ground-truth depth"),
        (f"gen/{KIND}/{extractor.name}", "fewer than 2 views scored"),
        (f"gen/{KIND}/{video.name}", f"fewer than 2 clips of {cfg.fvd_clip_frames} frames (fvd_clip_frames)"),
    ):
        if name.split(",")[0] not in metrics:
            not_computed[name] = why
    protocol = {
        "views": PROTOCOL,
        "frechet": label(extractor),
        "fvd": label(video),
        "targets": f"gen/{KIND}: every frame of the val world samples with ground truth; reference depth none "
        "(zeros), low-level conditions the release's pseudo RGB-D frames",
        "not_computed": not_computed,
        "unused_config": list(UNUSED_EVAL_CONFIG),
        "config": asdict(cfg),
    }
    (ctx.out_dir / "protocol.json").write_text(json.dumps(protocol, indent=2, sort_keys=True))
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    ctx.tracker.log_metrics(metrics)
    ctx.tracker.log_params({"fd_protocol": protocol["frechet"], "fvd_protocol": protocol["fvd"],
                            "metrics_protocol": PROTOCOL})  # fmt: skip
    ctx.tracker.log_artifact(str(ctx.out_dir / "protocol.json"))
    return metrics
