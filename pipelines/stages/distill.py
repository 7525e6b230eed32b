"""distill: lift frozen foundation features into per-Gaussian compact codes (paper Eqs. F_v = E_F(I_v),
f_i = D_F(z_i), F_v(u) = sum_i w_iu f_i, L_distill, L_ae). E_F is ``stage.distill.encoder``: the foundation encoder,
or the LangSplat stand-in of the ablations' "Distillation ✗" rows (``autoencoder.json`` records which).

Output of one scene::

    gaussians/<frame:05d>.arrow   the reconstructed Gaussians of that frame with ``feature`` = z_i (d_z dims)
    decoder.pt                    D_F (and E_z) weights, loaded with weights_only=True
    autoencoder.json              its config and variant
    metrics.json                  L_ae, L_distill curves' ends; held-out L1 vs the per-scene mean-feature baseline
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from gdwm.stage import StageContext, stage
from model_zoo import registry
from model_zoo.distill_math import l_distill
from model_zoo.encoders.daisy import DaisyConfig
from model_zoo.encoders.langsplat_proxy import LangSplatProxyConfig
from model_zoo.encoders.qwen3_vl_vision import QwenVisionConfig
from model_zoo.feature_ae import FeatureAEConfig, fit_autoencoder
from pipelines.data.layout import gaussians_table, write_arrow
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow
from pipelines.distill.config import DistillConfig
from pipelines.distill.field import load_field, view_weights
from pipelines.recon.init import load_views


def load_encoder(cfg: Mapping) -> torch.nn.Module:
    """The frozen E_F, loaded once per actor (``setup``)."""
    c = DistillConfig(**cfg["stage.distill"])
    if c.encoder == "daisy":
        return registry.build("encoder", "daisy", DaisyConfig(d_f=c.d_f, seed=c.seed))
    if c.encoder == "qwen3_vl_vision":
        return registry.build("encoder", "qwen3_vl_vision", QwenVisionConfig(path=c.encoder_path, tiny=c.encoder_tiny))
    if c.encoder == "langsplat_proxy":
        return registry.build("encoder", "langsplat_proxy", LangSplatProxyConfig(d_f=c.d_f))
    if c.encoder == "langsplat":
        raise ValueError(
            "stage.distill.encoder=langsplat: LangSplat's own codes come only with a dataset that ships them "
            "(experiment=gaussiandwm_release); from images, distil encoder=langsplat_proxy"
        )
    raise ValueError(f"stage.distill.encoder: unknown encoder '{c.encoder}' (daisy, qwen3_vl_vision, langsplat_proxy)")


def _render(weights: torch.Tensor, feats_NF: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """Eq. F_v(u) = sum_i w_iu D_F(z_i), with the view's precomputed weights."""
    return (weights @ feats_NF).reshape(*hw, -1)


