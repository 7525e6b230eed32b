"""A tiny GaussianDWM public release written from known random tensors (format in pipelines.data.gaussiandwm).

Layout written::

    qa_train.jsonl  qa_val.jsonl
    gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00000.pth   scene 0 frame 0, flat, with _features_dc
    gauss/output-full-6v/0_CAM_BACK/langsplat_3/per_frame/00000.pth    scene 0 frame 0, nested
    gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00001.pth   scene 0 frame 1, nested
    gauss/scene_0002/frame_00000.pth                                   scene 2 frame 0, flat
    gauss/scene_0002/frame_00003.pth                                   scene 2 frame 3, no record lists it
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

FRONT0 = "gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00000.pth"
BACK0 = "gauss/output-full-6v/0_CAM_BACK/langsplat_3/per_frame/00000.pth"
FRONT1 = "gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00001.pth"
S2F0 = "gauss/scene_0002/frame_00000.pth"
S2F3 = "gauss/scene_0002/frame_00003.pth"


class NotATensor:
    """A pickled object that weights_only loading must refuse."""


@dataclass
class Release:
    root: Path
    tensors: dict[str, dict[str, torch.Tensor]]  # relpath -> raw release fields
    records: list[dict]


def gaussian_fields(n: int, seed: int, with_dc: bool = False) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    out = {
        "_xyz": torch.randn(n, 3, generator=g) * 10,
        "_scaling": torch.randn(n, 3, generator=g) - 2,
        "_rotation": torch.randn(n, 4, generator=g) * 3,  # unnormalised, as 3DGS stores it
        "_opacity": torch.randn(n, 1, generator=g) * 2,
        "_language_feature": torch.rand(n, 3, generator=g),
    }
    if with_dc:
        out["_features_dc"] = torch.randn(n, 1, 3, generator=g)
    return out


def write_pth(path: Path, fields: dict, nested: bool = False) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"gaussians_state": fields, "iteration": 30000} if nested else fields, path)


def record(uid: str, scene: int, frame: int, gauss: list[str], group: str, subtask: str, question: str) -> dict:
    return {
        "major_task": "qa",
        "sample_uid": uid,
        "scene_idx": scene,
        "frame_idx": frame,
        "views": ["CAM_FRONT"],
        "image_paths": [f"images/{uid}.png"],
        "gauss_paths": gauss,
        "conversations": [
            {"role": "user", "content": question},
            {"role": "assistant", "content": f"answer of {uid}"},
        ],
        "qa_group": group,
        "qa_subtask": subtask,
    }


def write_jsonl(path: Path, records: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def write_release(root: Path) -> Release:
    specs = {
        FRONT0: (7, 1, False, True),  # n, seed, nested, with_dc
        BACK0: (5, 2, True, False),
        FRONT1: (6, 3, True, False),
        S2F0: (4, 4, False, False),
        S2F3: (3, 5, True, True),
    }
    tensors = {}
    for rel, (n, seed, nested, with_dc) in specs.items():
        tensors[rel] = gaussian_fields(n, seed, with_dc)
        write_pth(root / rel, tensors[rel], nested)
    train = [
        record("q1", 0, 0, [FRONT0, BACK0], "NuInteract_RD&P", "prediction", "<gauss> What happens next?"),
        record("q2", 0, 1, [FRONT1], "NuInteract_2DVG", "2D_perception_location", "Based on <gauss>, where is it?"),
        record("q3", 0, 1, [FRONT1], "NuInteract_3DVG", "perception", "<gauss> Locate the car in 3D."),
    ]
    val = [record("q4", 2, 0, [S2F0], "NuInteract_Planning", "planning_turn_left", "<gauss> Should we turn?")]
    write_jsonl(root / "qa_train.jsonl", train)
    write_jsonl(root / "qa_val.jsonl", val)
    return Release(root, tensors, train + val)
