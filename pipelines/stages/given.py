"""distill, for a dataset that ships its Gaussians (the GaussianDWM release): the dataset's per-frame Gaussians and
their 3-d LangSplat codes as they are, in the distill stage's output layout, so the tokenizer, lora and evaluate_qa
stages read them as they read distilled scenes. This is the journal table's "Distillation ✗" input (the conference
model's language features); a row that asks for foundation-feature distillation (``stage.distill.feature_tokenizer=
foundation``) needs the camera images the release does not have, and is refused before launch.

D_F is the identity on the codes (a one-layer map with identity weights): the release's model reads
``_language_feature`` directly and ships no decoder for it, so the world model's features are the codes themselves
(its shared feature head, which trains, sits on top as on distilled scenes).

Output of one scene (as ``pipelines.stages.distill``)::

    gaussians/<frame:05d>.arrow   the dataset's Gaussians of that frame, byte for byte (``feature`` = the 3-d code)
    decoder.pt                    D_F (and E_z): identity maps, loaded with weights_only=True
    autoencoder.json              their config, the variant ``langsplat3`` and the encoder ``given``
    metrics.json                  frames and Gaussians read
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict

import torch

from gdwm.api import StageContext, stage
from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder
from pipelines.data.layout import gaussians_relpath
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow
from pipelines.distill.config import DistillConfig, Encoder, FeatureTokenizer

GIVEN = "given"
"""``autoencoder.json`` ``encoder`` of scenes whose codes came with the dataset."""


def _needs(config: dict) -> dict[str, str]:
    needs = {"gaussians": "reads the dataset's own per-frame Gaussians and their codes"}
    cfg = DistillConfig(**config["stage.distill"])
    if cfg.encoder != Encoder.langsplat or cfg.feature_tokenizer != FeatureTokenizer.langsplat3:
        why = f"distilling {cfg.encoder} features (stage.distill.encoder={cfg.encoder}, feature_tokenizer="
        why += f"{cfg.feature_tokenizer}; the dataset's own codes are encoder=langsplat, feature_tokenizer=langsplat3)"
        needs |= {"images": f"{why} encodes the camera images", "cameras": f"{why} renders into every camera"}
    return needs


def identity_autoencoder(d: int) -> tuple[FeatureAEConfig, FeatureAutoencoder]:
    """E_z and D_F as identity maps on ``d``-dim codes (one linear layer each)."""
    cfg = FeatureAEConfig(d_f=d, d_z=d, hidden=d, layers=1)
    ae = FeatureAutoencoder(cfg)
    with torch.no_grad():
        for layer in (ae.encoder[0], ae.decoder[0]):
            layer.weight.copy_(torch.eye(d))
            layer.bias.zero_()
    return cfg, ae.requires_grad_(False)


@stage("distill", "1", config=["stage.distill"], per_scene=True, resources="cpu", needs=_needs)
def given_gaussians(ctx: StageContext) -> dict:
    scene = GSQADataset(ctx.data_root).scene(ctx.scene)
    dims, frames, gaussians = set(), 0, 0
    for f in scene.frames():
        src = ctx.data_root / gaussians_relpath(ctx.scene, f.idx)
        if not src.is_file():  # a frame without Gaussians in the release: its samples are skipped and counted
            continue
        arrays = gaussians_from_table(read_arrow(src, f.where))
        if "feature" not in arrays:
            raise ValueError(f"{f.where}: {src} has no feature codes; the release's Gaussians carry _language_feature")
        dims.add(int(arrays["feature"].shape[1]))
        frames, gaussians = frames + 1, gaussians + len(arrays["xyz"])
        dst = ctx.out_dir / "gaussians" / f"{f.idx:05d}.arrow"
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst)
    if not frames:
        raise ValueError(f"{ctx.scene}: the dataset at {ctx.data_root} has no Gaussians for any frame of this scene")
    if len(dims) != 1:
        raise ValueError(f"{ctx.scene}: the frames' feature codes differ in width {sorted(dims)}")
    cfg, ae = identity_autoencoder(dims.pop())
    torch.save(ae.state_dict(), ctx.out_dir / "decoder.pt")
    meta = {"variant": FeatureTokenizer.langsplat3.value, "config": asdict(cfg), "encoder": GIVEN}
    (ctx.out_dir / "autoencoder.json").write_text(json.dumps(meta))
    metrics = {"frames": frames, "gaussians": gaussians, "feature_dim": cfg.d_z}
    ctx.tracker.log_metrics({k: float(v) for k, v in metrics.items()})
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
