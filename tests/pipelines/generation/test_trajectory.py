"""Future targets on the LLM-predicted trajectory: answers parsed into poses, questions found per frame."""

from __future__ import annotations

import numpy as np

from pipelines.data.layout import GAUSS_TOKEN, pose_matrix
from pipelines.data.reader import GSQADataset
from pipelines.data.synth.planning import format_poses, pose_vector
from pipelines.generation.samples import GenTarget, target_pose
from pipelines.generation.trajectory import parse_trajectory, trajectory_questions


def test_parse_trajectory_inverts_the_answer_format():
    a = pose_matrix((np.cos(0.2), 0, 0, np.sin(0.2)), (3.5, -0.25, 0.0))  # 0.4 rad yaw
    b = pose_matrix((1, 0, 0, 0), (7.0, 0.5, 0.1))
    text = "Sure. " + format_poses([pose_vector(a), pose_vector(b)])
    got = parse_trajectory(text)
    assert len(got) == 2
    np.testing.assert_allclose(got[0], a, atol=0.01)  # the answer keeps 2 decimals
    np.testing.assert_allclose(got[1], b, atol=0.01)
    assert parse_trajectory("[PT, [1, 2, 3]]") == []  # malformed: no pose
    assert parse_trajectory("[PT, [1, 2, 3, 0, 0, 0, 0]]") == []  # not a rotation


def test_trajectory_questions_and_predicted_target_pose(synth_small):
    ds = GSQADataset(synth_small)
    qs = trajectory_questions(ds, ["scene-0000"], frames=10)
    n = ds.scene("scene-0000").num_frames  # windows of 4 history + 6 future frames: reference frames 4 .. n - 6
    assert sorted(f for _, f in qs) == list(range(4, n - 5)) and n - 5 > 4
    q = next(iter(qs.values()))
    assert q.instruction.startswith(f"Based on {GAUSS_TOKEN}, there are last 4 frames")
    ego = np.eye(4)
    ego[0, 3] = 5.0  # predicted: 5 m ahead
    t = GenTarget("scene-0000", 4, "CAM_FRONT", "future", horizon_frames=2, horizon_s=1.0,
                  ego_pose=tuple(ego.reshape(16)))  # fmt: skip
    assert t.name == "future_pred_1s"
    base = ds.scene("scene-0000").cameras["CAM_FRONT"].sensor2ego_44
    np.testing.assert_allclose(target_pose(ds, t), ego @ base)
