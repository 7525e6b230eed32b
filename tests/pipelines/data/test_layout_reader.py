"""DatasetWriter publishes atomically; GSQADataset reads back and names what is wrong."""

import json
import os

import numpy as np
import pytest

from pipelines.data.layout import (
    DataError,
    DatasetWriter,
    check_gaussians,
    decode_depth,
    depth_relpath,
    encode_depth,
    flat_pose,
    gaussians_relpath,
    image_relpath,
    lidar_relpath,
    matrix_to_quat_wxyz,
    pose_matrix,
)
from pipelines.data.reader import GSQADataset


def _gaussians(n=50, d=4, seed=0):
    rng = np.random.default_rng(seed)
    rot = rng.normal(size=(n, 4)).astype(np.float32)
    return {
        "xyz": rng.normal(size=(n, 3)).astype(np.float32),
        "scale": rng.uniform(0.1, 1, size=(n, 3)).astype(np.float32),
        "rotation": rot,
        "opacity": rng.uniform(size=n).astype(np.float32),
        "color": rng.uniform(size=(n, 3)).astype(np.float32),
        "feature": rng.normal(size=(n, d)).astype(np.float32),
    }


def _write_tiny(root, fail_after_files=False):
    with DatasetWriter(root, name="tiny", source="test") as w:
        w.add(
            "scenes",
            scene_id="s0",
            name="s0",
            num_frames=1,
            frame_rate_hz=2.0,
            description="",
            weathers=["clear"],
            source="test",
        )
        w.add("frames", scene_id="s0", frame_idx=0, timestamp_us=0, token="t0")
        w.add(
            "cameras",
            scene_id="s0",
            camera="CAM_FRONT",
            width=8,
            height=4,
            fx=4.0,
            fy=4.0,
            cx=4.0,
            cy=2.0,
            sensor2ego=flat_pose(np.eye(4)),
        )
        w.add("ego_poses", scene_id="s0", frame_idx=0, ego2world=flat_pose(pose_matrix([1, 0, 0, 0], [1, 2, 3])))
        img = np.zeros((4, 8, 3), np.uint8)
        img[:, :, 0] = 200
        w.write_image(image_relpath("s0", "CAM_FRONT", 0), img)
        w.write_depth(depth_relpath("s0", "CAM_FRONT", 0), np.full((4, 8), 12.5, np.float32))
        w.write_lidar(lidar_relpath("s0", 0), np.arange(12, dtype=np.float32).reshape(3, 4))
        w.write_gaussians(gaussians_relpath("s0", 0), _gaussians())
        if fail_after_files:
            raise RuntimeError("boom")
    return GSQADataset(root)


def test_round_trip(tmp_path):
    ds = _write_tiny(tmp_path / "ds")
    frame = ds.scene("s0").frame(0)
    assert frame.image("CAM_FRONT").shape == (4, 8, 3)
    assert frame.image("CAM_FRONT")[0, 0].tolist() == [200, 0, 0]
    np.testing.assert_allclose(frame.depth("CAM_FRONT"), 12.5)
    np.testing.assert_array_equal(frame.lidar(), np.arange(12, dtype=np.float32).reshape(3, 4))
    g, ref = frame.gaussians(), _gaussians()
    np.testing.assert_array_equal(g["xyz"], ref["xyz"])
    np.testing.assert_allclose(np.linalg.norm(g["rotation"], axis=1), 1.0, atol=1e-6)
    assert g["feature"].shape == (50, 4)
    np.testing.assert_allclose(frame.ego2world[:3, 3], [1, 2, 3])
    meta = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert meta["num_scenes"] == 1 and meta["num_frames"] == 1 and meta["cameras"] == ["CAM_FRONT"]
    assert len(meta["fingerprint"]) == 64


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        _write_tiny(tmp_path / "ds", fail_after_files=True)
    assert os.listdir(tmp_path) == []


