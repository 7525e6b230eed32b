"""What the tokenizer and lora stages share: config subtrees, the train call, the held-out monitor, outputs."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gdwm.api import StageContext
from pipelines.data.reader import GSQADataset
from pipelines.understanding.config import LoraStageConfig, TrainConfig
from pipelines.understanding.data import FrameStore, QASample, row_samples, task_counts
from pipelines.understanding.infer import write_predictions
from pipelines.understanding.model import Components, WorldModel, load_world_model
from pipelines.understanding.train import evaluate, train_loop

log = logging.getLogger(__name__)

MODEL_KEYS = ("world", "selector", "projection", "fine_adapter", "alignment", "llm")
MODEL_CONFIG = [f"model.{k}" for k in MODEL_KEYS]


def understanding_needs(config: Mapping[str, Any]) -> dict[str, str]:
    """Dataset tables the tokenizer and lora stages read with this model config (``gdwm.stage.stage(needs=...)``):
    a row whose variant needs what a dataset lacks (the release has no images) is refused before launch."""
    world, selector, alignment = config["model.world"], config["model.selector"], config["model.alignment"]
    needs = {"qa": "trains on the training split's QA"}
    if not world["gaussian_tokens"]:
        needs["images"] = "an image-only row reads the scene from the camera images"
    if alignment["name"] != "none":
        needs["images"] = f"L_KL aligns the world tokens to the image tokens (model.alignment={alignment['name']})"
    if world["gaussian_tokens"] and selector["name"] == "driving_aware":
        needs["ego_poses"] = "the driving-aware selector scores the Gaussians along the ego path"
        if str(selector.get("path")) in ("route", "PathSource.route"):
            needs["routes"] = "model.selector.path=route follows the planned route"
    return needs


def components(ctx: StageContext) -> Components:
    return Components.from_model_cfg({k: ctx.cfg(f"model.{k}") for k in MODEL_KEYS})


def log_skipped(ctx: StageContext, split: str, skipped: dict) -> None:
    """Samples a stage could not use are counted and logged, never dropped silently."""
    for reason, n in sorted(skipped.items()):
        ctx.tracker.log_metrics({f"skipped/{split}/{reason}": float(n)})


def training_samples(ctx: StageContext, scene_dirs: dict[str, Path]) -> list[QASample]:
    """The training split of the stage (``row_samples``): skips logged as metrics, and the samples per task family
    as the params ``tasks/<family>``, so a table's rows show they trained on the same tasks."""
    train, skipped = row_samples(GSQADataset(ctx.data_root), "train", scene_dirs)
    log_skipped(ctx, "train", skipped)
    if missing := skipped.get("instruction_without_gauss_placeholder"):
        log.warning(
            "%s: %d training samples have no <gauss> placeholder and no row trains on them (a synthetic_mini "
            "built by generator version 1 lacks it in trajectory QA: rebuild it with `gdwm data synth`)",
            ctx.name,
            missing,
        )
    ctx.tracker.log_params({f"tasks/{t}": n for t, n in task_counts(train).items()})
    return train


def run_training(
    ctx: StageContext, stage: str, init_dir: Path, cfg: TrainConfig, scene_dirs: dict[str, Path]
) -> WorldModel:
    """Train from ``init_dir`` under Ray Train and return the model with the final state loaded; a
    ``LoraStageConfig`` adds its LoRA (the config travels to the workers as it is: a dataclass pickles)."""
    result = ctx.train(
        train_loop,
        {
            "stage": stage,
            "init_dir": str(init_dir),
            "data_root": str(ctx.data_root),
            "scene_dirs": {k: str(v) for k, v in scene_dirs.items()},
            "train": cfg,
            "seed": ctx.seed,
        },
        total_steps=cfg.steps,
    )
    model = load_world_model(init_dir)
    if isinstance(cfg, LoraStageConfig):
        model.add_lora(cfg)
    if result.state is None:
        raise RuntimeError(f"{stage}: training reported no checkpoint")
    model.load_adapter_state(result.state["adapter"])
    if result.state.get("lora"):
        model.load_lora_state(result.state["lora"])
    return model


def variant(comp: Components) -> str:
    """Zoo variant of a world model: its ablation switches, e.g. ``driving_aware+query_xattn+kl``."""
    if not comp.world.gaussian_tokens:
        return "image_only"
    name = f"{comp.selector.name}+{comp.fine_adapter.name}+{comp.alignment.name}"
    return name if comp.world.train_decoder else f"{name}+frozen_features"


def finish(
    ctx: StageContext,
    model: WorldModel,
    cfg: TrainConfig,
    scene_dirs: dict[str, Path],
    extra: dict,
    register: str | None = None,
) -> dict:
    """Held-out monitor, then the saved model and its metrics in the stage output, registered in the model zoo as
    component ``register`` (e.g. ``gdwm-lora``) when given."""
    ds = GSQADataset(ctx.data_root)
    val, skipped = row_samples(ds, "val", scene_dirs)
    log_skipped(ctx, "val", skipped)
    store = FrameStore(ds, scene_dirs, model.comp.world.weather, model.comp.world.trajectory_frames)
    ev = evaluate(model, val, store, cfg)
    ctx.tracker.log_metrics(ev["metrics"])
    if ev["predictions"] is not None:
        write_predictions(ev["predictions"], ctx.out_dir / "val_predictions.parquet")
    model.save(ctx.out_dir, save_llm=model.comp.llm.tiny or model.comp.llm.path is None)
    n_val = 0 if ev["predictions"] is None else ev["predictions"].num_rows
    metrics = {**extra, **ev["metrics"], "val_samples": n_val}
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    if register:
        ctx.register(register, ".", variant(model.comp))
    return metrics
