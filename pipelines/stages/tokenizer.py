"""tokenizer (stage 1): the LLM frozen; the shared feature head (when distillation is on), projection and fine adapter
train with L_LM + lambda_KL alpha(t) L_KL (Sec. Scene Understanding with Gaussian World Tokens, Training Strategy).

The LLM comes from the ``llm`` stage (the tiny flavor, built once for every row) or ``model.llm.path`` (full runs)
and is saved with the model, so every later stage reads the same one. Output: a saved world model
(``pipelines.understanding.model``), ``metrics.json`` and ``val_predictions.parquet``, registered in the model zoo as
``gdwm-tokenizer`` when it trained; ``source: zoo:gdwm-tokenizer@champion`` takes the model from the zoo instead.
"""

from __future__ import annotations

from gdwm.api import StageContext, stage
from model_zoo.llm.qwen3_vl import WorldLLM
from pipelines.understanding.config import TokenizerStageConfig
from pipelines.understanding.model import LLM_DIR, WORLD_FILE, build_world_model, load_world_model
from pipelines.understanding.stage_common import (
    MODEL_CONFIG,
    components,
    finish,
    run_training,
    training_samples,
    understanding_needs,
)


@stage("tokenizer", "2", config=[*MODEL_CONFIG, "stage.tokenizer"], upstream=["llm", "distill"], resources="train",
       seeded=True, needs=understanding_needs)  # fmt: skip
def tokenizer(ctx: StageContext) -> dict:
    comp = components(ctx)
    cfg = TokenizerStageConfig(**ctx.cfg("stage.tokenizer"))
    scene_dirs = dict(ctx.upstream["distill"].scenes)
    if cfg.source:  # from the model zoo: nothing trains
        model = load_world_model(ctx.zoo_path(cfg.source))
        return finish(ctx, model, cfg, scene_dirs, {"train_samples": 0, "trained": 0.0})
    train = training_samples(ctx, scene_dirs)
    init = ctx.checkpoint_dir / "init"
    if not (init / WORLD_FILE).is_file():  # a resumed attempt reuses the same initial model
        built = ctx.upstream["llm"].path / LLM_DIR
        llm = WorldLLM.from_pretrained(built if comp.llm.tiny else comp.llm.path, comp.llm)
        build_world_model(comp, llm, scene_dirs, seed=ctx.seed).save(init, save_llm=True)
    trains = comp.world.gaussian_tokens and cfg.steps > 0  # image-only models have nothing to train in stage 1
    model = run_training(ctx, "tokenizer", init, cfg, scene_dirs) if trains else load_world_model(init)
    extra = {"train_samples": len(train), "trained": float(trains)}
    return finish(ctx, model, cfg, scene_dirs, extra, register="gdwm-tokenizer" if trains else None)
