"""The camera-target examples of the ``diffusion`` and ``evaluate_gen`` stages, assembled from a dataset with cameras:
the scenes of each split, the examples of a list of targets, their high-level conditions C_L (padded into a batch),
the views the tiny VAE is fitted to, and the sample grids the evaluation writes.

Legend: ``B`` examples, ``L`` condition tokens, ``H x W`` the model's image size.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from model_zoo.diffusion.vpred import depth_to_rgb
from pipelines.data.reader import GSQADataset
from pipelines.generation.conditions import NoGaussiansInView
from pipelines.generation.config import DiffusionStageConfig
from pipelines.generation.samples import GenExample, GenTarget, build_example, frame_gaussians
from pipelines.understanding.data import FrameStore, QASample


def split_scenes(ds: GSQADataset, available: set[str]) -> dict[str, list[str]]:
    """Scenes per QA split (the dataset's train/val assignment), restricted to those with reconstructions."""
    qa = ds.qa()
    out: dict[str, list[str]] = {"train": [], "val": []}
    for scene, split in sorted(set(zip(qa["scene_token"].to_pylist(), qa["split"].to_pylist(), strict=True))):
        if scene in available and split in out:
            out[split].append(scene)
    return out


def training_weathers(cfg: DiffusionStageConfig) -> list[str]:
    """The weather targets trained on: ``cfg.weathers``, or none with ``cfg.weather_targets`` off."""
    return list(cfg.weathers) if cfg.weather_targets else []


def camera_views(
    ds: GSQADataset, scenes: Sequence[str], hw: Sequence[int], max_depth: float, views_per_scene: int, seed: int
) -> torch.Tensor:
    """``[N, 3, H, W]`` in [0, 1] to fit the tiny VAE on: up to ``views_per_scene`` random (frame, camera) views of
    each scene (drawn with ``seed``), RGB and depth as pseudo-RGB (``(depth_to_rgb + 1) / 2``)."""
    rng = np.random.default_rng(seed)
    images = []
    for sid in scenes:
        scene = ds.scene(sid)
        views = [(f, cam) for f in range(scene.num_frames) for cam in scene.cameras]
        for i in rng.permutation(len(views))[:views_per_scene]:
            f, cam = views[i]
            frame = scene.frame(f)
            rgb = cv2.resize(frame.image(cam), (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
            depth = cv2.resize(frame.depth(cam), (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
            images.append(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0)
            images.append((depth_to_rgb(torch.from_numpy(depth)[None], max_depth)[0] + 1) / 2)
    return torch.stack(images)


def build_examples(
    ds: GSQADataset, targets: list[GenTarget], rec_dirs: dict[str, Path], hw: Sequence[int]
) -> tuple[list[GenExample], int]:
    """The examples of ``targets`` and how many were skipped (frame excluded by reconstruction QC, or no Gaussian in
    the target view); each frame's Gaussians are read once."""
    out, skipped, cache = [], 0, {}
    for t in targets:
        key = (t.scene, t.frame)
        if key not in cache:
            path = rec_dirs[t.scene] / "gaussians" / f"{t.frame:05d}.arrow"
            cache[key] = frame_gaussians(rec_dirs[t.scene], t.scene, t.frame) if path.is_file() else None
        if cache[key] is None:  # frame excluded by reconstruction QC
            skipped += 1
            continue
        try:
            out.append(build_example(ds, t, cache[key], hw))
        except NoGaussiansInView:  # nothing to condition on
            skipped += 1
    return out, skipped


def conditions_of(world, ds, distill_dirs, prompts: list[QASample], batch: int) -> list:
    """C_L of every prompt from the (frozen) world model, unpadded; Nones when the high-level condition is off."""
    if world is None:
        return [None] * len(prompts)
    store = FrameStore(ds, distill_dirs, world.comp.world.weather, world.comp.world.trajectory_frames)
    out = []
    for i in range(0, len(prompts), batch):
        chunk = prompts[i : i + batch]
        h, m = world.condition(chunk, store)
        out += [h[b, m[b]].cpu() for b in range(len(chunk))]
    return out


def pad_tokens(tokens: list[torch.Tensor | None]) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Unpadded C_L ``[L_b, D]`` each -> ``tokens_BLD`` zero-padded and ``mask_BL``; (None, None) when off."""
    if tokens[0] is None:
        return None, None
    n = max(len(t) for t in tokens)
    out = torch.zeros(len(tokens), n, tokens[0].shape[-1])
    mask = torch.zeros(len(tokens), n, dtype=torch.bool)
    for b, t in enumerate(tokens):
        out[b, : len(t)] = t
        mask[b, : len(t)] = True
    return out, mask


def save_grid(path: Path, ex: GenExample, rgb: torch.Tensor) -> None:
    """reference | condition | generated | ground truth, one row."""
    tiles = [ex.ref_rgb, ex.cond_rgb, rgb.cpu(), ex.target_rgb]
    row = torch.cat([t.clamp(0, 1) for t in tiles], dim=2).permute(1, 2, 0).numpy()
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor((row * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