def test_failed_overwrite_keeps_the_old_dataset(tmp_path):
    ds = _write_tiny(tmp_path / "ds")
    fp = ds.fingerprint
    with pytest.raises(RuntimeError), DatasetWriter(tmp_path / "ds", name="x", source="t", overwrite=True) as w:
        w.write_image("scenes/a.png", np.zeros((2, 2, 3), np.uint8))
        raise RuntimeError("interrupted")
    assert GSQADataset(tmp_path / "ds").fingerprint == fp
    assert os.listdir(tmp_path) == ["ds"]


def test_existing_dataset_is_not_replaced_without_overwrite(tmp_path):
    _write_tiny(tmp_path / "ds")
    with pytest.raises(DataError, match=r"ds: a dataset already exists \(pass overwrite to replace it\)"):
        _write_tiny(tmp_path / "ds")


def test_unpublished_root_is_refused(tmp_path):
    (tmp_path / "half").mkdir()
    with pytest.raises(DataError, match=r"half: not a gdwm dataset \(dataset.json missing"):
        GSQADataset(tmp_path / "half")


def test_errors_name_scene_frame_camera(tmp_path):
    ds = _write_tiny(tmp_path / "ds")
    frame = ds.scene("s0").frame(0)
    with pytest.raises(DataError, match=r"s0/frame_000: unknown camera 'CAM_SIDE' \(cameras: \['CAM_FRONT'\]\)"):
        frame.image("CAM_SIDE")
    with pytest.raises(DataError, match=r"unknown scene 's9'"):
        ds.scene("s9")
    with pytest.raises(DataError, match=r"s0: frame 3 out of range \(scene has 1 frames\)"):
        ds.scene("s0").frame(3)
    with pytest.raises(DataError, match=r"s0/frame_000 CAM_FRONT: scene has no 'fog' variant"):
        frame.image("CAM_FRONT", weather="fog")
    img = tmp_path / "ds" / image_relpath("s0", "CAM_FRONT", 0)
    img.write_bytes(img.read_bytes()[:-20])
    with pytest.raises(DataError, match=r"s0/frame_000 CAM_FRONT: image unreadable .*00000.png \(truncated"):
        frame.image("CAM_FRONT")
    img.unlink()
    with pytest.raises(DataError, match=r"s0/frame_000 CAM_FRONT: missing image .*00000.png"):
        frame.image("CAM_FRONT")


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (
            "xyz",
            np.full((50, 3), np.nan, np.float32),
            "f.arrow: Gaussian field 'xyz' has NaN/Inf (150 values, first at row 0)",
        ),
        (
            "rotation",
            np.ones((50, 3), np.float32),
            "f.arrow: Gaussian field 'rotation' has shape [50, 3], expected [50, 4]",
        ),
        ("rotation", np.zeros((50, 4), np.float32), "f.arrow: Gaussian field 'rotation' has a zero quaternion"),
        ("scale", np.zeros((50, 3), np.float32), "f.arrow: Gaussian field 'scale' has non-positive values"),
        ("opacity", np.full(50, 3.0, np.float32), "f.arrow: Gaussian field 'opacity' is outside [0, 1]"),
    ],
)
def test_bad_gaussians_are_named(field, value, message):
    g = _gaussians()
    g[field] = value
    with pytest.raises(DataError) as e:
        check_gaussians(g, "f.arrow")
    assert str(e.value).startswith(message)


def test_depth_codec_and_quaternions():
    d = np.array([[0.0, 1.0, 12.34, 80.0]], np.float32)
    np.testing.assert_allclose(decode_depth(encode_depth(d)), d, atol=1 / 512)
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(matrix_to_quat_wxyz(pose_matrix(q, [0, 0, 0])), q, atol=1e-12)
    yaw = np.pi / 3
    m = pose_matrix([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], [0, 0, 0])
    np.testing.assert_allclose(m[:2, :2], [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]], atol=1e-12)