@stage(
    "distill",
    "1",
    config=["stage.distill"],
    upstream=["reconstruct"],
    per_scene=True,
    resources="gpu",
    setup=load_encoder,
    needs={"cameras": "renders the features into every camera", "images": "encodes the camera images"},
)
def distill(ctx: StageContext) -> dict:
    cfg = DistillConfig(**ctx.cfg("stage.distill"))
    encoder = ctx.state if ctx.state is not None else load_encoder(ctx.config)
    rec_dir = ctx.upstream["reconstruct"].scenes[ctx.scene]
    field = load_field(rec_dir)
    split = json.loads((rec_dir / "views.json").read_text())
    held_set = {tuple(v) for v in split["heldout"]}
    scene = GSQADataset(ctx.data_root).scene(ctx.scene)
    # Every view trains and evaluates the shared field; QC-excluded frames only get no output file.
    views = load_views(scene)
    gen = torch.Generator().manual_seed(cfg.seed)

    per_view = []  # (view, held?, weights, target [H, W, d_f], valid [H, W])
    for i, v in enumerate(views):
        h, w = v.rgb_HW3.shape[:2]
        target = encoder.encode((v.rgb_HW3 * 255).round().astype(np.uint8), out_hw=(h, w)).float()
        weights, _ = view_weights(field, v, cfg.min_weight)
        alpha = (weights @ torch.ones(weights.shape[1], 1)).reshape(h, w)
        valid = encoder.valid_mask(h, w, out_hw=(h, w)) & (alpha >= cfg.min_alpha)
        per_view.append((v, (v.frame, v.camera) in held_set, weights, target, valid))
        ctx.progress(i + 1, len(views), "encoding views")
    train = [p for p in per_view if not p[1]]
    held = [p for p in per_view if p[1]]

    # Compact feature autoencoding (Eq. L_ae) on pixel features of the training views.
    samples = []
    for _, _, _, target, valid in train:
        pix = target[valid]
        take = torch.randperm(len(pix), generator=gen)[: cfg.ae_pixels_per_view]
        samples.append(pix[take])
    f_train = torch.cat(samples)
    d_z = 3 if cfg.feature_tokenizer == "langsplat3" else cfg.d_z
    ae_cfg = FeatureAEConfig(d_f=f_train.shape[1], d_z=d_z, hidden=cfg.ae_hidden)
    ae, ae_losses = fit_autoencoder(f_train, ae_cfg, steps=cfg.ae_steps, lr=cfg.ae_lr, seed=cfg.seed)
    for step in range(0, len(ae_losses), 10):
        ctx.tracker.log_metrics({"l_ae": ae_losses[step]}, step=step)
    ae.requires_grad_(False)

    # Initialise each code from the features of the pixels it covers (weighted by w_iu), then optimise Eq. L_distill.
    n = len(field.g)
    acc, mass = torch.zeros(n, f_train.shape[1]), torch.zeros(n)
    for _, _, weights, target, valid in train:
        wt = weights.t()
        acc += wt @ (target * valid[..., None]).reshape(-1, target.shape[-1])
        mass += (wt @ valid.reshape(-1, 1).float()).squeeze(1)
    mean_feature = f_train.mean(0)
    f_init = torch.where(mass[:, None] > 1e-6, acc / mass.clamp(min=1e-6)[:, None], mean_feature)
    z = ae.encode(f_init).detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=cfg.distill_lr)
    for step in range(cfg.distill_steps):
        decoded = ae.decode(z)
        batch = [train[i] for i in torch.randperm(len(train), generator=gen)[: cfg.views_per_step].tolist()]
        loss = l_distill(
            torch.stack([_render(wv, decoded, t.shape[:2]) for _, _, wv, t, _ in batch]),
            torch.stack([t for *_, t, _ in batch]),
            torch.stack([m for *_, m in batch]),
        )
        if not torch.isfinite(loss):
            raise FloatingPointError(f"{ctx.scene}: L_distill is {loss.item()} at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 10 == 0 or step == cfg.distill_steps - 1:
            ctx.tracker.log_metrics({"l_distill": loss.item()}, step=step)
            ctx.progress(step + 1, cfg.distill_steps, f"L_distill {loss.item():.4f}")

    # Held-out views: distilled field vs a per-scene mean-feature baseline, same metric (L1 over valid pixels).
    with torch.no_grad():
        decoded = ae.decode(z)
        ours = [float(l_distill(_render(wv, decoded, t.shape[:2]), t, m)) for _, _, wv, t, m in held]
        base = [float(l_distill(mean_feature.expand_as(t), t, m)) for *_, t, m in held]
    metrics = {
        "l_ae_final": float(ae_losses[-1]),
        "l_distill_final": loss.item() if cfg.distill_steps else float("nan"),
        "heldout_l1": float(np.mean(ours)) if ours else float("nan"),
        "heldout_l1_mean_baseline": float(np.mean(base)) if base else float("nan"),
    }
    metrics["heldout_l1_reduction"] = 1.0 - metrics["heldout_l1"] / metrics["heldout_l1_mean_baseline"]
    ctx.tracker.log_metrics(metrics)

    codes = z.detach().numpy().astype(np.float32)
    for f in scene.frames():
        if f.idx in field.excluded_frames:
            continue
        _, _, keep = field.poses[f.idx].apply(field.g)
        rel = Path("gaussians") / f"{f.idx:05d}.arrow"
        arrays = gaussians_from_table(read_arrow(rec_dir / rel, f.where))
        arrays["feature"] = codes[keep.numpy()]
        write_arrow(gaussians_table(arrays, where=f.where), ctx.out_dir / rel)
    torch.save(ae.state_dict(), ctx.out_dir / "decoder.pt")
    (ctx.out_dir / "autoencoder.json").write_text(
        json.dumps({"variant": cfg.feature_tokenizer, "config": asdict(ae_cfg), "encoder": cfg.encoder})
    )
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
