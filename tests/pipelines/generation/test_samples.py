"""Generation examples: targets, ground truth, conditions at the model's size; the scores."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipelines.data.reader import GSQADataset
from pipelines.generation.metrics import depth_errors, score_views
from pipelines.generation.samples import GenExample, GenTarget, build_example, enumerate_targets


def _lidar_gaussians(frame) -> dict[str, np.ndarray]:
    xyz = frame.lidar()[:, :3].astype(np.float32)
    n = len(xyz)
    return {
        "xyz": xyz,
        "scale": np.full((n, 3), 0.3, np.float32),
        "rotation": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)).astype(np.float32),
        "opacity": np.full(n, 0.9, np.float32),
        "color": np.full((n, 3), 0.5, np.float32),
    }


def test_enumerate_targets_keeps_futures_inside_the_scene(synth_small):
    ds = GSQADataset(synth_small)
    targets = enumerate_targets(ds, ["scene-0000"], ["CAM_FRONT"], [1.0, -1.0], [1.0], ["rain"])
    kinds = [t.kind for t in targets]
    # 10 frames: 2 shifts + 1 weather each, a 1 s (2-frame) future for frames 0..7
    assert kinds.count("shift") == 20 and kinds.count("weather") == 10 and kinds.count("future") == 8
    assert {t.name for t in targets} == {"shift_1m", "shift_-1m", "future_1s", "weather_rain"}
    t = targets[0]
    assert t.qa().instruction == "Based on <gauss>, generate the CAM_FRONT view shifted 1 m to the left."


@pytest.mark.parametrize(
    "target",
    [
        GenTarget("scene-0000", 3, "CAM_FRONT", "shift", lateral_m=-2.0),
        GenTarget("scene-0000", 3, "CAM_FRONT", "future", horizon_frames=2, horizon_s=1.0),
        GenTarget("scene-0000", 3, "CAM_FRONT", "weather", weather="night"),
    ],
    ids=lambda t: t.name,
)
def test_build_example_resizes_ground_truth_reference_and_conditions(synth_small, target):
    ds = GSQADataset(synth_small)
    frame = ds.scene("scene-0000").frame(3)
    ex = build_example(ds, target, _lidar_gaussians(frame), (24, 40))
    assert ex.target_rgb.shape == ex.ref_rgb.shape == ex.cond_rgb.shape == (3, 24, 40)
    assert ex.target_depth.shape == ex.cond_mask.shape == (24, 40)
    assert 0.05 < float(ex.cond_mask.mean()) <= 1.0  # LiDAR points cover part of the view
    assert float(ex.target_depth.max()) > 0
    same_view = target.kind == "weather"
    assert torch.equal(ex.target_depth, ex.ref_depth) == same_view  # weather: same geometry, new appearance
    assert not torch.equal(ex.target_rgb, ex.ref_rgb)


def test_scores_are_perfect_for_ground_truth_and_depth_errors_match_by_hand():
    gt_d = torch.tensor([[10.0, 20.0], [0.0, 90.0]])  # 0 and > max_depth are not scored
    absrel, rmse = depth_errors(torch.tensor([[11.0, 18.0], [5.0, 5.0]]), gt_d, max_depth=80.0)
    assert absrel == pytest.approx((0.1 + 0.1) / 2) and rmse == pytest.approx(np.sqrt((1 + 4) / 2))
    t = GenTarget("s", 0, "CAM_FRONT", "shift", lateral_m=1.0)
    rgb = torch.rand(3, 8, 8)
    depth = torch.full((8, 8), 12.0)
    ex = GenExample(t, rgb, depth, rgb, depth, rgb, depth, torch.ones(8, 8))
    s = score_views([(ex, rgb, depth)])
    assert s["gen/shift_1m/ssim"] == pytest.approx(1.0) and s["gen/shift_1m/psnr"] == float("inf")
    assert s["gen/shift_1m/depth_absrel"] == 0.0 and s["gen/shift_1m/depth_rmse"] == 0.0
