"""Novel-view ground truth of synthetic_mini: a re-render at the recorded pose is the stored view, bit for bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipelines.data.layout import DataError
from pipelines.data.reader import GSQADataset
from pipelines.data.synth.novel_view import render_view


@pytest.mark.parametrize("weather", ["clear", "night"])
def test_rerender_at_the_recorded_pose_equals_the_stored_view(synth_small, weather):
    frame = GSQADataset(synth_small).scene("scene-0001").frame(4)
    rgb, depth = render_view(synth_small, "scene-0001", 4, "CAM_FRONT_LEFT", weather=weather)
    assert rgb.dtype == np.uint8 and np.array_equal(rgb, frame.image("CAM_FRONT_LEFT", weather))
    np.testing.assert_allclose(depth, frame.depth("CAM_FRONT_LEFT"), atol=2e-3)  # depth PNG quantisation


def test_a_shifted_camera_sees_the_road_shift(synth_small):
    scene = GSQADataset(synth_small).scene("scene-0000")
    pose = scene.cameras["CAM_FRONT"].sensor2ego_44.copy()
    pose[2, 3] += 1.0  # 1 m higher: the road below the horizon is farther in every ground pixel
    _, d0 = render_view(synth_small, "scene-0000", 2, "CAM_FRONT")
    _, d1 = render_view(synth_small, "scene-0000", 2, "CAM_FRONT", pose)
    bottom = slice(d0.shape[0] - 3, None)
    assert (d1[bottom] > d0[bottom]).mean() > 0.9


def test_errors_name_the_view_and_value(synth_small, tmp_path):
    with pytest.raises(DataError, match=r"scene-0000/frame_002 CAM_X: unknown camera"):
        render_view(synth_small, "scene-0000", 2, "CAM_X")
    with pytest.raises(DataError, match=r"scene-0000/frame_002 CAM_FRONT: unknown weather 'snow'"):
        render_view(synth_small, "scene-0000", 2, "CAM_FRONT", weather="snow")
    with pytest.raises(DataError, match=r"scene-0009/frame_002 CAM_FRONT: out of range \(2 scenes x 10 frames\)"):
        render_view(synth_small, "scene-0009", 2, "CAM_FRONT")
    (tmp_path / "dataset.json").write_text(json.dumps({"source": "nuscenes"}))
    with pytest.raises(DataError, match="exists only for synthetic_mini datasets"):
        render_view(tmp_path, "scene-0000", 0, "CAM_FRONT")
