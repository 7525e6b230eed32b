"""evaluate_qa and evaluate_gen: the benchmark numbers of a trial.

``evaluate_qa`` answers the held-out QA with the LoRA'd world model in batches on a pool of Ray actors (each loads
the model once; fractional GPUs on the cluster, ``cluster.resources.eval``), scores the answers with every
understanding suite (NuInteract, NuInstruct, OmniDrive) and keeps the per-sample predictions as Parquet.

``evaluate_gen`` generates every held-out target of the val scenes with the trained diffusion model — lateral shifts
and future horizons, the latter on recorded or LLM-predicted ego poses — and scores them against ground truth.

Output: ``metrics.json`` (the stage's return value: the trial's metrics), ``protocol.json`` (what every metric
used; QA: each labelled ``official`` or ``approximate``, and ``proxy`` where the suite mapping says so, as the stage
run's params ``protocol/<metric>`` and ``proxy/<metric>`` that ``gdwm compare`` prints), and ``predictions.parquet``
(QA, with the suite mapping in its schema metadata) or ``samples/<target>/...png`` (generation). QA metrics that are
means over subtasks (NuInstruct's protocol) also write each subtask's value to ``subtasks.json``.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import pyarrow as pa
import ray
import torch
from ray.util import ActorPool

from gdwm.api import StageContext, stage
from pipelines.data.reader import GSQADataset
from pipelines.evaluate.config import FUTURE_POSES, EvaluateGenConfig, EvaluateQAConfig
from pipelines.evaluate.suites import score_predictions, score_table, with_mapping
from pipelines.generation.config import VIEW_TARGETS
from pipelines.understanding.data import FrameStore, QASample, balanced_subset, row_samples
from pipelines.understanding.infer import PREDICTION_SCHEMA, predict, write_predictions
from pipelines.understanding.model import load_world_model


class _Answerer:
    """One evaluation worker: the world model and its frame store, loaded once."""

    def __init__(self, model_dir: str, data_root: str, scene_dirs: dict[str, str]):
        self.model = load_world_model(Path(model_dir)).eval()
        if torch.cuda.is_available():
            self.model.to("cuda")
        w = self.model.comp.world
        self.store = FrameStore(GSQADataset(Path(data_root)), {k: Path(v) for k, v in scene_dirs.items()},
                                w.weather, w.trajectory_frames)  # fmt: skip

    def answer(self, batch: list[QASample], max_new_tokens: int) -> pa.Table:
        with torch.no_grad():
            return predict(self.model, batch, self.store, len(batch), max_new_tokens)


def answer_all(ctx: StageContext, model_dir: Path, samples: list[QASample], cfg: EvaluateQAConfig) -> pa.Table:
    """Answers of ``samples`` in batches, on ``resources.num_workers`` actors (in this process when 0)."""
    scene_dirs = {k: str(v) for k, v in ctx.upstream["distill"].scenes.items()}
    batches = [samples[i : i + cfg.batch_size] for i in range(0, len(samples), cfg.batch_size)]
    res = ctx.resources
    n_workers = min(int(res.get("num_workers", 0)), len(batches))
    tables, done = [], 0
    if n_workers == 0:
        local = _Answerer(str(model_dir), str(ctx.data_root), scene_dirs)
        results = (local.answer(b, cfg.max_new_tokens) for b in batches)
    else:
        actor = ray.remote(num_cpus=float(res.get("num_cpus", 1)), num_gpus=float(res.get("num_gpus", 0)))(_Answerer)
        pool = ActorPool([actor.remote(str(model_dir), str(ctx.data_root), scene_dirs) for _ in range(n_workers)])
        results = pool.map_unordered(lambda a, b: a.answer.remote(b, cfg.max_new_tokens), batches)
    for t in results:
        tables.append(t)
        done += t.num_rows
        ctx.progress(done, len(samples), "answering")
    if not tables:
        return PREDICTION_SCHEMA.empty_table()
    table = pa.concat_tables(tables)
    order = {s.sample_id: i for i, s in enumerate(samples)}  # back to sample order (ranking-based mAP uses it)
    return table.take(sorted(range(table.num_rows), key=lambda i: order[table["sample_id"][i].as_py()]))


@stage("evaluate_qa", "1", config=["stage.evaluate_qa"], upstream=["lora", "distill"], resources="eval",
       evaluation=True, samples="predictions.parquet", score=score_table, strata="task",
       needs={"qa": "answers the held-out QA"})  # fmt: skip
def evaluate_qa(ctx: StageContext) -> dict:
    cfg = EvaluateQAConfig(**ctx.cfg("stage.evaluate_qa"))
    model_dir = ctx.upstream["lora"].path
    ds = GSQADataset(ctx.data_root)
    # every row of a table answers the same samples, whether or not it reads Gaussian tokens
    samples, skipped = row_samples(ds, cfg.split, dict(ctx.upstream["distill"].scenes))
    if cfg.tasks:
        samples = [s for s in samples if s.task in cfg.tasks]
    samples = balanced_subset(samples, cfg.max_samples)
    if not samples:
        raise ValueError(
            f"evaluate_qa: split '{cfg.split}' has no samples to answer (tasks {cfg.tasks or 'all'}; "
            f"skipped {dict(skipped)})"
        )
    table = with_mapping(answer_all(ctx, model_dir, samples, cfg), cfg.suites)  # rescorings use the same mapping
    write_predictions(table, ctx.out_dir / "predictions.parquet")
    result = score_predictions(table.to_pylist(), cfg.suites)
    metrics = {**result.flat(), **{f"count/skipped/{k}": float(v) for k, v in skipped.items()}}
    metrics["count/answered"] = float(table.num_rows)
    (ctx.out_dir / "protocol.json").write_text(json.dumps(result.protocol, indent=2, sort_keys=True))
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    ctx.tracker.log_metrics(metrics)
    ctx.tracker.log_params({"split": cfg.split, "samples": len(samples), **result.params()})  # labels for compare
    ctx.tracker.log_artifact(str(ctx.out_dir / "predictions.parquet"))
    ctx.tracker.log_artifact(str(ctx.out_dir / "protocol.json"))
    if result.subtasks:  # metrics that are means over subtasks (NuInstruct's protocol): each subtask's value
        (ctx.out_dir / "subtasks.json").write_text(json.dumps(result.subtasks, indent=2, sort_keys=True))
        ctx.tracker.log_artifact(str(ctx.out_dir / "subtasks.json"))
    return metrics


@stage("evaluate_gen", "2", config=["stage.evaluate_gen"], upstream=["diffusion", "reconstruct", "lora", "distill"],
       resources="eval", evaluation=True, seeded=True, needs=VIEW_TARGETS)  # fmt: skip
def evaluate_gen(ctx: StageContext) -> dict:
    from model_zoo.diffusion.rgbd_dual import RGBDDual
    from pipelines.generation.examples import build_examples, conditions_of, pad_tokens, save_grid, split_scenes
    from pipelines.generation.frechet import build_extractor, build_video_extractor, label
    from pipelines.generation.metrics import PROTOCOL, score_views
    from pipelines.generation.samples import enumerate_targets, stack
    from pipelines.generation.trajectory import predicted_future_targets

    cfg = EvaluateGenConfig(**ctx.cfg("stage.evaluate_gen"))
    if cfg.future_poses not in FUTURE_POSES:
        raise ValueError(f"stage.evaluate_gen.future_poses: unknown '{cfg.future_poses}' (one of {list(FUTURE_POSES)})")
    extractor = build_extractor(cfg.fd_extractor, cfg.fd_weights)  # a missing weight file fails before sampling
    video = build_video_extractor(cfg.fvd_weights)
    model = RGBDDual.from_pretrained(ctx.upstream["diffusion"].path).eval()
    ds = GSQADataset(ctx.data_root)
    rec_dirs = dict(ctx.upstream["reconstruct"].scenes)
    distill_dirs = dict(ctx.upstream["distill"].scenes)
    scenes = split_scenes(ds, set(rec_dirs))["val"]
    needs_world = model.cfg.high_level or (cfg.future_poses == "predicted" and cfg.horizons_s)
    world = load_world_model(ctx.upstream["lora"].path).eval() if needs_world else None
    horizons = cfg.horizons_s if cfg.future_poses == "recorded" else []
    targets = [
        t for t in enumerate_targets(ds, scenes, cfg.cameras, cfg.shifts_m, horizons, []) if t.frame < cfg.frames
    ]
    unparsed = 0
    if cfg.future_poses == "predicted":
        predicted, unparsed = predicted_future_targets(world, ds, distill_dirs, scenes, cfg.cameras, cfg.horizons_s,
                                                       cfg.frames)  # fmt: skip
        targets += predicted
    held, skipped = build_examples(ds, targets, rec_dirs, model.cfg.image_size)
    if not held:
        raise ValueError(f"evaluate_gen: no held-out targets in val scenes {scenes} ({skipped} skipped)")
    c_L = conditions_of(world if model.cfg.high_level else None, ds, distill_dirs, [e.target.qa() for e in held],
                        cfg.batch_size)  # fmt: skip
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
            save_grid(ctx.out_dir / f"samples/{t.name}/{t.scene}_{t.frame:03d}_{t.camera}.png", ex, rgb[j])
        ctx.progress(min(i + cfg.batch_size, len(held)), len(held), "generating")
    metrics = score_views(scored, model.cfg.max_depth, extractor, video, cfg.fvd_clip_frames)
    metrics |= {"count/heldout_views": float(len(held)), "count/skipped_targets": float(skipped)}
    if cfg.future_poses == "predicted":
        metrics["count/trajectory_without_pose_at_horizon"] = float(unparsed)
    protocol = {
        "views": PROTOCOL,
        "frechet": label(extractor),
        "fvd": label(video),
        "future_poses": cfg.future_poses,
        "config": asdict(cfg),
    }
    (ctx.out_dir / "protocol.json").write_text(json.dumps(protocol, indent=2, sort_keys=True))
    (ctx.out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    ctx.tracker.log_metrics(metrics)
    ctx.tracker.log_params({"fd_protocol": protocol["frechet"], "fvd_protocol": protocol["fvd"],
                            "metrics_protocol": PROTOCOL})  # fmt: skip
    ctx.tracker.log_artifact(str(ctx.out_dir / "protocol.json"))
    return metrics
