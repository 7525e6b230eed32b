"""A tiny published dataset (tables only) for the orchestration tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.data.layout import DatasetWriter, flat_pose


def make_dataset(root: Path, scenes: int = 3, params: dict | None = None) -> Path:
    """``params``: what dataset.json records as built from (a run must request the same ``data.<key>``)."""
    with DatasetWriter(root, name="toy", source="test", params=params) as w:
        for i in range(scenes):
            sid = f"scene-{i:04d}"
            w.add(
                "scenes",
                scene_id=sid,
                name=sid,
                num_frames=1,
                frame_rate_hz=2.0,
                description="",
                weathers=[],
                source="test",
            )
            w.add("frames", scene_id=sid, frame_idx=0, timestamp_us=0, token=sid)
            w.add("ego_poses", scene_id=sid, frame_idx=0, ego2world=flat_pose(np.eye(4)))
    return root
