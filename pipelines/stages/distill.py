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

from gdwm.api import StageContext, stage
from model_zoo import registry
from model_zoo.encoders.base import EncoderSettings, FoundationEncoder
from pipelines.data.layout import gaussians_table, write_arrow
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow
from pipelines.distill.config import DistillConfig, Encoder
from pipelines.distill.field import load_field
from pipelines.distill.optimize import distill_codes, encode_views, heldout_l1
from pipelines.recon.init import load_views


def load_encoder(cfg: Mapping) -> FoundationEncoder:
    """The frozen E_F, loaded once per actor (``setup``)."""
    c = DistillConfig(**cfg["stage.distill"])
    if c.encoder == Encoder.langsplat:
        raise ValueError(
            "stage.distill.encoder=langsplat: LangSplat's own codes come only with a dataset that ships them "
            "(experiment=gaussiandwm_release); from images, distil encoder=langsplat_proxy"
        )
    try:
        build = registry.get("encoder", c.encoder)
    except registry.UnknownVariant:
        known = [e.value for e in Encoder if ("encoder", e.value) in registry.variants("encoder")]
        raise ValueError(f"stage.distill.encoder: unknown encoder '{c.encoder}' ({', '.join(known)})") from None
    return build(EncoderSettings(d_f=c.d_f, seed=c.seed, path=c.encoder_path, tiny=c.encoder_tiny))


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
    ae_cfg = registry.get("feature_tokenizer", cfg.feature_tokenizer).configure(encoder.d_f, cfg.d_z, cfg.ae_hidden)
    rec_dir = ctx.upstream["reconstruct"].scenes[ctx.scene]
    field = load_field(rec_dir)
    held_set = {tuple(v) for v in json.loads((rec_dir / "views.json").read_text())["heldout"]}
    scene = GSQADataset(ctx.data_root).scene(ctx.scene)

    def log(step: int, metrics: dict[str, float]) -> None:
        ctx.tracker.log_metrics(metrics, step=step)
        if "l_distill" in metrics:
            ctx.progress(step + 1, cfg.distill_steps, f"L_distill {metrics['l_distill']:.4f}")

    # Every view trains and evaluates the shared field; QC-excluded frames only get no output file.
    views = encode_views(encoder, field, load_views(scene), held_set, cfg,
                         lambda done, total: ctx.progress(done, total, "encoding views"))  # fmt: skip
    result = distill_codes(len(field.g), [v for v in views if not v.held], ae_cfg, cfg, log, ctx.scene)
    # Held-out views: distilled field vs a per-scene mean-feature baseline, same metric (L1 over valid pixels).
    ours, base = heldout_l1(result, [v for v in views if v.held])
    metrics = {
        "l_ae_final": float(result.ae_losses[-1]),
        "l_distill_final": result.l_distill_final,
        "heldout_l1": float(np.mean(ours)) if ours else float("nan"),
        "heldout_l1_mean_baseline": float(np.mean(base)) if base else float("nan"),
    }
    metrics["heldout_l1_reduction"] = 1.0 - metrics["heldout_l1"] / metrics["heldout_l1_mean_baseline"]
    ctx.tracker.log_metrics(metrics)

    codes = result.codes_NZ.numpy().astype(np.float32)
    for f in scene.frames():
        if f.idx in field.excluded_frames:
            continue
        _, _, keep = field.poses[f.idx].apply(field.g)
        rel = Path("gaussians") / f"{f.idx:05d}.arrow"
        arrays = gaussians_from_table(read_arrow(rec_dir / rel, f.where))
        arrays["feature"] = codes[keep.numpy()]
        write_arrow(gaussians_table(arrays, where=f.where), ctx.out_dir / rel)
    torch.save(result.ae.state_dict(), ctx.out_dir / "decoder.pt")
    (ctx.out_dir / "autoencoder.json").write_text(
        json.dumps({"variant": cfg.feature_tokenizer, "config": asdict(ae_cfg), "encoder": cfg.encoder})
    )
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
