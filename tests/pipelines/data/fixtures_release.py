"""A tiny GaussianDWM public release in the release's exact format, written from known random values.

As the release's ``examples/dummy_data``: no ``<gauss>`` in any record's text (its loader inserts the Gaussian item),
every record has ``major_task``, one QA record and one world record repeat unchanged in the ``_train`` and ``_val``
files, QA records name a row of a [N, 512] CLIP text shard, world records name pseudo RGB-D frames, ground truth and
rows of a latent pack ``[N, 2, 4, 56, 96]`` described by the ``meta.json`` beside it. Layout written::

    qa_train.jsonl  qa_val.jsonl            q1 q2 q3 q5 | q4 q5 (q5 in both)
    world_train.jsonl  world_val.jsonl      w1 w2 | w1 (w1 in both)
    gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00000.pth   scene 0 frame 0, flat, with _features_dc
    gauss/output-full-6v/0_CAM_BACK/langsplat_3/per_frame/00000.pth    scene 0 frame 0, nested
    gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00001.pth   scene 0 frame 1, nested
    gauss/scene_0002/frame_00000.pth                                   scene 2 frame 0, flat
    gauss/scene_0002/frame_00003.pth                                   scene 2 frame 3, no record lists it
    clip_text/features_000000.npy           [6, 512] float32
    images/world_ref.png                    w1's reference and input image, 48x32
    images/world_pseudo_00{0,1,2}.png       w1's pseudo RGB, 32x24;  depth/world_pseudo_00k.npz: depth_proj [24, 32]
    images/world_gt_00{0,1,2}.png           w1's ground truth, 32x24; depth/world_gt_00k.npz: depth [24, 32]
    images/w2_ref.png, images/w2_pseudo_00{0,1}.png, depth/w2_pseudo_00{0,1}.npz   w2: 40x20, no ground truth
    latents/world_pack.dat + meta.json      [5, 2, 4, 56, 96] float32; w1 rows [1, 2, 3], w2 rows [4, 0]
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

FRONT0 = "gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00000.pth"
BACK0 = "gauss/output-full-6v/0_CAM_BACK/langsplat_3/per_frame/00000.pth"
FRONT1 = "gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00001.pth"
S2F0 = "gauss/scene_0002/frame_00000.pth"
S2F3 = "gauss/scene_0002/frame_00003.pth"
CLIP_SHARD = "clip_text/features_000000.npy"
CLIP_ROWS = {"q1": 3, "q2": 0, "q3": 1, "q4": 5, "q5": 2}  # not in sample order: the mapping is what is tested
PACK = "latents/world_pack.dat"
PACK_SHAPE = (5, 2, 4, 56, 96)


class NotATensor:
    """A pickled object that weights_only loading must refuse."""


class RunsACommand:
    """Pickles as a call of ``os.system`` (GLOBAL posix.system); loading it must refuse, never run it."""

    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


@dataclass
class Release:
    root: Path
    tensors: dict[str, dict[str, torch.Tensor]]  # relpath -> raw release fields
    records: list[dict]  # QA records, in file order (q5 once)
    world: list[dict] = field(default_factory=list)  # world records (w1 once)
    images: dict[str, np.ndarray] = field(default_factory=dict)  # relpath -> [H, W, 3] uint8 RGB as written
    depths: dict[str, np.ndarray] = field(default_factory=dict)  # relpath -> [H, W] float32 as written
    pack: np.ndarray | None = None  # the latent pack as written
    clip: np.ndarray | None = None  # the CLIP shard as written


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


def record(
    uid: str, scene: int, frame: int, gauss: list[str], group: str, subtask: str, question: str, clip: bool = True
) -> dict:
    """A QA record as the release writes it (the question has no ``<gauss>``)."""
    out = {
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
    if clip and uid in CLIP_ROWS:
        out |= {"clip_text_embed_path": CLIP_SHARD, "clip_text_embed_row": CLIP_ROWS[uid]}
    return out


def world_record(
    uid: str,
    scene: int,
    frame: int,
    gauss: list[str],
    ref: str,
    pseudo: list[str],
    depth: list[str],
    indices: list[int],
    gt_rgb: list[str] | None = None,
    gt_depth: list[str] | None = None,
    fps: int = 5,
) -> dict:
    """A world record as the release writes it."""
    out = {
        "major_task": "world",
        "sample_uid": uid,
        "scene_idx": scene,
        "frame_idx": frame,
        "views": ["CAM_FRONT"],
        "image_paths": [ref],
        "gauss_paths": gauss,
        "conversations": [{"role": "user", "content": f"Generate the next {len(pseudo)} frames."}],
        "ref_image_path": ref,
        "pseudo_video_paths": pseudo,
        "pseudo_depth_paths": depth,
        "target_latent_pack_path": PACK,
        "target_latent_indices": indices,
        "fps": fps,
        "motion_bucket_id": 127,
    }
    if gt_rgb is not None:
        out |= {"gt_rgb_frame_paths": gt_rgb, "gt_depth_npz_paths": gt_depth}
    if uid == "w1":
        out |= {"pseudo_source_name": "dummy", "pseudo_source_kind": "contract"}
    return out


def write_jsonl(path: Path, records: list[dict]) -> None:
    path.write_text("".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records))


def write_png(path: Path, rgb_HW3: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb_HW3, cv2.COLOR_RGB2BGR))


def write_npz(path: Path, **arrays: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)


def write_pack(root: Path, rel: str, pack: np.ndarray, **meta) -> None:
    """A raw memmap and the meta.json beside it, as the release stores target latents."""
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    pack.tofile(path)
    info = {"dtype": str(pack.dtype), "shape": list(pack.shape), "streams": ["rgb", "depth"]}
    info |= {"cache_granularity": "scene_camera_pack", **meta}
    (path.parent / "meta.json").write_text(json.dumps(info, indent=2))


def _world_files(root: Path, rng: np.random.Generator, release: Release) -> None:
    def image(rel: str, w: int, h: int) -> str:
        release.images[rel] = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        write_png(root / rel, release.images[rel])
        return rel

    def depth(rel: str, key: str, w: int, h: int) -> str:
        release.depths[rel] = (rng.random((h, w)) * 80).astype(np.float32)
        write_npz(root / rel, **{key: release.depths[rel]})
        return rel

    ref = image("images/world_ref.png", 48, 32)
    w1 = world_record(
        "w1",
        0,
        0,
        [FRONT0, BACK0],
        ref,
        [image(f"images/world_pseudo_{k:03d}.png", 32, 24) for k in range(3)],
        [depth(f"depth/world_pseudo_{k:03d}.npz", "depth_proj", 32, 24) for k in range(3)],
        [1, 2, 3],
        gt_rgb=[image(f"images/world_gt_{k:03d}.png", 32, 24) for k in range(3)],
        gt_depth=[depth(f"depth/world_gt_{k:03d}.npz", "depth", 32, 24) for k in range(3)],
    )
    w2 = world_record(
        "w2",
        2,
        0,
        [S2F0],
        image("images/w2_ref.png", 40, 20),
        [image(f"images/w2_pseudo_{k:03d}.png", 40, 20) for k in range(2)],
        [depth(f"depth/w2_pseudo_{k:03d}.npz", "depth_proj", 40, 20) for k in range(2)],
        [4, 0],
        fps=10,
    )
    release.pack = rng.standard_normal(PACK_SHAPE).astype(np.float32)
    write_pack(root, PACK, release.pack)
    release.world = [w1, w2]
    write_jsonl(root / "world_train.jsonl", [w1, w2])
    write_jsonl(root / "world_val.jsonl", [w1])


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
    q5 = record("q5", 0, 1, [FRONT1], "NuInteract_Caption", "caption", "Describe the scene.")
    train = [
        record("q1", 0, 0, [FRONT0, BACK0], "NuInteract_RD&P", "prediction", "What happens next?"),
        record("q2", 0, 1, [FRONT1], "NuInteract_2DVG", "2D_perception_location", "Where is the car?"),
        record("q3", 0, 1, [FRONT1], "NuInteract_3DVG", "perception", "Locate the car in 3D."),
        q5,
    ]
    val = [record("q4", 2, 0, [S2F0], "NuInteract_Planning", "planning_turn_left", "Should we turn?"), q5]
    write_jsonl(root / "qa_train.jsonl", train)
    write_jsonl(root / "qa_val.jsonl", val)
    rng = np.random.default_rng(7)
    release = Release(root, tensors, train + val[:1])
    release.clip = rng.standard_normal((6, 512)).astype(np.float32)
    (root / CLIP_SHARD).parent.mkdir(parents=True)
    np.save(root / CLIP_SHARD, release.clip)
    _world_files(root, rng, release)
    return release
