"""Distillation's inner loop on CPU, gdwm's against torch's generic path, side by side in one run.

A view's compositing weights (``composite_weights``: the tile walk, then the sparse matrix), the same weights over a
scene's canonical rows (``view_weights``), and a distillation step over 8 such views (render the decoded features
through every view's weights, L1, backward). torch's generic path coalesces the weights twice (a sort, and a merge of
duplicates the walk never makes) and, in the backward of ``W @ F``, transposes the sparse ``W`` again at every step;
gdwm sorts the walk's entries once, keeps them flagged coalesced, and keeps each view's transpose
(``ViewFeatures.weights_NP``). Each pair gives the same tensors bit for bit, which the run checks before timing them.
"""

from __future__ import annotations

import contextlib

import torch

import model_zoo.render.torch_tiles as tiles
from benchmarks.bench_render import scene
from benchmarks.common import Result, median_time
from model_zoo.render import composite_weights
from pipelines.distill.field import on_rows
from pipelines.distill.optimize import render_features

FULL = {"n": 20_000, "width": 160, "height": 96, "channels": 64}
QUICK = {"n": 5_000, "width": 80, "height": 48, "channels": 64}
VIEWS = 8
"""``views_per_step`` of the distillation's default config."""


def _coalesce(pix, rows, w, shape):
    return torch.sparse_coo_tensor(torch.stack([pix, rows]), w, shape).coalesce()


@contextlib.contextmanager
def coalescing():
    """``splat_weights`` building its matrix with torch's coalesce, as it did before ``sorted_coo``."""
    tiles.sorted_coo, before = _coalesce, tiles.sorted_coo
    try:
        yield
    finally:
        tiles.sorted_coo = before


def on_rows_coalescing(w: torch.Tensor, rows: torch.Tensor, n: int, min_weight: float = 0.0) -> torch.Tensor:
    """``on_rows`` as ``view_weights`` did it before: the same entries, coalesced again."""
    idx, vals = w.indices(), w.values()
    big = vals >= min_weight
    out = torch.sparse_coo_tensor(torch.stack([idx[0, big], rows[idx[1, big]]]), vals[big], (w.shape[0], n))
    return out.coalesce().to_sparse_csr()


def run(quick: bool = False) -> list[Result]:
    size = QUICK if quick else FULL
    reps = 3 if quick else 7
    torch.set_num_threads(1)  # as one scene actor of a 2-CPU local Ray (num_cpus=1) runs it
    params, cam = scene(**size)
    g = (params["means"], params["scales"], params["quats"], params["opacities"])
    w = composite_weights(*g, cam)
    with coalescing():
        ref = composite_weights(*g, cam)
    assert torch.equal(w.indices(), ref.indices()) and torch.equal(w.values(), ref.values())
    t_ours, _ = median_time(lambda: composite_weights(*g, cam), reps)
    with coalescing():
        t_theirs, _ = median_time(lambda: composite_weights(*g, cam), reps)

    # the scene has twice the Gaussians the view sees; its visible ones are every other row
    rows, n_scene = torch.arange(0, 2 * size["n"], 2), 2 * size["n"]
    a, b = on_rows(w, rows, n_scene), on_rows_coalescing(w, rows, n_scene)
    parts = [(m.crow_indices(), m.col_indices(), m.values()) for m in (a, b)]
    assert all(torch.equal(x, y) for x, y in zip(*parts, strict=True))
    r_ours, _ = median_time(lambda: on_rows(w, rows, n_scene), reps)
    r_theirs, _ = median_time(lambda: on_rows_coalescing(w, rows, n_scene), reps)

    # views: the same geometry seen from cameras shifted sideways, as a drive's frames see a scene
    views = [composite_weights(params["means"] + torch.tensor([0.05 * i, 0.0, 0.0]), *g[1:], cam).to_sparse_csr()
             for i in range(VIEWS)]  # fmt: skip
    transposed = [v.t().to_sparse_csr() for v in views]
    gen = torch.Generator().manual_seed(0)
    feats = torch.randn(size["n"], size["channels"], generator=gen)
    target = torch.randn(VIEWS, cam.height, cam.width, size["channels"], generator=gen)
    hw = (cam.height, cam.width)

    def step(with_transpose: bool) -> torch.Tensor:
        f = feats.clone().requires_grad_(True)
        out = [render_features(v, f, hw, t if with_transpose else None) for v, t in zip(views, transposed, strict=True)]
        (torch.stack(out) - target).abs().mean().backward()
        return f.grad

    assert torch.equal(step(True), step(False))
    s_ours, _ = median_time(lambda: step(True), reps)
    s_theirs, _ = median_time(lambda: step(False), reps)
    t_transpose, _ = median_time(lambda: [v.t().to_sparse_csr() for v in views], reps)
    detail = f"{size['n']} Gaussians, {size['width']}x{size['height']}, median of {reps}, 1 thread"
    return [
        Result("distill", "a view's weights, sorted once (gdwm)", t_ours * 1e3, "ms",
               detail=f"{detail}; {w._nnz():,} weights"),
        Result("distill", "a view's weights, coalesced (torch)", t_theirs * 1e3, "ms", detail="same tensor, checked"),
        Result("distill", "  torch / gdwm (speed-up)", t_theirs / t_ours, "x", detail="the walk is most of it"),
        Result("distill", "the weights on a scene's rows, kept coalesced (gdwm)", r_ours * 1e3, "ms"),
        Result("distill", "the weights on a scene's rows, coalesced again (torch)", r_theirs * 1e3, "ms",
               detail="same CSR, checked"),
        Result("distill", "  torch / gdwm (speed-up)", r_theirs / r_ours, "x", 1.5, ">="),
        Result("distill", f"a step over {VIEWS} views, kept transposes (gdwm)", s_ours * 1e3, "ms",
               detail=f"{size['channels']} feature channels; + {t_transpose * 1e3:.0f} ms once for the transposes"),
        Result("distill", f"a step over {VIEWS} views, autograd's backward (torch)", s_theirs * 1e3, "ms",
               detail="same gradient bit for bit, checked"),
        Result("distill", "  torch / gdwm (speed-up)", s_theirs / s_ours, "x", 1.5, ">="),
    ]  # fmt: skip
