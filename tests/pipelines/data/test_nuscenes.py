"""nuScenes v1.0 tables -> our layout: round trip against hand-computed transforms, and exact errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipelines.data.layout import CAMERAS, DataError
from pipelines.data.nuscenes import NuScenesConfig, build
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_nuscenes import (
    CAM_BASE,
    CAMS,
    CX,
    CY,
    FX,
    FY,
    LIDAR_T,
    LIDAR_YAW,
    RAW_H,
    RAW_W,
    VERSION,
    cam_rotation,
    rz,
    write_nuscenes,
)

OUT_W, OUT_H = 32, 18  # half the fixture's 64x36 images


@pytest.fixture(scope="module")
def fixture(tmp_path_factory):
    return write_nuscenes(tmp_path_factory.mktemp("nuscenes"))


@pytest.fixture(scope="module")
def ds(fixture, tmp_path_factory) -> GSQADataset:
    root = tmp_path_factory.mktemp("converted") / "nuscenes"
    return GSQADataset(build(NuScenesConfig(width=OUT_W, height=OUT_H), root, str(fixture.root)))


def assert_nothing_published(root: Path) -> None:
    assert not root.exists()
    assert [p.name for p in root.parent.iterdir() if p.name.startswith(f".{root.name}")] == []


def test_scenes_frames_and_timestamps(ds, fixture):
    assert ds.scene_ids == ["scene-0001", "scene-0002"]
    for sid, frames in fixture.scenes.items():
        scene = ds.scene(sid)
        assert scene.num_frames == 3
        assert scene.info["frame_rate_hz"] == pytest.approx(2.0)
        assert scene.info["description"] == f"{sid}, rain"
        rows = ds._rows("frames", sid).sort_by("frame_idx").to_pylist()
        assert [r["timestamp_us"] for r in rows] == [f.timestamp_us for f in frames]
        assert [r["token"] for r in rows] == [f.token for f in frames]
    assert ds.meta["scene_splits"] == {"scene-0001": "train", "scene-0002": "val"}
    assert ds.table("qa").num_rows == 0 and ds.meta["qa"] == "none: raw nuScenes has no QA"


def test_cameras_intrinsics_scaled_and_extrinsics(ds):
    cams = ds.scene("scene-0001").cameras
    assert list(cams) == list(CAMERAS)
    sx, sy = OUT_W / RAW_W, OUT_H / RAW_H
    for name, cam in cams.items():
        assert (cam.width, cam.height) == (OUT_W, OUT_H)
        # Pixel centres as cv2.resize maps them: u' = (u + 0.5) * s - 0.5.
        want_K = [[FX * sx, 0, (CX + 0.5) * sx - 0.5], [0, FY * sy, (CY + 0.5) * sy - 0.5], [0, 0, 1]]
        np.testing.assert_allclose(cam.K_33, want_K, rtol=1e-6)
        np.testing.assert_allclose(cam.sensor2ego_44[:3, :3], cam_rotation(name), atol=1e-6)
        np.testing.assert_allclose(cam.sensor2ego_44[:3, 3], CAMS[name][1], atol=1e-6)
    # CAM_FRONT looks along ego x: its optical axis (camera z) is ego x.
    np.testing.assert_allclose(cams["CAM_FRONT"].sensor2ego_44[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(CAM_BASE @ [1, 0, 0], [0, -1, 0])


def test_ego_poses_are_the_lidar_keyframe_poses(ds, fixture):
    for sid, frames in fixture.scenes.items():
        poses = ds.scene(sid).ego_poses
        assert poses.shape == (3, 4, 4)
        for pose, f in zip(poses, frames, strict=True):
            want = np.eye(4)
            want[:3, :3], want[:3, 3] = rz(f.ego_yaw), f.ego_t
            np.testing.assert_allclose(pose, want, atol=1e-5)


def test_boxes3d_in_the_current_ego_frame(ds, fixture):
    frames = fixture.scenes["scene-0001"]
    for idx, f in enumerate(frames):
        boxes = {b["instance_id"]: b for b in ds.scene("scene-0001").frame(idx).boxes3d()}
        assert sorted(boxes) == (["scene-0001-car", "scene-0001-ped"] if idx < 2 else ["scene-0001-car"])
        car = boxes["scene-0001-car"]
        # Hand inverse of ego->world: R^T (c - t).
        centre = rz(f.ego_yaw).T @ (f.boxes["scene-0001-car"]["center"] - f.ego_t)
        np.testing.assert_allclose(car["center"], centre, atol=1e-4)
        np.testing.assert_allclose(car["center"], [10.0, 1.0, 0.8], atol=1e-4)
        np.testing.assert_allclose(car["size"], [4.5, 1.8, 1.6], atol=1e-6)  # (l, w, h) from nuScenes (w, l, h)
        assert car["yaw"] == pytest.approx(0.2, abs=1e-5)
        assert (car["category"], car["attribute"]) == ("vehicle.car", "vehicle.moving")
    ped = {b["instance_id"]: b for b in ds.scene("scene-0001").frame(0).boxes3d()}["scene-0001-ped"]
    assert (ped["category"], ped["attribute"]) == ("human.pedestrian.adult", "")


def test_velocity_from_neighbouring_annotations(ds, fixture):
    frames = fixture.scenes["scene-0001"]
    mid = {b["instance_id"]: b for b in ds.scene("scene-0001").frame(1).boxes3d()}
    c0, c2 = (frames[k].boxes["scene-0001-car"]["center"] for k in (0, 2))
    v_world = (c2 - c0) / 1.0  # central difference over two 0.5 s steps
    np.testing.assert_allclose(mid["scene-0001-car"]["velocity"], (rz(frames[1].ego_yaw).T @ v_world)[:2], atol=1e-4)
    # The pedestrian has two annotations: at frame 1 only the backward difference exists.
    p0, p1 = (frames[k].boxes["scene-0001-ped"]["center"] for k in (0, 1))
    v_ped = rz(frames[1].ego_yaw).T @ ((p1 - p0) / 0.5)
    np.testing.assert_allclose(mid["scene-0001-ped"]["velocity"], v_ped[:2], atol=1e-4)


def test_lidar_points_moved_into_ego(ds, fixture):
    f = fixture.scenes["scene-0002"][2]
    got = ds.scene("scene-0002").frame(2).lidar()
    want_xyz = f.lidar_points[:, :3].astype(np.float64) @ rz(LIDAR_YAW).T + LIDAR_T
    assert got.shape == (20, 4)
    np.testing.assert_allclose(got[:, :3], want_xyz, atol=1e-4)
    np.testing.assert_array_equal(got[:, 3], f.lidar_points[:, 3])


def test_images_resized(ds):
    img = ds.scene("scene-0001").frame(1).image("CAM_BACK")
    assert img.shape == (OUT_H, OUT_W, 3)
    # Fixture colour of camera index 3 at frame 1 is BGR (120, 120, 200) -> RGB (200, 120, 120).
    np.testing.assert_allclose(img.reshape(-1, 3).mean(axis=0), [200, 120, 120], atol=3)


def _project(center_world, f, cam) -> np.ndarray:
    """Pixel of a world point in the stored image, using the camera's own (camera-time) ego pose."""
    p_ego = rz(f.ego_yaw).T @ (center_world - f.cam_ego_t)
    p_cam = cam_rotation(cam).T @ (p_ego - np.asarray(CAMS[cam][1]))
    sx, sy = OUT_W / RAW_W, OUT_H / RAW_H
    fx, fy, cx, cy = FX * sx, FY * sy, (CX + 0.5) * sx - 0.5, (CY + 0.5) * sy - 0.5
    return np.array([fx * p_cam[0] / p_cam[2] + cx, fy * p_cam[1] / p_cam[2] + cy])


