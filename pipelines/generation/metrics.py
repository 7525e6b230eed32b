"""Scores of generated RGB-D views against ground truth, per target family (names as in README: Stages).

``gen/<target>/psnr`` and ``ssim`` on RGB in [0, 1] at the model's resolution; ``depth_absrel`` = mean |d - d*| / d*
and ``depth_rmse`` (metres) over pixels with ground-truth depth in (0, max_depth]. Protocol ``approximate``: computed
at the model's working resolution, not the dataset's.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch

from pipelines.recon.losses import psnr, ssim

PROTOCOL = "approximate"


def depth_errors(pred_HW: torch.Tensor, gt_HW: torch.Tensor, max_depth: float = 80.0) -> tuple[float, float]:
    """(AbsRel, RMSE) over valid ground-truth pixels; NaN when there are none."""
    valid = (gt_HW > 0) & (gt_HW <= max_depth)
    if not bool(valid.any()):
        return float("nan"), float("nan")
    p, g = pred_HW[valid].double(), gt_HW[valid].double()
    return float(((p - g).abs() / g).mean()), float(((p - g) ** 2).mean().sqrt())


def score_views(scored: list, max_depth: float = 80.0, extractor=None) -> dict[str, float]:
    """``scored``: (example, generated rgb [3, H, W], generated depth [H, W]) triples -> means per target, plus the
    Fréchet distance of each target's generated views to its ground truth under ``extractor`` (named by it:
    ``fid`` or ``fd_<extractor>``) where a target has >= 2 views."""
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
    if extractor is not None:
        from pipelines.generation.frechet import frechet

        for name in sorted(per):
            pairs = [(ex.target_rgb, rgb.clamp(0, 1)) for ex, rgb, _ in scored if ex.target.name == name]
            if len(pairs) >= 2:
                real, fake = (torch.stack(x) for x in zip(*pairs, strict=True))
                out[f"gen/{name}/{extractor.name}"] = frechet(real, fake, extractor)
    return out
