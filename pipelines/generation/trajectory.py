"""Future targets on the ego trajectory the LLM predicts (Sec. Trajectory-oriented QA Dataset): the trajectory
question of frame ``f`` (its 4 history poses) is answered by the LoRA'd world model, the answer's pose list is
parsed, and the pose ``h`` frames ahead places the target camera. Ground truth stays what the camera recorded at
``f + h``, so the score measures prediction and generation together."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pipelines.data.layout import GAUSS_TOKEN, pose_matrix
from pipelines.data.reader import GSQADataset
from pipelines.generation.conditions import horizon_frames
from pipelines.generation.samples import GenTarget
from pipelines.understanding.data import FrameStore, QASample

_NUM = r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?"
_POSE = re.compile(rf"\[\s*({_NUM}(?:\s*,\s*{_NUM}){{6}})\s*\]")


def parse_trajectory(text: str) -> list[np.ndarray]:
    """The 4x4 poses of a "[PT, [x, y, z, qx, qy, qz, qw], ...]" answer, in order; [] when none parses."""
    out = []
    for m in _POSE.finditer(text):
        x, y, z, qx, qy, qz, qw = (float(v) for v in m.group(1).split(","))
        if qx == qy == qz == qw == 0:
            continue  # not a rotation
        out.append(pose_matrix((qw, qx, qy, qz), (x, y, z)))
    return out


def trajectory_questions(ds: GSQADataset, scenes: list[str], frames: int) -> dict[tuple[str, int], QASample]:
    """The trajectory QA per (scene, reference frame < ``frames``): the question the LLM answers. The future list
    of the answer starts at the reference frame (index k = frame f + k)."""
    out = {}
    for row in (r for r in ds.qa().to_pylist() if r["task"] == "traj"):
        gt = json.loads(row["gt"]) if row.get("gt") else {}
        f = int(gt.get("reference_frame", row["frame_idx"]))
        if row["scene_token"] in scenes and f < frames:
            human = next(c["value"] for c in row["conversations"] if c["from"] == "human")
            if GAUSS_TOKEN not in human:  # the world model reads the scene through its Gaussian tokens
                human = f"Based on {GAUSS_TOKEN}, {human[0].lower()}{human[1:]}"
            out[(row["scene_token"], f)] = QASample(row["sample_id"], row["scene_token"], f, "traj", human, "",
                                                    tuple(row["views"]), row["category"])  # fmt: skip
    return out


def predicted_future_targets(
    world,
    ds: GSQADataset,
    distill_dirs: Mapping[str, Path],
    scenes: list[str],
    cameras: list[str],
    horizons_s: list[float],
    frames: int,
    max_new_tokens: int = 160,
) -> tuple[list[GenTarget], int]:
    """Future targets whose ego pose the world model predicted; and how many answers had no pose at a horizon."""
    questions = trajectory_questions(ds, scenes, frames)
    if not questions or not horizons_s:
        return [], 0
    store = FrameStore(ds, distill_dirs, world.comp.world.weather, world.comp.world.trajectory_frames)
    keys = sorted(questions)
    answers = world.answer([questions[k] for k in keys], store, max_new_tokens)
    targets, missing = [], 0
    for (sid, f), text in zip(keys, answers, strict=True):
        poses = parse_trajectory(text)
        rate = float(ds.scene(sid).info["frame_rate_hz"])
        for s in horizons_s:
            h = horizon_frames(s, rate)
            if f + h >= ds.scene(sid).num_frames:
                continue
            if h >= len(poses):
                missing += 1
                continue
            ego = tuple(float(v) for v in poses[h].reshape(16))
            targets += [GenTarget(sid, f, cam, "future", horizon_frames=h, horizon_s=float(s), ego_pose=ego)
                        for cam in cameras]  # fmt: skip
    return targets, missing
