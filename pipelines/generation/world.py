"""Generation examples from the GaussianDWM release's world samples (``pipelines.data.gaussiandwm_world``), for a
dataset with Gaussians but no cameras, LiDAR or scene images.

A world sample is one clip: a reference view, T pseudo RGB-D frames the release rendered from the Gaussians, and
optionally T ground-truth frames and depths. Frame t of a clip becomes one ``GenExample`` (target ``WorldTarget``):

- reference: the sample's ``ref_image``; its depth is zeros (0 = none: the release has no depth of the reference view);
- low-level C_I, C_D: pseudo frame t and its ``depth_proj``, in place of our Gaussians projected into a target camera
  (``samples.build_example``), which needs a camera rig the release lacks; the mask is ``depth_proj > 0``;
- target: ground-truth frame t and its depth; a sample without ground-truth depth has zeros (0 = none), which
  ``metrics.depth_errors`` leaves out and training refuses (``need_depth``: Eq. L_gen has no per-pixel mask, so
  zeros would teach the depth latent a blank map);
- C_L: one prompt per clip, the sample's instruction with ``<gauss>`` over its frame's Gaussians, read through the
  ``FrameStore`` the world model's QA are read through, so C_L sees what the world model trained on (on the release:
  the instruction and the world tokens, no image; the reference view reaches the UNet as d_ref).

Every image is resized (not cropped) to the model's ``image_size`` as ``samples.build_example`` does: RGB with area
interpolation, depth nearest.

Target latents: the release packs SVD VAE latents ``[T, 2, C, h, w]`` (``meta.json``); ``RGBDDual.loss`` and
``sample`` encode images with the model's own VAE (the tiny one ``diffusion_vae`` fits, or a full run's
``model.diffusion.path``), whose latent space is another, so neither flavor trains on the pack. It is read only to
check that every sample names T rows of shape ``[2, C, h, w]`` inside it (``check_latents``, from ``meta.json``).

Legend: T frames of a clip, H x W the model's image size.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from model_zoo.diffusion.vpred import depth_to_rgb
from pipelines.data.layout import GAUSS_TOKEN, DataError, read_latent_meta
from pipelines.data.reader import GSQADataset, WorldSample
from pipelines.generation.samples import GenExample
from pipelines.understanding.data import FrameStore, QASample, gaussians_path

KIND = "world"
"""Target family (metric names ``gen/world/<metric>``)."""


@dataclass(frozen=True)
class WorldTarget:
    """Frame ``index`` of world sample ``sample_id``: the ``target`` of its ``GenExample``."""

    sample_id: str
    split: str
    scene: str
    """The sample's scene (``scene_token``)."""
    frame: int
    """The scene frame whose Gaussians the sample reads (``frame_idx``)."""
    index: int
    """Frame t of the clip, 0..T-1."""
    camera: str
    """The sample's first view, as the release names it (e.g. ``CAM_FRONT``); the dataset has no camera rig."""
    kind: str = KIND

    @property
    def name(self) -> str:
        return KIND

    @property
    def clip(self) -> tuple[tuple[str, str], int]:
        """(clip key, position): every sample is a clip of its own, its frames in order (``metrics.clips``)."""
        return (self.sample_id, self.split), self.index


@dataclass
class WorldClip:
    """One usable world sample: its C_L prompt and one example per frame."""

    sample: WorldSample
    prompt: QASample
    examples: list[GenExample]


def split_samples(ds: GSQADataset, split: str) -> list[WorldSample]:
    """The world samples of ``split``; none is an error naming the dataset and the split."""
    samples = ds.world_samples(split)
    if not samples:
        held = sorted(set(ds.world()["split"].to_pylist()))
        why = (
            f"its world table holds splits {held}"
            if held
            else "it has no world table (world.parquet: import the GaussianDWM release with its world_*.jsonl)"
        )
        name = ds.meta.get("name", ds.root.name)
        raise DataError(f"dataset '{name}' at {ds.root}: no world samples in split '{split}'; {why}")
    return samples


def instruction(w: WorldSample) -> str:
    """The sample's first human turn (our ``from``/``value`` or the release's ``role``/``content``)."""
    for c in w.row["conversations"]:
        if c.get("from", c.get("role")) in ("human", "user"):
            return c.get("value", c.get("content"))
    raise DataError(f"{w.where}: conversation has no human turn ({w.row['conversations']!r})")


def prompt(w: WorldSample) -> QASample:
    """The prompt the LLM turns into C_L: the instruction over the sample's frame and views."""
    views = tuple(w.row["views"])
    return QASample(w.id, w.row["scene_token"], int(w.row["frame_idx"]), KIND, instruction(w), "", views)


def check_latents(w: WorldSample) -> tuple[int, ...]:
    """The per-frame latent shape ``(2, C, h, w)`` the sample names in its pack, after checking one row per frame
    inside the pack (``meta.json`` only; no latent is read)."""
    rel = w.row["latent_pack"]
    _, shape = read_latent_meta(w.ds.root / rel, f"{w.where} latent_pack {rel}")
    indices = list(w.row["latent_indices"])
    if len(indices) != w.num_frames:
        raise DataError(f"{w.where}: {len(indices)} latent_indices for {w.num_frames} pseudo frames")
    if indices and max(indices) >= shape[0]:
        raise DataError(f"{w.where}: latent_indices reach {max(indices)} but {rel} holds {shape[0]} latents")
    return tuple(shape[1:])


