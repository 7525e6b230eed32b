"""Tile-based differentiable rasterizer in pure PyTorch: the CPU backend (gsplat has no CPU path).

Legend: N Gaussians, M (tile, Gaussian) intersections, T tiles (A of them active in a chunk), P = tile_size^2 pixels
per tile, K Gaussians per chunk, E = D value channels + depth + 1 (the ones channel that accumulates alpha).

Same algorithm as the 3DGS CUDA rasterizer (Kerbl et al. 2023, Sec. 6), vectorised instead of one thread per pixel:
bin each projected Gaussian into the tiles its footprint box touches, sort each tile's list by depth, then walk all
tiles' lists together K Gaussians at a time, carrying each pixel's transmittance from chunk to chunk. A tile leaves
the walk when its list ends or every pixel in it has terminated (T < T_MIN), which is where the speed comes from.
Autograd differentiates it end to end (means, scales, quats, opacities, colours, features).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from model_zoo.render.camera import Camera
from model_zoo.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected, Splatted

LOG_T_MIN = math.log(T_MIN)


def bin_tiles(box_N4: Tensor, tile_size: int, n_tiles_x: int, n_tiles: int) -> tuple[Tensor, Tensor, Tensor]:
    """Intersections of footprint boxes with tiles, grouped by tile in input order.

    Returns ``gauss_M`` (row of each intersection, tile-major, input order kept inside a tile), ``start_T`` and
    ``count_T`` (each tile's slice of ``gauss_M``).
    """
    t_box = box_N4 // tile_size  # tile columns tx0, tx1 and rows ty0, ty1
    nx = t_box[:, 1] - t_box[:, 0] + 1
    cnt_N = nx * (t_box[:, 3] - t_box[:, 2] + 1)
    gauss_M = torch.repeat_interleave(torch.arange(box_N4.shape[0], device=box_N4.device), cnt_N)
    first_N = torch.cumsum(cnt_N, 0) - cnt_N
    off_M = torch.arange(gauss_M.numel(), device=box_N4.device) - first_N[gauss_M]
    nx_M = nx[gauss_M]
    tile_M = (t_box[gauss_M, 2] + off_M // nx_M) * n_tiles_x + t_box[gauss_M, 0] + off_M % nx_M
    tile_M, perm = torch.sort(tile_M, stable=True)  # stable: depth order survives within each tile
    count_T = torch.bincount(tile_M, minlength=n_tiles)
    return gauss_M[perm], torch.cumsum(count_T, 0) - count_T, count_T


def _walk_tiles(projected: Projected, values_ND: Tensor, camera: Camera, tile_size: int, chunk: int, on_chunk):
    """The shared tile walk; ``on_chunk(active, rows_AK, w_APK, T_in_AP, values_AKE)`` sees every chunk's weights."""
    p, W, H, ts = projected, camera.width, camera.height, tile_size
    ntx, nty = -(-W // ts), -(-H // ts)
    n_tiles, P, dev = ntx * nty, ts * ts, values_ND.device

    idx = p.visible_N.nonzero().squeeze(1)
    idx = idx[torch.argsort(p.depth_N[idx].detach(), stable=True)]
    n = idx.numel()
    # Per-Gaussian tables in depth order; row n is a transparent dummy (log-opacity -inf) that pads short lists.
    pad = values_ND.new_zeros(1)
    mu_x, mu_y = (torch.cat([col, pad]) for col in p.means2d_N2[idx].unbind(-1))
    a, b, c = p.conic_N3[idx].unbind(-1)
    half_a, b, half_c = torch.cat([0.5 * a, pad]), torch.cat([b, pad]), torch.cat([0.5 * c, pad])
    log_o = torch.cat([torch.log(p.opacity_N[idx]), pad - torch.inf])
    ones = torch.ones_like(p.depth_N[idx, None])
    values_NE = torch.cat([values_ND[idx], p.depth_N[idx, None], ones], dim=-1)  # values, z, 1 (-> alpha)
    values_NE = torch.cat([values_NE, values_NE.new_zeros(1, values_NE.shape[1])])
    rows_N = torch.cat([idx, idx.new_full((1,), -1)])  # input row of each depth-ordered Gaussian (-1: padding)

    gauss_M, start_T, count_T = bin_tiles(p.box_N4[idx], ts, ntx, n_tiles)
    gauss_M = torch.cat([gauss_M, gauss_M.new_full((1,), n)])  # gather target for padding slots

    local = torch.arange(P, device=dev)
    tile = torch.arange(n_tiles, device=dev)
    px_TP = (tile[:, None] % ntx) * ts + local % ts
    py_TP = (tile[:, None] // ntx) * ts + local // ts
    inside_TP = (px_TP < W) & (py_TP < H)
    px_TP, py_TP = px_TP.to(values_ND) + 0.5, py_TP.to(values_ND) + 0.5
    # Pixels past the image edge start "terminated" (T = 0), so they never count and never keep a tile alive.
    T_TP = inside_TP.to(values_ND)
    k_range = torch.arange(chunk, device=dev)

    for c0 in range(0, int(count_T.max()) if n else 0, chunk):
        with torch.no_grad():
            active = ((count_T > c0) & (T_TP.amax(dim=1) >= T_MIN)).nonzero().squeeze(1)
        if active.numel() == 0:
            break
        pos_AK = c0 + k_range
        slot_AK = torch.where(pos_AK < count_T[active, None], start_T[active, None] + pos_AK, gauss_M.numel() - 1)
        g_AK = gauss_M[slot_AK]

        dx = px_TP[active, :, None] - mu_x[g_AK][:, None]
        dy = py_TP[active, :, None] - mu_y[g_AK][:, None]
        power = dx * (half_a[g_AK][:, None] * dx + b[g_AK][:, None] * dy) + half_c[g_AK][:, None] * dy * dy
        alpha_APK = torch.exp(log_o[g_AK][:, None] - power).clamp(max=ALPHA_MAX)
        alpha_APK = torch.where(alpha_APK >= ALPHA_MIN, alpha_APK, 0.0)
        log_1m = torch.log1p(-alpha_APK)
        log_T_incl = torch.cumsum(log_1m, dim=-1)  # transmittance within the chunk, in log space
        T_in = T_TP[active]
        with torch.no_grad():
            # Count a Gaussian only while the transmittance after it stays >= T_MIN (3DGS's early stop).
            alive = log_T_incl >= (LOG_T_MIN - torch.log(T_in))[:, :, None]
        w_APK = torch.where(alive, alpha_APK * torch.exp(log_T_incl - log_1m), 0.0)
        on_chunk(active, rows_N[g_AK], w_APK, T_in, values_NE[g_AK])
        T_TP = T_TP.index_copy(0, active, T_in * torch.exp(log_T_incl[..., -1]))
    return n


def splat_tiles(
    projected: Projected, values_ND: Tensor, camera: Camera, tile_size: int = 16, chunk: int = 32
) -> Splatted:
    """Rasterize the visible Gaussians of ``projected`` tile by tile; see the module docstring.

    Args:
        projected: output of ``project_gaussians`` for ``camera``.
        values_ND: per-Gaussian channels to composite (colours, then features).
        camera: the view (its size sets the tile grid).
        tile_size: tile edge in pixels.
        chunk: Gaussians per tile list composited per step (K); smaller chunks stop sooner once tiles go opaque.
    """
    W, H, ts = camera.width, camera.height, tile_size
    ntx, nty = -(-W // ts), -(-H // ts)
    E = values_ND.shape[1] + 2
    out = [values_ND.new_zeros(ntx * nty, ts * ts, E)]

    def accumulate(active, _rows, w_APK, T_in, values_AKE):
        # T_in is constant along the chunk: apply it to the [A, P, E] sums rather than to every weight.
        out[0] = out[0].index_add(0, active, torch.bmm(w_APK, values_AKE) * T_in[:, :, None])

    n = _walk_tiles(projected, values_ND, camera, tile_size, chunk, accumulate)
    out_HWE = out[0].reshape(nty, ntx, ts, ts, E).permute(0, 2, 1, 3, 4).reshape(nty * ts, ntx * ts, E)[:H, :W]
    return Splatted(out_HWE[..., :-2], out_HWE[..., -2], out_HWE[..., -1], n)


def splat_weights(projected: Projected, camera: Camera, tile_size: int = 16, chunk: int = 32) -> Tensor:
    """The compositing weights w_{i,u} of every (pixel u, Gaussian i) as a sparse ``[H*W, N]`` matrix.

    With geometry fixed, any per-Gaussian channels render as ``W @ values`` (Eq. F_v(u) = sum_i w_iu f_i), which
    is how feature distillation optimises codes without re-rasterizing every step.
    """
    W, ts = camera.width, tile_size
    ntx = -(-W // ts)
    dev = projected.means2d_N2.device
    local = torch.arange(ts * ts, device=dev)
    parts: list[tuple[Tensor, Tensor, Tensor]] = []

    def collect(active, rows_AK, w_APK, T_in, _values):
        w = w_APK * T_in[:, :, None]
        px = (active[:, None] % ntx) * ts + local % ts
        py = (active[:, None] // ntx) * ts + local // ts
        a, pi, k = torch.nonzero(w > 0, as_tuple=True)
        parts.append((py[a, pi] * W + px[a, pi], rows_AK[a, k], w[a, pi, k]))

    with torch.no_grad():
        dummy = projected.depth_N.new_zeros(projected.depth_N.shape[0], 0)
        _walk_tiles(projected, dummy, camera, tile_size, chunk, collect)
    n_pix = camera.height * camera.width
    if not parts:
        return torch.sparse_coo_tensor(torch.zeros(2, 0, dtype=torch.long), [], (n_pix, projected.depth_N.shape[0]))
    pix, rows, w = (torch.cat(x) for x in zip(*parts, strict=True))
    return sorted_coo(pix, rows, w, (n_pix, projected.depth_N.shape[0]))


def sorted_coo(pix: Tensor, rows: Tensor, w: Tensor, shape: tuple[int, int]) -> Tensor:
    """The coalesced sparse matrix of entries ``(pix, rows) = w`` that are unique, as the tile walk's are (a pixel
    lies in one tile, a Gaussian once in a tile's list): a sort is all a coalesce would do, in about half its time
    on CPU (``python -m benchmarks distill``), the same tensor."""
    n = shape[1]
    key, order = torch.sort(pix * n + rows)
    return torch.sparse_coo_tensor(torch.stack([key // n, key % n]), w[order], shape, is_coalesced=True)
