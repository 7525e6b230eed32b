"""lora (stage 2): peft LoRA on the LLM with the Gaussian adapter trainable; ``mode: zero_shot`` trains nothing
and drops the Gaussian tokens (tab:qa-ablation-conference, first row); ``source: zoo:gdwm-lora@champion`` takes
the model from the zoo. Output as the tokenizer stage's, plus ``lora/`` (the peft adapter); a trained one is
registered as ``gdwm-lora``."""

from __future__ import annotations

from dataclasses import replace

from gdwm.api import StageContext, stage
from pipelines.understanding.config import LoraStageConfig
from pipelines.understanding.model import load_world_model
from pipelines.understanding.stage_common import (
    MODEL_CONFIG,
    finish,
    run_training,
    training_samples,
    understanding_needs,
)

MODES = ("train", "zero_shot")


@stage("lora", "2", config=[*MODEL_CONFIG, "stage.lora"], upstream=["tokenizer", "distill"], resources="train",
       seeded=True, needs=understanding_needs)  # fmt: skip
def lora(ctx: StageContext) -> dict:
    cfg = LoraStageConfig(**ctx.cfg("stage.lora"))
    if cfg.mode not in MODES:
        raise ValueError(f"stage.lora.mode: unknown mode '{cfg.mode}' (one of {list(MODES)})")
    init = ctx.upstream["tokenizer"].path
    scene_dirs = dict(ctx.upstream["distill"].scenes)
    if cfg.source:  # from the model zoo: nothing trains, the version's world model is the output
        if cfg.mode != "train":
            raise ValueError(f"stage.lora: source={cfg.source} needs mode=train, got mode={cfg.mode}")
        model = load_world_model(ctx.zoo_path(cfg.source))
        return finish(ctx, model, cfg, scene_dirs, {"train_samples": 0, "trained": 0.0})
    if cfg.mode == "zero_shot":
        model = load_world_model(init)
        model.comp = replace(model.comp, world=replace(model.comp.world, gaussian_tokens=False))
        return finish(ctx, model, cfg, scene_dirs, {"train_samples": 0, "trained": 0.0})
    train = training_samples(ctx, scene_dirs)
    model = run_training(ctx, "lora", init, cfg, scene_dirs)
    return finish(ctx, model, cfg, scene_dirs, {"train_samples": len(train), "trained": 1.0}, register="gdwm-lora")