def _corners_world(box) -> np.ndarray:
    w, length, h = box["wlh"]
    local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * [length / 2, w / 2, h / 2]
    return local @ rz(box["yaw"]).T + box["center"]


def test_boxes2d_is_the_hull_of_projected_corners(ds, fixture):
    """The car lies wholly inside CAM_FRONT: its 2D box is the bounds of its 8 projected corners,
    projected with the camera-time ego pose (the lidar-time pose would shift it by ~0.7 px)."""
    for idx, f in enumerate(fixture.scenes["scene-0001"]):
        (row,) = ds.scene("scene-0001").frame(idx).boxes2d("CAM_FRONT")
        uv = np.array([_project(c, f, "CAM_FRONT") for c in _corners_world(f.boxes["scene-0001-car"])])
        np.testing.assert_allclose(row["box"], [*uv.min(axis=0), *uv.max(axis=0)], atol=1e-3)
        assert row["visible_fraction"] == pytest.approx(1.0)


def test_boxes2d_contain_projected_centre(ds, fixture):
    for idx, f in enumerate(fixture.scenes["scene-0001"]):
        rows = ds.scene("scene-0001").frame(idx).boxes2d("CAM_FRONT")
        assert [r["instance_id"] for r in rows] == ["scene-0001-car"]  # the pedestrian is behind
        x1, y1, x2, y2 = rows[0]["box"]
        u, v = _project(f.boxes["scene-0001-car"]["center"], f, "CAM_FRONT")
        assert x1 < u < x2 and y1 < v < y2
        assert 0 <= x1 < x2 <= OUT_W and 0 <= y1 < y2 <= OUT_H
        assert 0 < rows[0]["visible_fraction"] <= 1
    back = ds.scene("scene-0001").frame(0).boxes2d("CAM_BACK")
    assert [r["instance_id"] for r in back] == ["scene-0001-ped"]
    u, v = _project(
        fixture.scenes["scene-0001"][0].boxes["scene-0001-ped"]["center"], fixture.scenes["scene-0001"][0], "CAM_BACK"
    )
    x1, y1, x2, y2 = back[0]["box"]
    assert x1 < u < x2 and y1 < v < y2


