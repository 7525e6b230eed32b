"""synthetic_mini: determinism, layout, sensors and boxes, checked against independent geometry."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from pipelines.data.layout import CAMERAS, WEATHERS, DataError, gaussians_relpath
from pipelines.data.reader import GSQADataset
from pipelines.data.synth.build import build
from pipelines.data.synth.config import SynthConfig, coerce_config

W, H = 64, 36  # synth_small's image size
NUSCENES_FX = {"CAM_FRONT": 1266.4, "CAM_BACK": 809.2}
YAWS_DEG = {
    "CAM_FRONT": 0,
    "CAM_FRONT_RIGHT": -55,
    "CAM_BACK_RIGHT": -110,
    "CAM_BACK": 180,
    "CAM_BACK_LEFT": 110,
    "CAM_FRONT_LEFT": 55,
}


def _hashes(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def ds(synth_small) -> GSQADataset:
    return GSQADataset(synth_small)


# ----------------------------------------------------------------------------- determinism


def test_same_seed_gives_byte_identical_files(synth_small, synth_small_cfg, tmp_path):
    # In-process this time (the fixture used worker processes): the bytes must not care.
    again = build(dataclasses.replace(synth_small_cfg, num_workers=1), tmp_path / "again")
    first, second = _hashes(synth_small), _hashes(again)
    # images, depth, lidar, tables, routes.json, dataset.json
    assert len(first) == 2 * 10 * 6 * (len(WEATHERS) + 1) + 2 * 10 + 7 + 1 + 1
    del first["dataset.json"], second["dataset.json"]  # it records each file's mtime: compared below without them
    assert first == second
    meta, meta_again = (json.loads((r / "dataset.json").read_text()) for r in (synth_small, again))
    for m in (meta, meta_again):
        for rec in m["files"].values():
            del rec["mtime_ns"]
    assert meta == meta_again and len(meta["fingerprint"]) == 64


def test_other_seed_gives_other_scenes(synth_small, synth_small_cfg, tmp_path):
    other = GSQADataset(build(dataclasses.replace(synth_small_cfg, seed=1), tmp_path / "seed1"))
    base = GSQADataset(synth_small)
    assert other.fingerprint != base.fingerprint
    assert other.meta["generator"]["config"]["seed"] == 1
    # Seed 1 starts the scenario cycle one step later, and the numbers differ too.
    assert other.meta["generator"]["scenarios"] == ["stop", "lane_change"]
    assert base.meta["generator"]["scenarios"] == ["curve", "stop"]
    poses0 = base.scene("scene-0001").ego_poses
    poses1 = other.scene("scene-0000").ego_poses  # both "stop" scenes
    assert np.abs(poses0 - poses1).max() > 0.1


# ----------------------------------------------------------------------------- layout


def test_counts_and_tables(ds, synth_small):
    assert ds.meta["source"] == "synthetic_mini"
    assert ds.meta["num_scenes"] == 2 and ds.meta["num_frames"] == 20
    assert ds.cameras == list(CAMERAS)
    assert ds.scene_ids == ["scene-0000", "scene-0001"]
    for sid in ds.scene_ids:
        scene = ds.scene(sid)
        assert scene.num_frames == 10
        assert scene.weathers == list(WEATHERS)
        assert scene.info["frame_rate_hz"] == pytest.approx(2.0)
        assert scene.info["description"].startswith(("curve:", "stop:"))
        assert sorted(scene.cameras) == sorted(CAMERAS)
        assert scene.ego_poses.shape == (10, 4, 4)
        for weather in WEATHERS:
            folder = "images" if weather == "clear" else f"images_{weather}"
            for cam in CAMERAS:
                assert len(list((synth_small / "scenes" / sid / folder / cam).glob("*.png"))) == 10
        for cam in CAMERAS:
            assert len(list((synth_small / "scenes" / sid / "depth" / cam).glob("*.png"))) == 10
        assert len(list((synth_small / "scenes" / sid / "lidar").glob("*.arrow"))) == 10
        assert not (synth_small / gaussians_relpath(sid, 0)).exists()  # reconstruction writes these later
    frames = ds.table("frames").to_pylist()
    assert len(frames) == 20 and len({f["token"] for f in frames}) == 20
    for sid in ds.scene_ids:
        ts = [f["timestamp_us"] for f in frames if f["scene_id"] == sid]
        assert np.diff(ts).tolist() == [500_000] * 9
    gen = ds.meta["generator"]
    assert gen["resolution"] == [W, H] and gen["val_scenes"] == ["scene-0001"] and gen["skipped_tasks"] == {}


def test_rig_intrinsics_and_extrinsics(ds):
    cams = ds.scene("scene-0000").cameras
    for name, cam in cams.items():
        assert (cam.width, cam.height) == (W, H)
        fx = NUSCENES_FX.get(name)
        if fx is not None:
            assert cam.K_33[0, 0] == pytest.approx(fx * W / 1600, rel=1e-6)
            assert cam.K_33[1, 1] == pytest.approx(fx * H / 900, rel=1e-6)
        assert cam.K_33[:2, 2].tolist() == [W / 2, H / 2]
        yaw = np.deg2rad(YAWS_DEG[name])
        r = cam.sensor2ego_44[:3, :3]
        np.testing.assert_allclose(r[:, 2], [np.cos(yaw), np.sin(yaw), 0.0], atol=1e-6)  # optical axis
        np.testing.assert_allclose(r[:, 1], [0.0, 0.0, -1.0], atol=1e-6)  # image down = ego down
        assert 1.45 <= cam.sensor2ego_44[2, 3] <= 1.6


def test_images_and_depth(ds):
    frame = ds.scene("scene-0000").frame(4)
    clear = frame.image("CAM_FRONT")
    assert clear.shape == (H, W, 3) and clear.dtype == np.uint8
    depth = frame.depth("CAM_FRONT")
    assert depth.shape == (H, W) and depth.dtype == np.float32
    assert (depth[-1] > 0).all() and depth[-1].max() < 8.0  # the road just ahead of the bumper
    assert 0 < depth.max() <= 150.0
    sky = depth == 0
    assert sky[0].any() and not sky[-1].any()
    # Sky is the same in every view: depth 0 where the clear image shows it, and it is bright there.
    assert clear[sky].mean() > clear[~sky].mean()
    night = frame.image("CAM_FRONT", "night")
    fog = frame.image("CAM_FRONT", "fog")
    rain = frame.image("CAM_FRONT", "rain")
    assert night.mean() < 0.5 * clear.mean()
    assert fog.astype(float).std() < clear.astype(float).std()
    assert np.abs(rain.astype(int) - clear.astype(int)).mean() > 5
    # Fog hides far things more than near ones: the far half converges to grey.
    far, near = depth > 30, (depth > 0) & (depth < 8)
    grey = np.abs(fog.astype(float) - fog[sky].mean(0)).sum(-1)
    assert grey[far].mean() < grey[near].mean()


def test_lidar_in_range_and_consistent_with_depth(ds):
    scene = ds.scene("scene-0001")
    cam = scene.cameras["CAM_FRONT"]
    mount = np.array(ds.meta["generator"]["lidar_mount"])
    world2cam = np.linalg.inv(cam.sensor2ego_44)
    for f in (0, 5, 9):
        pts = scene.frame(f).lidar()
        assert pts.shape[1] == 4 and 5_000 < len(pts) <= 32 * 360
        rng_m = np.linalg.norm(pts[:, :3] - mount, axis=1)
        assert rng_m.min() >= 1.0 - 1e-4 and rng_m.max() <= 70.0 + 1e-3
        assert pts[:, 2].min() > -1e-3  # nothing below the ground plane
        assert pts[:, 3].min() >= 0 and pts[:, 3].max() <= 255
        pc = pts[:, :3] @ world2cam[:3, :3].T + world2cam[:3, 3]
        z = pc[:, 2]
        keep = (z > 2) & (z < 40)
        uvw = pc[keep] @ cam.K_33.T
        u = np.floor(uvw[:, 0] / uvw[:, 2]).astype(int)
        v = np.floor(uvw[:, 1] / uvw[:, 2]).astype(int)
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        u, v, z = u[inside], v[inside], z[keep][inside]
        assert len(z) > 500
        depth = np.pad(scene.frame(f).depth("CAM_FRONT"), 1, mode="edge")
        nb = np.stack([depth[v + dy, u + dx] for dy in range(3) for dx in range(3)], 1)
        lo, hi = np.where(nb > 0, nb, np.inf).min(1), nb.max(1)
        tol = 0.05 + 0.02 * z
        # The camera and the LiDAR sit apart, so silhouettes differ by a pixel or two; the rest must agree.
        assert ((z >= lo - tol) & (z <= hi + tol)).mean() > 0.95


# ----------------------------------------------------------------------------- boxes


def _world_track(ds, sid):
    """instance -> {frame: (world centre xyz, world velocity xy, size, attribute)} from the tables alone."""
    scene = ds.scene(sid)
    out: dict[str, dict] = {}
    for f in range(scene.num_frames):
        e = scene.ego_poses[f]
        for b in scene.frame(f).boxes3d():
            c = e[:3, :3] @ np.asarray(b["center"]) + e[:3, 3]
            vel = e[:2, :2] @ np.asarray(b["velocity"])
            out.setdefault(b["instance_id"], {})[f] = (c, vel, tuple(b["size"]), b["attribute"], b["category"])
    return out


def test_boxes3d_follow_consistent_world_motion(ds):
    checked_parked = checked_moving = 0
    for sid in ds.scene_ids:
        for inst, track in _world_track(ds, sid).items():
            frames = sorted(track)
            assert len({track[f][2] for f in frames}) == 1, f"{inst}: size changes"
            assert len({track[f][4] for f in frames}) == 1, f"{inst}: category changes"
            assert track[frames[0]][2][2] == pytest.approx(2 * track[frames[0]][0][2], abs=1e-4)  # on the ground
            if track[frames[0]][3] == "vehicle.parked":
                centres = np.stack([track[f][0] for f in frames])
                assert np.abs(centres - centres[0]).max() < 1e-3, f"{inst}: parked but moving"
                checked_parked += 1
            for f in frames:
                if f - 1 in track and f + 1 in track:
                    # Central differences of the world track reproduce the stored velocity.
                    fd = (track[f + 1][0][:2] - track[f - 1][0][:2]) / (2 * 0.5)
                    assert np.linalg.norm(fd - track[f][1]) < 0.5, f"{inst} frame {f}: velocity {track[f][1]} vs {fd}"
                    checked_moving += 1
    assert checked_parked >= 2 and checked_moving >= 100


def _corners_ego(b) -> np.ndarray:
    lx, ly, lz = (np.asarray(b["size"]) / 2).tolist()
    c, s = np.cos(b["yaw"]), np.sin(b["yaw"])
    xs = np.array([sx * lx for sx in (-1, 1) for _ in range(4)])
    ys = np.array([sy * ly for _ in range(2) for sy in (-1, 1) for _ in range(2)])
    zs = np.array([sz * lz for _ in range(4) for sz in (-1, 1)])
    return np.stack([c * xs - s * ys, s * xs + c * ys, zs], 1) + np.asarray(b["center"])


def test_boxes2d_lie_inside_the_projected_3d_box(ds):
    checked = 0
    for sid in ds.scene_ids:
        scene = ds.scene(sid)
        for f in range(scene.num_frames):
            frame = scene.frame(f)
            b3 = {b["instance_id"]: b for b in frame.boxes3d()}
            for b in frame.boxes2d():
                assert b["instance_id"] in b3, f"{sid}/{f}: 2D box without a 3D box"
                assert 0 < b["visible_fraction"] <= 1
                x1, y1, x2, y2 = b["box"]
                assert 0 <= x1 < x2 <= W and 0 <= y1 < y2 <= H
                assert all(float(v).is_integer() for v in b["box"])
                assert (x2 - x1) * (y2 - y1) >= 12  # min_box_pixels visible pixels fit inside
                cam = scene.cameras[b["camera"]]
                t = np.linalg.inv(cam.sensor2ego_44)
                pc = _corners_ego(b3[b["instance_id"]]) @ t[:3, :3].T + t[:3, 3]
                if (pc[:, 2] < 0.5).any():
                    continue
                uv = pc @ cam.K_33.T
                u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
                assert x1 >= np.floor(u.min()) - 1 and x2 <= np.ceil(u.max()) + 1, f"{sid}/{f} {b}"
                assert y1 >= np.floor(v.min()) - 1 and y2 <= np.ceil(v.max()) + 1, f"{sid}/{f} {b}"
                checked += 1
    assert checked >= 50


# ----------------------------------------------------------------------------- config errors


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ({"num_scenes": 0}, "data.num_scenes must be >= 1, got 0"),
        ({"width": 0}, "data.width must be >= 16 pixels, got 0"),
        ({"frame_rate_hz": 0.0}, "data.frame_rate_hz must be > 0, got 0.0"),
        ({"val_fraction": 1.0}, "data.val_fraction must be in [0, 1), got 1.0"),
        ({"max_depth_m": 300.0}, "data.max_depth_m must be in (0, 255] (uint16 depth PNG range), got 300.0"),
        (
            {"weathers": ["clear", "snow"]},
            "data.weathers must be a subset of ['clear', 'rain', 'fog', 'night'], got ['clear', 'snow']",
        ),
        (
            {"weathers": ["rain"]},
            "data.weathers must be a list that includes 'clear' (the images/ folder), got ['rain']",
        ),
        (
            {"scenarios": ["drift"]},
            "data.scenarios must be a non-empty subset of "
            "['curve', 'stop', 'lane_change', 'start', 'follow', 'cruise'], got ['drift']",
        ),
    ],
)
def test_bad_config_names_the_key(override, message, tmp_path):
    with pytest.raises(DataError) as e:
        build(SynthConfig(**override), tmp_path / "ds")
    assert str(e.value) == message
    assert not (tmp_path / "ds").exists()


def test_source_must_be_none(tmp_path):
    with pytest.raises(DataError) as e:
        build(SynthConfig(), tmp_path / "ds", source="/data/nuscenes")
    assert str(e.value) == "synthetic_mini reads no input data: source must be None, got '/data/nuscenes'"


def test_hydra_node_is_accepted():
    node = OmegaConf.structured(SynthConfig(num_scenes=3, weathers=["clear", "fog"]))
    cfg = coerce_config(node)
    assert isinstance(cfg, SynthConfig)
    assert cfg.num_scenes == 3 and cfg.weathers == ["clear", "fog"] and type(cfg.weathers) is list
    assert cfg == SynthConfig(num_scenes=3, weathers=["clear", "fog"])


def test_short_clips_skip_trajectory_and_planning_qa(tmp_path):
    root = build(SynthConfig(num_scenes=1, num_frames=3, width=32, height=18, weathers=["clear"]), tmp_path / "ds")
    ds = GSQADataset(root)
    skipped = ds.meta["generator"]["skipped_tasks"]
    assert skipped == {
        "traj": "needs data.num_frames >= 10 (4 history + 6 future frames), got 3",
        "plan": "needs data.num_frames > 4 (plan_horizon_s x frame_rate_hz frames of future), got 3",
    }
    tasks = set(ds.qa().column("task").to_pylist())
    assert tasks <= {"rdp", "vg2d", "vg3d"} and "rdp" in tasks
    assert ds.scene("scene-0000").weathers == ["clear"]
    assert not (root / "scenes" / "scene-0000" / "images_rain").exists()
