"""Target cameras and low-level conditions: pinhole offsets by hand, zero shifts, the recorded views as reference."""

from __future__ import annotations

import re

import numpy as np
import pytest

from pipelines.data.reader import GSQADataset
from pipelines.data.synth.novel_view import render_view
from pipelines.generation.conditions import (
    NoGaussiansInView,
    future_camera_pose,
    horizon_frames,
    low_level_conditions,
    render_ego,
    shifted_camera_pose,
    target_name,
)
from pipelines.generation.samples import GenTarget, enumerate_targets, target_pose
from pipelines.recon.init import load_views

K_33 = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 18.0], [0.0, 0.0, 1.0]])
W, H = 64, 36


def one_gaussian(xyz, opacity=0.99, scale=0.05, color=(0.2, 0.6, 0.9)) -> dict[str, np.ndarray]:
    return {
        "xyz": np.array([xyz], np.float32),
        "scale": np.full((1, 3), scale, np.float32),
        "rotation": np.array([[1.0, 0, 0, 0]], np.float32),
        "opacity": np.array([opacity], np.float32),
        "color": np.array([color], np.float32),
        "feature": np.zeros((1, 0), np.float32),
    }


def backprojected(frame, camera: str, max_depth: float = 60.0) -> dict[str, np.ndarray]:
    """The stored depth of one view as small opaque Gaussians (ego frame), coloured by the stored image."""
    cam = frame.scene.cameras[camera]
    depth, rgb = frame.depth(camera), frame.image(camera) / 255.0
    v, u = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
    ok = (depth > 0) & (depth < max_depth)
    K = cam.K_33
    pc = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], -1)[ok]
    n = len(pc)
    return {
        "xyz": (pc @ cam.sensor2ego_44[:3, :3].T + cam.sensor2ego_44[:3, 3]).astype(np.float32),
        "scale": np.repeat((depth[ok] / K[0, 0] * 0.5)[:, None], 3, 1).astype(np.float32),
        "rotation": np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
        "opacity": np.full(n, 0.99, np.float32),
        "color": rgb[ok].astype(np.float32),
    }


@pytest.fixture(scope="module")
def scene0(synth_small):
    return GSQADataset(synth_small).scene("scene-0000")


