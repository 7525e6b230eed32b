"""reconstruct: initialisation, frames, posing of moving objects, QC, and the stage on a tiny scene."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from gdwm.stage import StageContext
from pipelines.data.layout import pose_matrix
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow
from pipelines.recon.config import ReconstructConfig
from pipelines.recon.init import aggregate_lidar, box_pose, voxel_downsample
from pipelines.recon.optimize import FramePoses, NaNLossError, Trainer, init_gaussians
from pipelines.stages.reconstruct import reconstruct, split_views, to_ego


class Recorder:
    def __init__(self):
        self.metrics, self.params = [], {}

    def log_metrics(self, m, step=None):
        self.metrics.append((step, dict(m)))

    def log_params(self, p):
        self.params.update(p)

    def flush(self):
        return None


def test_split_views_holds_out_every_nth():
    train, held = split_views(20, 8)
    assert held == [4, 12] and len(train) == 18 and not set(train) & set(held)
    assert split_views(5, 0) == ([0, 1, 2, 3, 4], [])


def test_to_ego_moves_centres_and_rotations():
    yaw = np.pi / 2
    ego2world = pose_matrix([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], [10.0, 5.0, 0.0])
    world = {"xyz": np.array([[10.0, 7.0, 1.0]], np.float32), "rotation": np.array([[1.0, 0, 0, 0]], np.float32)}
    ego = to_ego(world, ego2world)
    # 2 m along world +y from the ego, which faces +y: 2 m straight ahead
    np.testing.assert_allclose(ego["xyz"], [[2.0, 0.0, 1.0]], atol=1e-5)
    np.testing.assert_allclose(np.abs(ego["rotation"][0]), [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-6)


def test_frame_poses_move_dynamic_gaussians_and_hide_absent_ones():
    g = init_gaussians(
        np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]), np.full((3, 3), 0.5), np.full(3, 0.1), np.array([-1, 0, 1])
    )
    pose = box_pose({"center": [5.0, 1.0, 0.0], "yaw": np.pi / 2})
    fp = FramePoses.build(["car-a", "car-b"], {"car-a": pose})  # car-b is absent in this frame
    means, quats, keep = fp.apply(g)
    assert keep.tolist() == [True, True, False]
    np.testing.assert_allclose(means.numpy(), [[0, 0, 0], [5.0, 2.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(quats[1].numpy(), [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-6)


def test_voxel_downsample_keeps_one_point_per_voxel_and_caps():
    pts = np.array([[0.01, 0, 0], [0.02, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    assert len(voxel_downsample(pts, 0.5, 10, 0)) == 3
    assert len(voxel_downsample(pts, 0.5, 2, 0)) == 2


def test_aggregate_lidar_splits_moving_objects(synth_small):
    scene = GSQADataset(synth_small).scene("scene-0001")
    lidar = aggregate_lidar(scene, split_moving=True, moving_speed=0.5)
    kept = aggregate_lidar(scene, split_moving=False, moving_speed=0.5)
    n_dyn = sum(len(v) for v in lidar.dynamic.values())
    assert len(lidar.static_P3) + n_dyn == len(kept.static_P3) and kept.dynamic == {}
    moving = {b["instance_id"] for f in scene.frames() for b in f.boxes3d() if np.hypot(*b["velocity"]) > 0.5}
    assert set(lidar.dynamic) <= moving and n_dyn > 0
    for inst, pts in lidar.dynamic.items():  # box frame: every return lies within the (inflated) box
        size = next(b["size"] for f in scene.frames() for b in f.boxes3d() if b["instance_id"] == inst)
        assert (np.abs(pts) <= np.asarray(size) / 2 + 0.21).all(), inst


def test_scene_without_lidar_returns_is_named(synth_small, tmp_path):
    import shutil

    from pipelines.data.layout import LIDAR_SCHEMA, DataError, lidar_relpath, write_arrow

    root = tmp_path / "data"
    shutil.copytree(synth_small, root)
    scene = GSQADataset(root).scene("scene-0001")
    for f in scene.frames():  # every sweep present and readable, but with no returns
        write_arrow(LIDAR_SCHEMA.empty_table(), root / lidar_relpath("scene-0001", f.idx))
    assert GSQADataset(root).scene("scene-0001").frame(0).lidar().shape == (0, 4)
    with pytest.raises(DataError, match=r"^scene-0001: no LiDAR points \(reconstruction is LiDAR-initialised\)$"):
        aggregate_lidar(GSQADataset(root).scene("scene-0001"), split_moving=True, moving_speed=0.5)


def test_nan_loss_names_the_view(synth_small):
    from pipelines.recon.init import load_views

    scene = GSQADataset(synth_small).scene("scene-0000")
    v = load_views(scene)[0]
    g = init_gaussians(np.array([[0.0, 0, 5]]), np.full((1, 3), 0.5), np.full(1, 0.1))
    g.color_logits = torch.full((1, 3), float("nan"))
    t = Trainer(g, ReconstructConfig(depth_weight=0), 1.0, torch.zeros(3), {0: FramePoses.build([], {})})
    with pytest.raises(NaNLossError, match=r"frame 0 CAM_FRONT: rasterize: colors \(shape \(1, 3\)\) contains NaN"):
        t.step(v)


def run_tiny_reconstruct(data: Path, out: Path, min_psnr_db: float) -> tuple[dict, Recorder]:
    """The reconstruct stage on scene-0000 of ``data`` with a seconds-sized budget (shared with the distill tests)."""
    cfg = asdict(
        ReconstructConfig(
            iterations=40,
            max_gaussians=2500,
            voxel_m=0.4,
            densify_from=10,
            densify_until=30,
            densify_every=10,
            opacity_reset_every=0,
            min_psnr_db=min_psnr_db,
        )
    )
    rec = Recorder()
    out.mkdir(exist_ok=True)
    ctx = StageContext(
        "reconstruct",
        "k" * 64,
        {"stage.reconstruct": cfg},
        out,
        {},
        Path(data),
        "fp",
        rec,
        out / "ck",
        {},
        scene="scene-0000",
    )
    return reconstruct.fn(ctx), rec


def test_reconstruct_stage_on_a_tiny_scene(synth_small, tmp_path):
    out = tmp_path / "out"
    extra, rec = run_tiny_reconstruct(synth_small, out, min_psnr_db=30.0)
    qc = json.loads((out / "qc.json").read_text())
    losses = [m["loss"] for step, m in rec.metrics if step is not None and "loss" in m]
    assert losses[-1] < losses[0]  # it learns
    assert 5.0 < qc["heldout_psnr_mean"] < 60.0
    # min_psnr_db=30 excludes every frame with held-out views at this tiny budget: recorded, not silent
    assert qc["excluded_frames"] == sorted(int(f) for f, p in qc["frame_psnr"].items() if p < 30.0)
    assert extra["excluded_frames"] == qc["excluded_frames"]
    written = sorted(int(p.stem) for p in (out / "gaussians").glob("*.arrow"))
    assert written == sorted(set(range(10)) - set(qc["excluded_frames"]))
    g = gaussians_from_table(read_arrow(out / "world.arrow", "world"))
    assert g["xyz"].shape[1] == 3 and g["feature"].shape == (len(g["xyz"]), 0)
    assert np.all((g["opacity"] >= 0) & (g["opacity"] <= 1))
    views = json.loads((out / "views.json").read_text())
    assert len(views["heldout"]) == 60 // 8 and len(views["train"]) == 60 - 60 // 8
