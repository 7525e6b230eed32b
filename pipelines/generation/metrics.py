"""Scores of generated RGB-D views against ground truth, per target family (names as in README: Stages).

``gen/<target>/psnr`` and ``ssim`` on RGB in [0, 1] at the model's resolution; ``depth_absrel`` = mean |d - d*| / d*
and ``depth_rmse`` (metres) over pixels with ground-truth depth in (0, max_depth]. Protocol ``approximate``: computed
at the model's working resolution, not the dataset's. Fréchet distances (``pipelines.generation.frechet``) are
reported per target and per pooled shift family ``shift_pm<m>m`` (the ±m views together, as the paper's tables pool
them): ``gen/shift_pm1m/fid`` (or ``fd_daisy``) and ``gen/shift_pm1m/fvd`` (or its stand-in ``fd_video_daisy``) are
Tab. world's two columns.
"""

from __future__ import annotations

import re
from collections import defaultdict

import numpy as np
import torch

from pipelines.generation.conditions import target_name
from pipelines.recon.losses import psnr, ssim

PROTOCOL = "approximate"


def depth_errors(pred_HW: torch.Tensor, gt_HW: torch.Tensor, max_depth: float = 80.0) -> tuple[float, float]:
    """(AbsRel, RMSE) over valid ground-truth pixels; NaN when there are none."""
    valid = (gt_HW > 0) & (gt_HW <= max_depth)
    if not bool(valid.any()):
        return float("nan"), float("nan")
    p, g = pred_HW[valid].double(), gt_HW[valid].double()
    return float(((p - g).abs() / g).mean()), float(((p - g) ** 2).mean().sqrt())


def pooled_groups(names: list[str]) -> dict[str, list[str]]:
    """The pooled shift families the paper reports (``±1 m``: the +1 m and -1 m views together): ``shift_pm<m>m`` ->
    its two target names, for every magnitude logged with both signs."""
    lateral = {}
    for n in names:
        m = re.fullmatch(r"shift_(-?[0-9.e+-]+)m", n)
        if m:
            lateral[float(m[1])] = n
    return {
        f"shift_pm{target_name(lateral_m=v)[6:-1]}m": [lateral[v], lateral[-v]]
        for v in sorted(lateral)
        if v > 0 and -v in lateral
    }


def clip_position(target) -> tuple[tuple, int]:
    """(clip key, frame) of a scored target: its (scene, camera) and frame, unless it names its own ``clip`` (a world
    sample's frames are a clip of their own: ``pipelines.generation.world.WorldTarget``)."""
    own = getattr(target, "clip", None)
    return own if own is not None else ((target.scene, target.camera), target.frame)


def clips(scored: list, names: list[str], frames: int) -> list[list[int]]:
    """Indices into ``scored`` of every clip of ``frames`` consecutive frames of one (scene, camera, target), in frame
    order: non-overlapping windows of each run of consecutive frames; the incomplete tail of a run is left out."""
    seqs: dict[tuple, list[tuple[int, int]]] = defaultdict(list)
    for i, (ex, _, _) in enumerate(scored):
        t = ex.target
        if t.name in names:
            key, frame = clip_position(t)
            seqs[(t.name, *key)].append((frame, i))
    out = []
    for key in sorted(seqs):
        run: list[int] = []
        prev = None
        for f, i in sorted(seqs[key]):
            if prev is not None and f != prev + 1:
                run = []
            run.append(i)
            prev = f
            if len(run) == frames:
                out.append(run)
                run = []
    return out


def score_views(
    scored: list, max_depth: float = 80.0, extractor=None, video_extractor=None, clip_frames: int = 10
) -> dict[str, float]:
    """``scored``: (example, generated rgb [3, H, W], generated depth [H, W]) triples -> means per target, plus
    Fréchet distances of generated views to ground truth per target and per pooled shift family (``shift_pm1m``:
    the ±1 m views together, the paper's Tab. world):

    - ``extractor`` (image features, named ``fid`` or ``fd_<extractor>``) over views, where a group has >= 2;
    - ``video_extractor`` (``fvd``, or its stand-in ``fd_video_daisy``) over clips of ``clip_frames`` consecutive
      frames of one scene, camera and target (``clips``), where a group has >= 2.
    """
    per: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for ex, rgb, depth in scored:
        name = ex.target.name
        a, b = rgb.clamp(0, 1).permute(1, 2, 0).float(), ex.target_rgb.permute(1, 2, 0).float()
        per[name]["psnr"].append(psnr(a, b))
        per[name]["ssim"].append(float(ssim(a, b)))
        absrel, rmse = depth_errors(depth, ex.target_depth, max_depth)
        per[name]["depth_absrel"].append(absrel)
        per[name]["depth_rmse"].append(rmse)
    out = {f"gen/{t}/{k}": float(np.nanmean(v)) for t, d in sorted(per.items()) for k, v in d.items()}
    groups = {n: [n] for n in sorted(per)} | pooled_groups(sorted(per))
    if extractor is not None:
        from pipelines.generation.frechet import feature_stats, frechet_distance

        real = torch.stack([ex.target_rgb for ex, _, _ in scored])
        fake = torch.stack([rgb.clamp(0, 1) for _, rgb, _ in scored])
        f_real, f_fake = extractor(real), extractor(fake)  # each view once; every group selects its rows
        for group, names in groups.items():
            idx = [i for i, (ex, _, _) in enumerate(scored) if ex.target.name in names]
            if len(idx) >= 2:
                out[f"gen/{group}/{extractor.name}"] = frechet_distance(
                    *feature_stats(f_real[idx]), *feature_stats(f_fake[idx])
                )
    if video_extractor is not None:
        from pipelines.generation.frechet import feature_stats, frechet_distance

        if clip_frames < 2:
            raise ValueError(f"stage.evaluate_gen.fvd_clip_frames must be >= 2 (a clip is a video), got {clip_frames}")
        per_group = {g: clips(scored, names, clip_frames) for g, names in groups.items()}
        every = sorted({tuple(c) for cl in per_group.values() for c in cl})  # each clip once; groups select rows
        if every:
            real = torch.stack([torch.stack([scored[i][0].target_rgb for i in c]) for c in every])
            fake = torch.stack([torch.stack([scored[i][1].clamp(0, 1) for i in c]) for c in every])
            row = {c: k for k, c in enumerate(every)}
            v_real, v_fake = video_extractor(real), video_extractor(fake)
        for group, cl in per_group.items():
            if len(cl) >= 2:
                idx = [row[tuple(c)] for c in cl]
                out[f"gen/{group}/{video_extractor.name}"] = frechet_distance(
                    *feature_stats(v_real[idx]), *feature_stats(v_fake[idx])
                )
    return out
