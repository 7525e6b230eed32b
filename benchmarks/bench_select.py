"""Coarse selection: ``driving_aware`` (torch) against the straightforward numpy + dict reference, in one run.

Median wall time of one selection, the speed-up over the reference, whether both select the same set, and where the
time goes (the scores; the TopK/VoxelTopK branches and their union). Other variants are timed for information only.
"""

from __future__ import annotations

import torch

from benchmarks.common import Result, median_time
from model_zoo import registry, selectors
from model_zoo.selectors import DrivingAwareSelector, SelectorConfig, SelectorInputs, driving_aware_reference, voxel_ids

FULL = {"n": 1_000_000, "k_c": 16_384, "repeats": 15, "ref_repeats": 3}
QUICK = {"n": 100_000, "k_c": 2_048, "repeats": 5, "ref_repeats": 1}
TARGET_MS = 100.0
OTHERS = ("voxel_topk", "topk_uniform", "random")


def scene(n: int, seed: int = 0) -> SelectorInputs:
    """A driving-like field: 60% of the Gaussians along a road (y ~ N(0, 8 m)), the rest spread over 150 x 80 x 8 m;
    log-uniform scales 1 cm-0.6 m, non-unit quaternions, uniform opacities; a 13-waypoint gently curving 60 m path."""
    g = torch.Generator().manual_seed(seed)
    road = int(0.6 * n)
    x = torch.rand(n, generator=g) * 150 - 30
    y = torch.cat([torch.randn(road, generator=g) * 8, torch.rand(n - road, generator=g) * 80 - 40])
    z = torch.rand(n, generator=g) * 8 - 2
    xs = torch.linspace(0, 60, 13)
    return SelectorInputs(
        xyz=torch.stack([x, y, z], dim=1),
        scale=torch.exp(torch.rand(n, 3, generator=g) * 4.1 - 4.6),
        rotation=torch.randn(n, 4, generator=g),
        opacity=torch.rand(n, generator=g),
        trajectory=torch.stack([xs, 0.004 * xs**2], dim=1),
        similarity=torch.rand(n, generator=g),
    )


def run(quick: bool = False) -> list[Result]:
    size = QUICK if quick else FULL
    n, k_c = size["n"], size["k_c"]
    g = scene(n)
    cfg = SelectorConfig(name="driving_aware", k_c=k_c)
    sel = DrivingAwareSelector(cfg)
    t_torch, _ = median_time(lambda: sel(g), size["repeats"], warmup=2)
    t_score, _ = median_time(lambda: sel.score(g), size["repeats"], warmup=1)
    s_N = sel.score(g)
    t_branch, _ = median_time(lambda: selectors._topk_voxel_union(g, s_N, cfg), size["repeats"], warmup=1)
    t_ref, _ = median_time(lambda: driving_aware_reference(g, cfg), size["ref_repeats"], warmup=0)
    picked = sel(g)
    ours = set(picked.index[picked.mask].tolist())
    ref = set(driving_aware_reference(g, cfg).tolist())
    voxels = len(set(voxel_ids(g.xyz, cfg.voxel_size)[0].tolist()))
    detail = (
        f"N={n:,}, K_c={k_c:,}, 13 waypoints, voxel {cfg.voxel_size} m ({voxels:,} occupied), "
        f"{torch.get_num_threads()} threads, median of {size['repeats']}"
    )
    others = []
    for name in OTHERS:
        other = registry.build("selector", name, SelectorConfig(name=name, k_c=k_c))
        t, _ = median_time(lambda other=other: other(g), 3, warmup=1)
        others.append(Result("select", f"{name} (median, info)", t * 1e3, "ms", detail=f"N={n:,}, K_c={k_c:,}"))
    return [
        Result("select", "driving_aware (median)", t_torch * 1e3, "ms", TARGET_MS, "<=", detail),
        Result("select", "  scores S_i alone", t_score * 1e3, "ms", detail="Q_i, d_i, T_i, S_i"),
        Result("select", "  TopK ∪ VoxelTopK alone", t_branch * 1e3, "ms",
               detail="on a precomputed S; parts timed alone need not add up to the whole"),
        Result("select", "numpy + dict reference", t_ref * 1e3, "ms", detail=f"median of {size['ref_repeats']}"),
        Result("select", "reference / driving_aware (speed-up)", t_ref / t_torch, "x"),
        Result("select", "same selected set as the reference", float(ours == ref), "bool", 1.0, ">=",
               f"|symmetric difference| = {len(ours ^ ref)}"),
        *others,
    ]  # fmt: skip
