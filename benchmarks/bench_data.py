"""Data layer: synthetic_mini generation time; 1M-Gaussian frame from Arrow vs torch.load of a .pth."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import Result, median_time
from pipelines.data.layout import gaussians_table, write_arrow
from pipelines.data.reader import gaussians_from_table, read_arrow
from pipelines.data.synth.build import build as build_synth
from pipelines.data.synth.config import SynthConfig


def _gaussians(n: int, d: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    rot = rng.normal(size=(n, 4)).astype(np.float32)
    return {
        "xyz": rng.normal(scale=20, size=(n, 3)).astype(np.float32),
        "scale": rng.uniform(0.01, 0.5, size=(n, 3)).astype(np.float32),
        "rotation": rot / np.linalg.norm(rot, axis=1, keepdims=True),
        "opacity": rng.uniform(size=n).astype(np.float32),
        "color": rng.uniform(size=(n, 3)).astype(np.float32),
        "feature": rng.normal(size=(n, d)).astype(np.float32),
    }


def bench_generation(quick: bool) -> list[Result]:
    cfg = SynthConfig()
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(1 if quick else 3):
            t0 = time.perf_counter()
            build_synth(cfg, root=Path(tmp) / f"ds{i}")
            times.append(time.perf_counter() - t0)
    detail = (
        f"{cfg.num_scenes} scenes x {cfg.num_frames} frames x 6 cams, {cfg.width}x{cfg.height}, "
        f"{len(cfg.weathers)} weathers"
    )
    return [Result("data", "synthetic_mini generation (median)", float(np.median(times)), "s", 60.0, "<=", detail)]


def bench_gaussian_load(quick: bool) -> list[Result]:
    n, d = (200_000 if quick else 1_000_000), 16
    g = _gaussians(n, d)
    repeats = 5 if quick else 20
    with tempfile.TemporaryDirectory() as tmp:
        arrow_path, pth_path = Path(tmp) / "frame.arrow", Path(tmp) / "frame.pth"
        write_arrow(gaussians_table(g), arrow_path)
        # The public release's per-frame dict (logits / log-scales, as 3DGS stores them).
        torch.save(
            {
                "_xyz": torch.from_numpy(g["xyz"]),
                "_scaling": torch.from_numpy(np.log(g["scale"])),
                "_rotation": torch.from_numpy(g["rotation"]),
                "_opacity": torch.from_numpy(g["opacity"]).logit()[:, None],
                "_language_feature": torch.from_numpy(g["feature"]),
            },
            pth_path,
        )

        def load_arrow():
            arrays = gaussians_from_table(read_arrow(arrow_path, "bench"))
            return {k: torch.from_numpy(v) for k, v in arrays.items()}

        def load_arrow_copied():
            # Forces every byte off the mapping into owned memory, as torch.load must.
            arrays = gaussians_from_table(read_arrow(arrow_path, "bench"))
            return {k: torch.from_numpy(np.array(v, copy=True)) for k, v in arrays.items()}

        def load_pth():
            return torch.load(pth_path, map_location="cpu", weights_only=True)

        # Both sides produce CPU tensors of every field; alternate so neither gets a warmer cache.
        t_arrow, _ = median_time(load_arrow, repeats, warmup=2)
        t_copy, _ = median_time(load_arrow_copied, repeats, warmup=2)
        t_pth, _ = median_time(load_pth, repeats, warmup=2)
        size_mb = arrow_path.stat().st_size / 2**20
    detail = f"{n:,} Gaussians, d_feature={d}, {size_mb:.0f} MiB, page cache warm, median of {repeats}"
    return [
        Result("data", "gaussian frame load, Arrow mmap", t_arrow * 1e3, "ms", detail=detail),
        Result("data", "gaussian frame load, torch.load .pth", t_pth * 1e3, "ms", detail=detail),
        Result("data", "gaussian frame load, Arrow mmap + copy", t_copy * 1e3, "ms", detail=detail),
        Result("data", "torch.load / Arrow mmap (speed-up)", t_pth / t_arrow, "x", 1.0, ">=", "zero-copy views"),
        Result("data", "torch.load / Arrow copied (speed-up)", t_pth / t_copy, "x", detail="every byte read"),
    ]


def run(quick: bool = False) -> list[Result]:
    return bench_gaussian_load(quick) + bench_generation(quick)