def test_scene_selection_and_no_lidar(fixture, tmp_path):
    cfg = NuScenesConfig(width=OUT_W, height=OUT_H, scenes=["scene-0002"], cameras=["CAM_FRONT"], lidar=False)
    ds = GSQADataset(build(cfg, tmp_path / "one", str(fixture.root)))
    assert ds.scene_ids == ["scene-0002"] and ds.cameras == ["CAM_FRONT"]
    assert not (tmp_path / "one" / "scenes" / "scene-0002" / "lidar").exists()
    ds = GSQADataset(
        build(NuScenesConfig(width=OUT_W, height=OUT_H, max_scenes=1), tmp_path / "first", str(fixture.root))
    )
    assert ds.scene_ids == ["scene-0001"]
    with pytest.raises(DataError, match=r"^scenes=: unknown scene\(s\) \['scene-9999'\] in v1.0-mini"):
        build(NuScenesConfig(scenes=["scene-9999"]), tmp_path / "bad", str(fixture.root))


def test_unknown_camera_lists_valid_ones(fixture, tmp_path):
    with pytest.raises(DataError) as e:
        build(NuScenesConfig(cameras=["CAM_FRONT", "CAM_TOP"]), tmp_path / "out", str(fixture.root))
    assert str(e.value) == (
        "cameras=: unknown camera 'CAM_TOP' (valid: CAM_FRONT, CAM_FRONT_RIGHT, CAM_BACK_RIGHT, CAM_BACK, "
        "CAM_BACK_LEFT, CAM_FRONT_LEFT)"
    )


@pytest.fixture
def fresh(tmp_path):
    return write_nuscenes(tmp_path / "src")


def test_missing_image_names_scene_frame_camera(fresh, tmp_path):
    path = fresh.image_path("scene-0002", 1, "CAM_FRONT_LEFT")
    path.unlink()
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(NuScenesConfig(width=OUT_W, height=OUT_H), root, str(fresh.root))
    assert str(e.value) == f"scene-0002/frame_001 CAM_FRONT_LEFT: missing image {path}"
    assert_nothing_published(root)


def test_truncated_jpeg_is_refused(fresh, tmp_path):
    path = fresh.image_path("scene-0001", 2, "CAM_BACK")
    path.write_bytes(path.read_bytes()[:-40])
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(NuScenesConfig(width=OUT_W, height=OUT_H), root, str(fresh.root))
    assert str(e.value) == f"scene-0001/frame_002 CAM_BACK: image unreadable {path} (truncated JPEG)"
    assert_nothing_published(root)


def test_missing_table_is_named(fresh, tmp_path):
    path = fresh.table_path("instance")
    path.unlink()
    with pytest.raises(DataError) as e:
        build(NuScenesConfig(), tmp_path / "out", str(fresh.root))
    assert str(e.value) == f"{path}: missing nuScenes table 'instance.json'"


def test_missing_lidar_and_source(fresh, tmp_path):
    lidar = fresh.root / "samples" / "LIDAR_TOP" / "scene-0001_0.pcd.bin"
    lidar.unlink()
    with pytest.raises(DataError) as e:
        build(NuScenesConfig(), tmp_path / "out", str(fresh.root))
    assert str(e.value) == f"scene-0001/frame_000 LIDAR_TOP: missing LiDAR file {lidar}"
    with pytest.raises(DataError, match=rf"^source= is required: the nuScenes root holding {VERSION}/"):
        build(NuScenesConfig(), tmp_path / "out", None)
