"""Rasterizer: the torch tile backend against the dense reference, side by side in one run.

Forward and forward+backward wall time (median), their ratio, and peak memory of one forward+backward. Peak memory is
measured in a fresh subprocess per backend: the peak RSS of the call (Linux VmHWM, reset just before it) minus the
RSS before it, with glibc's mmap threshold at 64 KiB so freed tensors go back to the OS and RSS tracks live tensors.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import psutil
import torch

from benchmarks.common import Result, median_time
from model_zoo.render import Camera, rasterize

FULL = {"n": 20_000, "width": 160, "height": 96, "channels": 16}
QUICK = {"n": 5_000, "width": 80, "height": 48, "channels": 16}


def scene(n: int, width: int, height: int, channels: int, seed: int = 0) -> tuple[dict[str, torch.Tensor], Camera]:
    """A driving-like frustum: Gaussians 2-50 m ahead (denser near), 1-8 cm scales, opacities 0.05-0.6."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    cam = Camera(torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]), torch.eye(4), width, height)
    z = 2 + torch.rand(n, generator=g) ** 2 * 48
    xy = (torch.rand(n, 2, generator=g) - 0.5) * z[:, None] * torch.tensor([width / f, height / f]) * 1.1
    params = {
        "means": torch.cat([xy, z[:, None]], dim=1),
        "scales": torch.exp(torch.rand(n, 3, generator=g) * 2 - 4.5),
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.rand(n, generator=g) * 0.55 + 0.05,
        "colors": torch.rand(n, 3, generator=g),
        "features": torch.randn(n, channels, generator=g),
    }
    return params, cam


def render_step(backend: str, params: dict, cam: Camera, backward: bool):
    """One render (and backward of a fixed weighted sum of rgb, depth and features) as a zero-argument callable."""
    leaves = {k: v.clone().requires_grad_(backward) for k, v in params.items()}
    g = torch.Generator().manual_seed(1)
    h, w, c = cam.height, cam.width, params["features"].shape[1]
    weights = [torch.randn(h, w, 3, generator=g), torch.randn(h, w, generator=g), torch.randn(h, w, c, generator=g)]

    def step():
        for v in leaves.values():
            v.grad = None
        with torch.set_grad_enabled(backward):
            out = rasterize(**leaves, camera=cam, backend=backend)
            if backward:
                loss = (out.rgb * weights[0]).sum() + (out.depth * weights[1]).sum()
                (loss + (out.features * weights[2]).sum()).backward()
        return out

    return step


def peak_memory_mb(backend: str, size: dict) -> float:
    """Peak RSS growth (MiB) of one forward+backward, in a fresh subprocess."""
    env = os.environ | {"MALLOC_MMAP_THRESHOLD_": "65536"}
    cmd = [sys.executable, "-m", "benchmarks.bench_render", "--peak", backend, json.dumps(size)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    done = subprocess.run(cmd, env=env, cwd=root, capture_output=True, text=True, check=True)
    return float(done.stdout.strip().splitlines()[-1])


def _peak_worker(backend: str, size: dict) -> None:
    params, cam = scene(**size)
    step = render_step(backend, params, cam, backward=True)
    # Reset the high-water mark to the current RSS (Linux >= 4.0); exec keeps the parent's ru_maxrss otherwise.
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = psutil.Process().memory_info().rss
    step()
    with open("/proc/self/status") as f:
        hwm_kib = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    print((hwm_kib * 1024 - before) / 2**20)


def run(quick: bool = False) -> list[Result]:
    size = QUICK if quick else FULL
    params, cam = scene(**size)
    reps_fast, reps_dense = (3, 1) if quick else (7, 2)
    t = {}
    for backend, reps in (("torch", reps_fast), ("dense", reps_dense)):
        for backward in (False, True):
            step = render_step(backend, params, cam, backward)
            t[backend, backward], _ = median_time(step, reps, warmup=1 if backend == "torch" else 0)
    out = render_step("torch", params, cam, backward=False)()
    mem = {b: peak_memory_mb(b, size) for b in ("torch", "dense")}
    detail = (
        f"{size['n']:,} Gaussians ({out.n_visible:,} visible), {size['width']}x{size['height']}, RGB+depth+"
        f"{size['channels']} features, mean alpha {out.alpha.mean():.2f}, {torch.get_num_threads()} threads"
    )
    mem_detail = "one fwd+bwd in a fresh process: VmHWM - RSS before, glibc mmap threshold 64 KiB"
    ms = {k: v * 1e3 for k, v in t.items()}
    return [
        Result("render", "torch tiles forward (median)", ms["torch", False], "ms", detail=detail),
        Result("render", "torch tiles forward+backward (median)", ms["torch", True], "ms", detail=detail),
        Result("render", "dense reference forward", ms["dense", False], "ms", detail=f"median of {reps_dense}"),
        Result(
            "render", "dense reference forward+backward", ms["dense", True], "ms",
            detail=f"median of {reps_dense}; pixel chunks checkpointed to fit in memory",
        ),
        Result("render", "dense / torch forward (speed-up)", ms["dense", False] / ms["torch", False], "x"),
        Result("render", "dense / torch forward+backward (speed-up)", ms["dense", True] / ms["torch", True], "x",
               10.0, ">="),
        Result("render", "torch tiles fwd+bwd peak memory", mem["torch"], "MiB", detail=mem_detail),
        Result("render", "dense reference fwd+bwd peak memory", mem["dense"], "MiB", detail=mem_detail),
    ]  # fmt: skip


if __name__ == "__main__" and sys.argv[1:2] == ["--peak"]:
    _peak_worker(sys.argv[2], json.loads(sys.argv[3]))
