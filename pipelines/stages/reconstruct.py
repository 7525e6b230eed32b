"""reconstruct: LiDAR-initialised 3DGS per scene; per-frame Gaussians in each frame's ego frame; held-out QC.

Output of one scene::

    world.arrow                 the optimised static Gaussians in the scene (world) frame
    gaussians/<frame:05d>.arrow the same Gaussians in that frame's ego frame (excluded frames absent)
    qc.json                     per-view PSNR/SSIM of held-out views, per-frame means, excluded frames
    views.json                  which (frame, camera) views were trained on and which held out
    canonical.pt                the field's parameters (static: world frame; moving objects: box frames) + instance
    instances.json              moving instance ids and their per-frame box -> world poses
"""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import torch

from gdwm.api import StageContext, stage
from pipelines.data.layout import gaussians_relpath, gaussians_table, transform_gaussians, write_arrow
from pipelines.data.reader import GSQADataset
from pipelines.recon.config import ReconstructConfig
from pipelines.recon.init import aggregate_lidar, initial_gaussians, load_views
from pipelines.recon.optimize import FramePoses, evaluate, init_gaussians, optimise


def split_views(n: int, every: int) -> tuple[list[int], list[int]]:
    """(train, held-out) indices: every ``every``-th view is held out, starting mid-cycle."""
    if every <= 0:
        return list(range(n)), []
    held = [i for i in range(n) if i % every == every // 2]
    return [i for i in range(n) if i % every != every // 2], held


def to_ego(world: dict[str, np.ndarray], ego2world_44: np.ndarray) -> dict[str, np.ndarray]:
    """Gaussians from the world frame into one frame's ego frame (centres and orientations)."""
    return transform_gaussians(world, np.linalg.inv(ego2world_44))


NEEDS = {
    "cameras": "projects the Gaussians into every camera",
    "images": "fits the Gaussians to the camera images",
    "lidar": "initialises the Gaussians from the aggregated LiDAR",
    "ego_poses": "places every frame's LiDAR and cameras in the scene",
}


@stage("reconstruct", "1", config=["stage.reconstruct"], per_scene=True, resources="gpu", needs=NEEDS)
def reconstruct(ctx: StageContext) -> dict:
    cfg = ReconstructConfig(**ctx.cfg("stage.reconstruct"))
    if cfg.iterations < 1:
        raise ValueError(f"{ctx.scene}: stage.reconstruct.iterations must be >= 1, got {cfg.iterations}")
    scene = GSQADataset(ctx.data_root).scene(ctx.scene)
    lidar = aggregate_lidar(scene, cfg.drop_moving, cfg.moving_speed_mps)
    views = load_views(scene)
    train_idx, held_idx = split_views(len(views), cfg.holdout_every)
    train, held = [views[i] for i in train_idx], [views[i] for i in held_idx]
    init = initial_gaussians(lidar, train, cfg.voxel_m, cfg.max_gaussians, cfg.seed)
    g = init_gaussians(init.points_N3, init.colors_N3, init.scales_N, init.instance_N)
    frame_ids = [f.idx for f in scene.frames()]
    poses = {f: FramePoses.build(init.instances, lidar.poses.get(f, {})) for f in frame_ids}
    centres = np.stack([np.linalg.inv(v.world2cam_44)[:3, 3] for v in views])
    extent = max(1.0, 1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max()))
    ctx.tracker.log_params(
        {
            "initial_gaussians": len(g),
            "train_views": len(train),
            "heldout_views": len(held),
            "moving_instances": len(init.instances),
        }
    )

    def log(it: int, stats: dict) -> None:
        if it % 10 == 0 or it == cfg.iterations - 1:
            ctx.tracker.log_metrics(stats, step=it)
            ctx.progress(it + 1, cfg.iterations, f"loss {stats['loss']:.4f}")

    trainer = optimise(g, train, cfg, log, extent, poses)
    rows = evaluate(trainer, held)
    per_frame: dict[int, list[dict]] = {}
    for r in rows:
        per_frame.setdefault(r["frame"], []).append(r)
    frame_psnr = {f: float(np.mean([r["psnr"] for r in rs])) for f, rs in per_frame.items()}
    frame_ssim = {f: float(np.mean([r["ssim"] for r in rs])) for f, rs in per_frame.items()}
    excluded = sorted(f for f, p in frame_psnr.items() if p < cfg.min_psnr_db)
    for f in sorted(frame_psnr):
        ctx.tracker.log_metrics({"heldout_psnr": frame_psnr[f], "heldout_ssim": frame_ssim[f]}, step=f)
    mean_psnr = float(np.mean([r["psnr"] for r in rows])) if rows else float("nan")
    mean_ssim = float(np.mean([r["ssim"] for r in rows])) if rows else float("nan")
    ctx.tracker.log_metrics({"heldout_psnr_mean": mean_psnr, "heldout_ssim_mean": mean_ssim})

    static = trainer.g.activated()
    write_arrow(gaussians_table(static, where=f"{ctx.scene} world", frame="world"), ctx.out_dir / "world.arrow")
    for f in scene.frames():
        if f.idx in excluded:
            continue
        rel = gaussians_relpath(ctx.scene, f.idx).split("/", 2)[2]  # gaussians/<frame>.arrow
        posed = trainer.g.activated(poses[f.idx])
        write_arrow(gaussians_table(to_ego(posed, f.ego2world), where=f.where), ctx.out_dir / rel)
    qc = {
        "heldout_psnr_mean": mean_psnr,
        "heldout_ssim_mean": mean_ssim,
        "frame_psnr": {str(k): v for k, v in sorted(frame_psnr.items())},
        "frame_ssim": {str(k): v for k, v in sorted(frame_ssim.items())},
        "excluded_frames": excluded,
        "min_psnr_db": cfg.min_psnr_db,
        "views": rows,
        "gaussians": len(trainer.g),
        "config": asdict(cfg),
    }
    (ctx.out_dir / "qc.json").write_text(json.dumps(qc, indent=2))
    # The canonical field (static part in the world, moving objects in their box frames) and the per-frame box
    # poses: what distillation optimises codes on, so a Gaussian keeps one code across frames.
    torch.save(
        {k: v.detach().clone() for k, v in {**trainer.g.params(), "instance": trainer.g.instance}.items()},
        ctx.out_dir / "canonical.pt",
    )
    poses_json = {
        str(f): {k: [float(x) for x in m.reshape(16)] for k, m in lidar.poses.get(f, {}).items()} for f in frame_ids
    }
    (ctx.out_dir / "instances.json").write_text(json.dumps({"instances": init.instances, "poses": poses_json}))
    split = {"train": [[v.frame, v.camera] for v in train], "heldout": [[v.frame, v.camera] for v in held]}
    (ctx.out_dir / "views.json").write_text(json.dumps(split))
    return {"heldout_psnr_mean": mean_psnr, "excluded_frames": excluded, "gaussians": len(trainer.g)}