def test_shifted_pose_moves_the_camera_in_the_ego_frame():
    s2e = np.eye(4)
    s2e[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    s2e[:3, 3] = [1.7, 0.0, 1.51]
    moved = shifted_camera_pose(s2e, lateral_m=2.0, longitudinal_m=-3.0)
    np.testing.assert_array_equal(moved[:3, :3], s2e[:3, :3])
    np.testing.assert_allclose(moved[:3, 3], [1.7 - 3.0, 2.0, 1.51])
    assert np.array_equal(shifted_camera_pose(s2e), s2e) and shifted_camera_pose(s2e) is not s2e


@pytest.mark.parametrize("lateral", [0.0, 2.0, -4.0])
def test_projection_lands_on_the_hand_computed_pixel(scene0, lateral):
    """One small opaque Gaussian ahead of CAM_FRONT: its alpha-weighted centroid is the pinhole pixel by hand."""
    s2e = scene0.cameras["CAM_FRONT"].sensor2ego_44
    # the stored CAM_FRONT looks along ego +x: camera x right = ego -y, y down = ego -z, z forward = ego +x
    np.testing.assert_allclose(s2e[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-6)
    cx, cy, cz = s2e[:3, 3]
    p = (10.0, 1.0, 1.0)
    X, Y, Z = -(p[1] - (cy + lateral)), -(p[2] - cz), p[0] - cx
    u_hand, v_hand = 50.0 * X / Z + 32.0, 50.0 * Y / Z + 18.0
    out = render_ego(one_gaussian(p), K_33, shifted_camera_pose(s2e, lateral_m=lateral), W, H)
    a = out.alpha.numpy()
    v, u = np.mgrid[0:H, 0:W] + 0.5  # pixel centres
    assert abs((a * u).sum() / a.sum() - u_hand) < 0.5
    assert abs((a * v).sum() / a.sum() - v_hand) < 0.5
    cond = low_level_conditions(
        one_gaussian(p),
        K_33,
        shifted_camera_pose(s2e, lateral_m=lateral),
        W,
        H,
        scene="scene-0000",
        frame=0,
        alpha_threshold=0.3,
    )
    assert cond.mask.sum() > 0
    np.testing.assert_allclose(cond.depth[cond.mask], Z, rtol=1e-5)
    np.testing.assert_allclose(cond.rgb[cond.mask], np.tile([0.2, 0.6, 0.9], (cond.mask.sum(), 1)), atol=1e-5)


def test_a_2m_left_shift_moves_the_point_right_by_fx_times_2_over_z(scene0):
    s2e = scene0.cameras["CAM_FRONT"].sensor2ego_44
    _, u = np.mgrid[0:H, 0:W] + 0.5
    cols = []
    for lateral in (0.0, 2.0):
        a = render_ego(one_gaussian((10.0, 1.0, 1.0)), K_33, shifted_camera_pose(s2e, lateral_m=lateral), W, H).alpha
        cols.append(float((a.numpy() * u).sum() / a.numpy().sum()))
    assert abs((cols[1] - cols[0]) - 50.0 * 2.0 / (10.0 - s2e[0, 3])) < 0.5


def test_conditions_shapes_mask_and_zeros_outside():
    s2e = np.eye(4)
    s2e[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    g = one_gaussian((6.0, 0.0, 0.0), scale=0.4)
    c = low_level_conditions(g, K_33, s2e, W, H, scene="scene-0000", frame=1)
    assert c.rgb.shape == (H, W, 3) and c.depth.shape == (H, W) and c.mask.shape == (H, W)
    assert c.rgb.dtype == np.float32 and c.depth.dtype == np.float32 and c.mask.dtype == bool
    assert 0 < c.mask.sum() < H * W
    assert (c.rgb[~c.mask] == 0).all() and (c.depth[~c.mask] == 0).all()
    np.testing.assert_allclose(c.depth[c.mask], 6.0, rtol=1e-5)
    alpha = render_ego(g, K_33, s2e, W, H).alpha.numpy()
    np.testing.assert_array_equal(c.mask, alpha >= 0.5)
    faint = one_gaussian((6.0, 0.0, 0.0), scale=0.4, opacity=0.3)
    assert low_level_conditions(faint, K_33, s2e, W, H, scene="s", frame=1).mask.sum() == 0
    assert low_level_conditions(faint, K_33, s2e, W, H, scene="s", frame=1, alpha_threshold=0.2).mask.sum() > 0


def test_zero_shift_reproduces_the_unshifted_conditions(scene0):
    cam = scene0.cameras["CAM_FRONT"]
    g = backprojected(scene0.frame(2), "CAM_FRONT")
    a = low_level_conditions(g, cam.K_33, cam.sensor2ego_44, cam.width, cam.height, scene="scene-0000", frame=2)
    pose = shifted_camera_pose(cam.sensor2ego_44, 0.0, 0.0)
    b = low_level_conditions(g, cam.K_33, pose, cam.width, cam.height, scene="scene-0000", frame=2)
    for x, y in ((a.rgb, b.rgb), (a.depth, b.depth), (a.mask, b.mask)):
        np.testing.assert_array_equal(x, y)


def test_no_gaussians_in_view_names_scene_frame_and_pose():
    s2e = np.eye(4)
    s2e[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    behind = one_gaussian((-5.0, 0.0, 0.0))
    msg = "scene-0003/frame_007: no Gaussians in view of the target camera (shift_-4m CAM_FRONT)"
    with pytest.raises(ValueError, match=re.escape(msg)):
        low_level_conditions(behind, K_33, s2e, W, H, scene="scene-0003", frame=7, target="shift_-4m CAM_FRONT")
    msg = "scene-0003/frame_007: no Gaussians in view of the target camera (camera at ego (0.00, 2.00, 0.00) m)"
    with pytest.raises(ValueError, match=re.escape(msg)):
        low_level_conditions(behind, K_33, shifted_camera_pose(s2e, 2.0), W, H, scene="scene-0003", frame=7)
    empty = {k: v[:0] for k, v in behind.items()}
    with pytest.raises(NoGaussiansInView, match=r"scene-0003/frame_007: no Gaussians in view"):
        low_level_conditions(empty, K_33, s2e, W, H, scene="scene-0003", frame=7)


def test_future_pose_at_horizon_zero_is_the_current_camera(scene0):
    s2e = scene0.cameras["CAM_FRONT"].sensor2ego_44
    np.testing.assert_allclose(future_camera_pose(scene0.ego_poses, 3, 0, s2e), s2e, atol=1e-9)


def test_future_pose_is_the_recorded_future_view_in_the_current_ego_frame(scene0):
    """Against the reconstruction's own view poses: ego2world[f] @ target == cam2world of view (f + h)."""
    views = {(v.frame, v.camera): v for v in load_views(scene0)}
    for f, h, cam in ((2, 2, "CAM_FRONT"), (5, 4, "CAM_BACK_LEFT")):
        target = future_camera_pose(scene0.ego_poses, f, h, scene0.cameras[cam].sensor2ego_44)
        np.testing.assert_allclose(
            scene0.ego_poses[f] @ target, np.linalg.inv(views[(f + h, cam)].world2cam_44), atol=1e-5
        )
    with pytest.raises(ValueError, match=r"scene-0000/frame_008: horizon 2 frames reaches frame 10, outside"):
        future_camera_pose(scene0.ego_poses, 8, 2, np.eye(4), scene="scene-0000")


def test_horizons_and_target_names(scene0):
    assert horizon_frames(1.0, 2.0) == 2 and horizon_frames(2.0, 2.0) == 4 and horizon_frames(1.0, 12.0) == 12
    defaults = enumerate_targets(
        scene0.ds, [scene0.id], ["CAM_FRONT"], [1.0, -1.0, 2.0, -2.0, 4.0, -4.0], [1.0, 2.0], []
    )
    names = list(dict.fromkeys(t.name for t in defaults))
    assert names == [
        "shift_1m",
        "shift_-1m",
        "shift_2m",
        "shift_-2m",
        "shift_4m",
        "shift_-4m",
        "future_1s",
        "future_2s",
    ]
    assert target_name(0.5) == "shift_0.5m" and target_name(longitudinal_m=2.0) == "shift_long_2m"
    assert target_name(1.0, 2.0) == "shift_1m_long_2m" and target_name(future_s=1.5) == "future_1.5s"
    with pytest.raises(ValueError, match="a spatial shift or a future horizon"):
        target_name(1.0, future_s=1.0)
    s2e, rate = scene0.cameras["CAM_FRONT"].sensor2ego_44, float(scene0.info["frame_rate_hz"])
    future = GenTarget(scene0.id, 3, "CAM_FRONT", "future", horizon_frames=horizon_frames(1.0, rate), horizon_s=1.0)
    np.testing.assert_array_equal(target_pose(scene0.ds, future), future_camera_pose(scene0.ego_poses, 3, 2, s2e))
    shift = GenTarget(scene0.id, 3, "CAM_FRONT", "shift", lateral_m=-2.0)
    np.testing.assert_array_equal(target_pose(scene0.ds, shift)[1, 3], -2.0)


def _median_rel(c, depth_gt) -> float:
    m = c.mask & (depth_gt > 0)
    return float(np.median(np.abs(c.depth[m] - depth_gt[m]) / depth_gt[m]))


def test_shifted_conditions_match_the_generator_rerendered_at_the_shifted_pose(synth_small, scene0):
    """CAM_FRONT_LEFT's stored depth, projected 2 m left, agrees with synthetic_mini's exact render there; the
    opposite shift does not (a sign error would swap the two)."""
    cam = scene0.cameras["CAM_FRONT_LEFT"]
    g = backprojected(scene0.frame(2), "CAM_FRONT_LEFT")
    pose = shifted_camera_pose(cam.sensor2ego_44, lateral_m=2.0)
    c = low_level_conditions(g, cam.K_33, pose, cam.width, cam.height, scene="scene-0000", frame=2)
    left, right_side = cam.sensor2ego_44.copy(), cam.sensor2ego_44.copy()
    left[1, 3] += 2.0  # ego +y is left
    right_side[1, 3] -= 2.0
    _, right = render_view(synth_small, "scene-0000", 2, "CAM_FRONT_LEFT", left)
    _, wrong = render_view(synth_small, "scene-0000", 2, "CAM_FRONT_LEFT", right_side)
    assert _median_rel(c, right) < 0.03 and _median_rel(c, wrong) > 0.1


def test_future_conditions_match_the_recorded_future_view(scene0):
    """Frame 2's CAM_FRONT evidence projected 1 s ahead agrees with the stored depth of frame 4 (static scene)."""
    cam = scene0.cameras["CAM_FRONT"]
    g = backprojected(scene0.frame(2), "CAM_FRONT")
    future = scene0.frame(4).depth("CAM_FRONT")
    E = scene0.ego_poses
    right = future_camera_pose(E, 2, 2, cam.sensor2ego_44)
    mirrored = np.linalg.inv(E[4]) @ E[2] @ cam.sensor2ego_44  # the composition the other way round
    errs = [
        _median_rel(low_level_conditions(g, cam.K_33, pose, cam.width, cam.height, scene="scene-0000", frame=2), future)
        for pose in (right, mirrored)
    ]
    assert errs[0] < 0.06 and errs[1] > 0.1