def skip_reason(w: WorldSample, scene_dirs: Mapping[str, Path], need_depth: bool) -> str | None:
    """Why the sample gives no examples, or None. The Gaussian checks hold whether or not C_L is on, so every row of
    an ablation table trains and scores the same samples."""
    if not w.row["gt_rgb"]:
        return "no_ground_truth"
    if need_depth and not w.row["gt_depth"]:
        return "no_gt_depth"
    scene = w.row["scene_token"]
    if scene not in scene_dirs:
        return "scene_without_gaussians"
    if not gaussians_path(scene_dirs[scene], int(w.row["frame_idx"])).is_file():
        return "frame_without_gaussians"
    if GAUSS_TOKEN not in instruction(w):
        return "instruction_without_gauss_placeholder"
    return None


def resize_rgb(img_HW3: np.ndarray, hw: Sequence[int]) -> torch.Tensor:
    """``[3, H, W]`` in [0, 1], area-interpolated (as ``samples.build_example``)."""
    small = cv2.resize(img_HW3, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(small)).permute(2, 0, 1).float() / 255.0


def resize_depth(depth_HW: np.ndarray, hw: Sequence[int]) -> torch.Tensor:
    """``[H, W]`` metres, nearest (a depth is never blended across an edge)."""
    return torch.from_numpy(cv2.resize(depth_HW.astype(np.float32), (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST))


def clip_examples(w: WorldSample, hw: Sequence[int]) -> list[GenExample]:
    """One example per frame of a sample with ground-truth frames (see the module docstring for each part)."""
    gt_rgb = w.gt_rgb()
    if len(gt_rgb) == 0:
        raise DataError(f"{w.where}: no ground-truth frames to make targets of")
    gt_depth = w.gt_depth()
    pseudo_rgb, pseudo_depth = w.pseudo_rgb(), w.pseudo_depth()
    H, W = hw
    ref_rgb, none_HW = resize_rgb(w.ref_image(), hw), torch.zeros(H, W)
    out = []
    for t in range(w.num_frames):
        cond_depth = resize_depth(pseudo_depth[t], hw)
        target = WorldTarget(w.id, w.split, w.row["scene_token"], int(w.row["frame_idx"]), t, _camera(w))
        out.append(
            GenExample(
                target,
                resize_rgb(gt_rgb[t], hw),
                resize_depth(gt_depth[t], hw) if len(gt_depth) else none_HW,
                ref_rgb,
                none_HW,
                resize_rgb(pseudo_rgb[t], hw),
                cond_depth,
                (cond_depth > 0).float(),
            )
        )
    return out


def world_clips(
    ds: GSQADataset, split: str, scene_dirs: Mapping[str, Path], hw: Sequence[int], *, need_depth: bool
) -> tuple[list[WorldClip], Counter]:
    """The usable samples of ``split`` as clips, and how many were skipped, by reason (``skip_reason``)."""
    clips, skipped = [], Counter()
    for w in split_samples(ds, split):
        reason = skip_reason(w, scene_dirs, need_depth)
        if reason is not None:
            skipped[reason] += 1
            continue
        check_latents(w)
        clips.append(WorldClip(w, prompt(w), clip_examples(w, hw)))
    return clips, skipped


def clip_conditions(
    world, ds: GSQADataset, scene_dirs: Mapping[str, Path], clips: Sequence[WorldClip], batch: int
) -> list[torch.Tensor | None]:
    """C_L of every example, unpadded: one LLM pass per clip (its frames share the prompt); Nones when ``world`` is
    None (the high-level condition off)."""
    n = [len(c.examples) for c in clips]
    if world is None:
        return [None] * sum(n)
    store = FrameStore(ds, scene_dirs, world.comp.world.weather, world.comp.world.trajectory_frames)
    per_clip = []
    with torch.no_grad():
        for i in range(0, len(clips), batch):
            chunk = [c.prompt for c in clips[i : i + batch]]
            h, m = world.condition(chunk, store)
            per_clip += [h[b, m[b]].cpu() for b in range(len(chunk))]
    return [c for c, k in zip(per_clip, n, strict=True) for _ in range(k)]


def vae_images(
    samples: Sequence[WorldSample], hw: Sequence[int], max_depth: float, frames_per_sample: int, seed: int
) -> torch.Tensor:
    """``[N, 3, H, W]`` in [0, 1] to fit the tiny VAE on: every sample's reference view, and up to
    ``frames_per_sample`` of its ground-truth frames (drawn with ``seed``), each with its depth as pseudo-RGB
    (``(depth_to_rgb + 1) / 2``, as ``RGBDDual.fit_vae`` expects)."""
    rng = np.random.default_rng(seed)
    out = []
    for w in samples:
        out.append(resize_rgb(w.ref_image(), hw))
        gt_rgb, gt_depth = w.gt_rgb(), w.gt_depth()
        for t in sorted(rng.permutation(len(gt_rgb))[:frames_per_sample].tolist()):
            out.append(resize_rgb(gt_rgb[t], hw))
            if len(gt_depth):
                out.append((depth_to_rgb(resize_depth(gt_depth[t], hw)[None], max_depth)[0] + 1) / 2)
    return torch.stack(out)


def _camera(w: WorldSample) -> str:
    views = w.row["views"]
    return views[0] if views else ""
