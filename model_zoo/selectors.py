"""Coarse selectors, K_c of N Gaussians (Sec. Geometry-aware Gaussian Adapter, Driving-aware Coarse Selection).

Written here because no maintained library ranks Gaussians by a score and unions a global top-K with per-voxel bests.

Legend: ``N`` Gaussians, ``K`` candidates (``K_c``), ``T`` trajectory waypoints, ``V`` occupied voxels, ``R`` voxel
grid cells. Ties in any ranking go to the lower Gaussian index, so every selector is deterministic for fixed inputs.

Variants (``registry.build("selector", name, SelectorConfig(...))``): ``random``, ``topk_uniform`` and
``topk_uniform_similarity`` (conference version), ``voxel_topk`` (quality only) and ``driving_aware`` (the paper's).

The ego path P_traj of T_i (``SelectorConfig.path``): ``route`` waypoints come from ``route_path`` (the planned
route ahead of the ego), ``extrapolated`` ones from the past poses; the caller hands neither a recorded future pose
(the leakage policy of ``model_zoo.config.PathSource``).

Union rule of Eq. C: read literally, the top K_c of ``TopK(S, K_c) ∪ VoxelTopK(S, K_c)`` by S is ``TopK(S, K_c)``
whenever N >= K_c, so the voxel branch would never survive. By default (``coverage_first``) the VoxelTopK members are
kept first and TopK fills the remaining slots: every occupied voxel is covered when ``K_c >= V``, and the result is
the top K_c voxel bests when ``V >= K_c``. ``coverage_first=False`` gives the literal rule.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np
import torch

from model_zoo.config import SelectorConfig  # torch-free, so config composition never loads torch
from model_zoo.registry import register

logger = logging.getLogger("model_zoo.selectors")

# Above this many grid cells the voxel keys are compacted with torch.unique instead of a dense scatter table.
_DENSE_CELLS_PER_GAUSSIAN = 4
_DENSE_CELLS_MIN = 1 << 16
_LOW32 = 0xFFFFFFFF
_CHUNK = 1 << 17
_MIN_EXPONENT = -80.0
# TopK over at least this many keys thresholds on a strided sample of about _SAMPLE_SIZE keys first.
_SAMPLE_MIN = 1 << 17
_SAMPLE_SIZE = 1 << 16
_warned_no_trajectory = False


@dataclass
class SelectorInputs:
    """One scene's Gaussians in the ego frame (x forward, y left, z up, metres)."""

    xyz: torch.Tensor
    """[N, 3] centres."""
    scale: torch.Tensor
    """[N, 3] linear standard deviations (metres, > 0)."""
    rotation: torch.Tensor
    """[N, 4] quaternions wxyz, possibly not unit (their norm feeds rho_i)."""
    opacity: torch.Tensor
    """[N] opacity as a probability in [0, 1] (already sigma(o_i), not a logit)."""
    trajectory: torch.Tensor | None = None
    """[T, 2] ego path ahead as ground-plane waypoints (x, y): the planned route or the extrapolated past
    (``SelectorConfig.path``), never the recorded future; None or T = 0 means no trajectory prior."""
    similarity: torch.Tensor | None = None
    """[N] text-Gaussian similarity; only topk_uniform_similarity reads it."""


@dataclass
class Selection:
    """``K_c`` candidate slots: real candidates first (descending score), then padding."""

    index: torch.Tensor
    """[K_c] int64 indices into the N Gaussians; padding slots hold 0."""
    mask: torch.Tensor
    """[K_c] bool, True = a real candidate, False = an invalid (padding) token."""


class Selector(Protocol):
    """What ``registry.build("selector", name, cfg)`` returns."""

    cfg: SelectorConfig
    needs_trajectory: bool
    needs_similarity: bool

    def __call__(self, g: SelectorInputs, generator: torch.Generator | None = None) -> Selection: ...


# ---------------------------------------------------------------------------------------------------------------------
# Scores (pure functions)


def rotation_validity(rotation_N4: torch.Tensor) -> torch.Tensor:
    """Eq. rho_i (Sec. Geometry-aware Gaussian Adapter): ``1 / (1 + | ||r_i||_2 - 1 |)``, 1 for a unit quaternion."""
    r = rotation_N4.unbind(dim=-1)  # column by column: ~2x faster than vector_norm over the last dim
    sq = (r[0] * r[0]).addcmul_(r[1], r[1]).addcmul_(r[2], r[2]).addcmul_(r[3], r[3])
    return sq.sqrt_().sub_(1).abs_().add_(1).reciprocal_()


def minmax_normalize(x_N: torch.Tensor) -> torch.Tensor:
    """Norm_[0,1] of Eq. Q_i: min-max normalisation within the scene; a constant (or empty) input gives zeros.

    ``quality_score`` inlines it to reuse the extremes for its finiteness check.
    """
    if x_N.numel() == 0:
        return x_N.clone()
    lo, hi = torch.aminmax(x_N)
    span = hi - lo
    if span <= 0:
        return torch.zeros_like(x_N)
    return (x_N - lo).div_(span)


def quality_score(scale_N3: torch.Tensor, rotation_N4: torch.Tensor, opacity_N: torch.Tensor) -> torch.Tensor:
    """Eq. Q_i (Sec. Geometry-aware Gaussian Adapter): ``Norm_[0,1](log(1 + sigma(o_i) (||s_i||_1 + 1) rho_i))``.

    ``opacity_N`` is already the probability ``sigma(o_i)`` (the Gaussian field stores activated opacities), so it
    enters as is; ``scale_N3`` holds the linear standard deviations ``s_i``.
    """
    s = scale_N3.unbind(dim=-1)
    raw = s[0].abs().add_(s[1].abs()).add_(s[2].abs()).add_(1).mul_(opacity_N).mul_(rotation_validity(rotation_N4))
    raw.log1p_()
    if raw.numel() == 0:
        return raw
    lo, hi = torch.aminmax(raw)  # NaN and inf reach the extremes: no separate isfinite pass
    if not bool(torch.isfinite(lo) & torch.isfinite(hi)):
        bad = int((~torch.isfinite(raw)).sum())
        raise ValueError(
            f"quality_score: {bad} of {raw.numel()} Gaussians have a non-finite opacity, scale or rotation"
        )
    return raw.sub_(lo).div_(hi - lo) if hi > lo else raw.zero_()


def trajectory_distance(xyz_N3: torch.Tensor, trajectory_T2: torch.Tensor | None) -> torch.Tensor:
    """Eq. d_i^traj (Sec. Geometry-aware Gaussian Adapter): ``min_j || pi_xy(x_i) - p_j ||_2``.

    A running minimum over the (few) waypoints, so no ``[N, T]`` matrix is built. With no waypoint (None or
    ``T = 0``) the minimum over the empty set is ``+inf`` for every Gaussian, hence ``T_i = 0``.
    """
    n = xyz_N3.shape[0]
    if trajectory_T2 is None or trajectory_T2.shape[0] == 0:
        return torch.full((n,), math.inf, dtype=xyz_N3.dtype, device=xyz_N3.device)
    x_N, y_N = xyz_N3[:, 0].contiguous(), xyz_N3[:, 1].contiguous()  # (a transpose copy of [N, 3] is 5x slower)
    waypoints = trajectory_T2.to(dtype=xyz_N3.dtype).tolist()
    best_N = torch.empty_like(x_N)
    # Chunks small enough for the cache: 5 passes per waypoint over an L2-resident slice, not over all of N.
    for c in range(0, n, _CHUNK):
        x, y, best = x_N[c : c + _CHUNK], y_N[c : c + _CHUNK], best_N[c : c + _CHUNK]
        dx, dy = torch.empty_like(x), torch.empty_like(y)
        for j, (px, py) in enumerate(waypoints):
            torch.sub(x, px, out=dx).mul_(dx).addcmul_(torch.sub(y, py, out=dy), dy)
            if j == 0:
                best.copy_(dx)
            else:
                torch.minimum(best, dx, out=best)
    return best_N.sqrt_()


def route_path(route_P2: np.ndarray, ego2world_44: np.ndarray, ahead_m: float, step_m: float = 1.0) -> np.ndarray:
    """P_traj for ``path=route``: ``[T, 2]`` waypoints every ``step_m`` metres along the planned route, from the
    ego's projection onto it up to ``ahead_m`` metres ahead, in the ego frame (x forward, y left).

    ``route_P2`` is the route as a world-frame ground-plane polyline in driving order (navigation: a lane or road
    centreline, from the map, not from the ego's motion). The waypoints are shifted sideways by the ego's own offset
    from the route, so they run through the ego and follow the road in its current lane. Only the current pose
    ``ego2world_44`` places the route: nothing the ego does later enters.
    """
    pts = np.asarray(route_P2, dtype=np.float64).reshape(-1, 2)
    if len(pts) >= 2:
        pts = pts[np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]]  # no zero-length segments
    if len(pts) < 2 or not np.isfinite(pts).all():
        raise ValueError(f"route_path: the route needs >= 2 distinct finite points, got {len(pts)}")
    if ahead_m <= 0 or step_m <= 0:
        raise ValueError(f"route_path: ahead_m and step_m must be > 0 metres, got {ahead_m}, {step_m}")
    world_to_ego = np.linalg.inv(np.asarray(ego2world_44, dtype=np.float64))
    pts = pts @ world_to_ego[:2, :2].T + world_to_ego[:2, 3]  # the ground-plane part of the pose
    seg_S2 = np.diff(pts, axis=0)
    length_S = np.linalg.norm(seg_S2, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(length_S)])
    normal_S2 = np.stack([-seg_S2[:, 1], seg_S2[:, 0]], axis=1) / length_S[:, None]  # left of the driving direction
    t_S = np.clip(-(pts[:-1] * seg_S2).sum(1) / length_S**2, 0.0, 1.0)  # the ego sits at the ego-frame origin
    foot_S2 = pts[:-1] + t_S[:, None] * seg_S2
    j = int(np.argmin(np.linalg.norm(foot_S2, axis=1)))
    offset = -float(foot_S2[j] @ normal_S2[j])
    s_T = arc[j] + t_S[j] * length_S[j] + np.arange(0.0, ahead_m + 1e-9, step_m)
    s_T = s_T[s_T <= arc[-1] + 1e-9]
    k_T = np.clip(np.searchsorted(arc, s_T, side="right") - 1, 0, len(seg_S2) - 1)
    frac_T = (s_T - arc[k_T]) / length_S[k_T]
    return (pts[k_T] + frac_T[:, None] * seg_S2[k_T] + offset * normal_S2[k_T]).astype(np.float32)


def trajectory_relevance(distance_N: torch.Tensor, sigma_traj: float) -> torch.Tensor:
    """Eq. T_i (Sec. Geometry-aware Gaussian Adapter): ``exp(-(d_i^traj)^2 / (2 sigma_traj^2))``.

    The exponent is clamped at -80, so ``T_i >= 1.8e-35`` (reached beyond ``12.6 sigma_traj``, and for ``d = inf``):
    float32 ``exp`` underflowing to denormals or zero is ~50x slower on x86 CPUs, denormals slow every later pass,
    and ``S_i`` cannot tell the clamped value from the exact one unless ``Q_i`` is below ~1e-28.
    """
    if sigma_traj <= 0:
        raise ValueError(f"trajectory_relevance: sigma_traj must be > 0 metres, got {sigma_traj}")
    return distance_N.square().div_(-2.0 * sigma_traj**2).clamp_(min=_MIN_EXPONENT).exp_()


def driving_score(quality_N: torch.Tensor, relevance_N: torch.Tensor, w_q: float, w_t: float) -> torch.Tensor:
    """Eq. S_i (Sec. Geometry-aware Gaussian Adapter): ``(w_q Q_i + w_t T_i) / (w_q + w_t)``."""
    if w_q < 0 or w_t < 0 or w_q + w_t <= 0:
        raise ValueError(f"driving_score: w_q and w_t must be >= 0 with w_q + w_t > 0, got w_q={w_q}, w_t={w_t}")
    return (quality_N * w_q).add_(relevance_N * w_t).div_(w_q + w_t)


# ---------------------------------------------------------------------------------------------------------------------
# Branches of Eq. C (pure functions)


def _rank_key(score_N: torch.Tensor, index_N: torch.Tensor | None = None) -> torch.Tensor:
    """Unique int64 key, larger = better: the float32 score's order-preserving bits over the reversed index."""
    n = score_N.shape[0]
    if n >= 1 << 32:
        raise ValueError(f"selectors: rank keys hold at most 2^32 - 1 Gaussians, got {n}")
    score_N = score_N.to(torch.float32).contiguous()
    bits = score_N.view(torch.int32)
    if n and bool(bits.min() < 0):  # a sign bit is set: flip magnitude bits so that int order equals float order
        bits = (score_N + 0.0).view(torch.int32)  # -0.0 + 0.0 = +0.0: equal scores must tie
        bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)
    if index_N is None:
        low = torch.arange(_LOW32, _LOW32 - n, -1, device=score_N.device)
    else:
        low = _LOW32 - index_N
    return torch.add(low, bits.to(torch.int64), alpha=1 << 32)  # bits * 2^32 + low: 3 passes instead of 5


def _key_index(key: torch.Tensor) -> torch.Tensor:
    return _LOW32 - (key & _LOW32)


def _top_by_key(key_M: torch.Tensor, k: int) -> torch.Tensor:
    """Positions of the ``k`` largest (unique) keys, best first.

    On large inputs a strided sample gives a threshold that about ``1.2 k`` keys pass; when at least ``k`` do, the
    exact top ``k`` are among them, so one compare pass and a small topk replace a full topk (4x faster at 1M).
    """
    m = key_M.shape[0]
    k = min(k, m)
    if k == 0:
        return torch.empty(0, dtype=torch.int64, device=key_M.device)
    if m >= _SAMPLE_MIN and m >= 8 * k:
        stride = m // _SAMPLE_SIZE
        sample = key_M[::stride]
        rank = min(sample.shape[0], int(1.2 * k / stride) + 32)
        threshold = torch.topk(sample, rank, sorted=False).values.min()
        passed = torch.nonzero(key_M >= threshold).squeeze(1)
        if passed.shape[0] >= k:  # else (an unlucky sample): the full topk below
            return passed[torch.topk(key_M[passed], k, sorted=True).indices]
    return torch.topk(key_M, k, sorted=True).indices


def topk_indices(score_N: torch.Tensor, k: int) -> torch.Tensor:
    """TopK of Eq. C (Sec. Geometry-aware Gaussian Adapter): the ``min(k, N)`` best indices, descending score.

    Ties go to the lower index.
    """
    return _top_by_key(_rank_key(score_N), k)


def voxel_ids(xyz_N3: torch.Tensor, voxel_size: float) -> tuple[torch.Tensor, int]:
    """Voxel of each Gaussian on the grid ``floor(x / voxel_size)`` (anchored at the ego origin), ids in ``[0, R)``.

    Ids index the bounding box of occupied cells when it is small (a dense table, no sort); otherwise they are
    compacted to the ``V`` occupied voxels with ``torch.unique``. Returns ``(ids_N, R)``.
    """
    n = xyz_N3.shape[0]
    if n == 0:
        return torch.empty(0, dtype=torch.int64, device=xyz_N3.device), 0
    # Column by column: reductions over contiguous columns are ~3x faster than aminmax(dim=0) of [N, 3].
    cell = [torch.floor(c / voxel_size) for c in xyz_N3.unbind(dim=-1)]
    bounds = torch.stack([torch.stack(torch.aminmax(c)) for c in cell])
    if not bool(torch.isfinite(bounds).all()):
        bad = int((~torch.isfinite(xyz_N3)).any(dim=1).sum())
        raise ValueError(f"voxel_ids: {bad} of {n} Gaussian centres are not finite")
    (lo0, hi0), (lo1, hi1), (lo2, hi2) = bounds.tolist()
    dims = [int(hi0 - lo0) + 1, int(hi1 - lo1) + 1, int(hi2 - lo2) + 1]
    cells = math.prod(dims)
    for c, lo in zip(cell, (lo0, lo1, lo2), strict=True):
        c.sub_(lo)
    if cells <= max(_DENSE_CELLS_PER_GAUSSIAN * n, _DENSE_CELLS_MIN) and cells < 1 << 24:
        # Exact in float32 below 2^24, and cheaper than three int64 casts.
        ids = cell[0].mul_(dims[1]).add_(cell[1]).mul_(dims[2]).add_(cell[2])
        return ids.to(torch.int64), cells
    c = [x.to(torch.int64) for x in cell]
    ids = (c[0] * dims[1] + c[1]) * dims[2] + c[2]  # cannot overflow int64 for any metric scene
    _, ids = torch.unique(ids, return_inverse=True)
    return ids, int(ids.max()) + 1


def _voxel_best_keys(ids_N: torch.Tensor, cells: int, key_N: torch.Tensor) -> torch.Tensor:
    """Rank key of the best Gaussian of every occupied voxel, ``[V]`` in voxel-id order."""
    floor = torch.iinfo(torch.int64).min
    best_R = torch.full((cells,), floor, dtype=torch.int64, device=key_N.device)
    best_R.scatter_reduce_(0, ids_N, key_N, reduce="amax")
    return best_R[best_R != floor]


def voxel_topk_indices(xyz_N3: torch.Tensor, score_N: torch.Tensor, k: int, voxel_size: float) -> torch.Tensor:
    """VoxelTopK of Eq. C (Sec. Geometry-aware Gaussian Adapter): best Gaussian per occupied voxel, then the top ``k``.

    Ties go to the lower index. Returns up to ``min(k, V)`` indices, descending score.
    """
    ids_N, cells = voxel_ids(xyz_N3, voxel_size)
    best_V = _voxel_best_keys(ids_N, cells, _rank_key(score_N))
    return _key_index(best_V[_top_by_key(best_V, k)])


def uniform_spatial_indices(
    xyz_N3: torch.Tensor,
    k: int,
    voxel_size: float,
    generator: torch.Generator | None = None,
    candidates: torch.Tensor | None = None,
) -> torch.Tensor:
    """Uniform spatial sampling of the conference selector: one random Gaussian per randomly ordered occupied voxel.

    Rounds repeat over the voxels (a voxel drops out once it has no unpicked Gaussian) until ``k`` are drawn or the
    pool is empty. ``candidates`` restricts the pool (default: all N). Returns up to ``k`` indices in draw order.
    """
    pool = torch.arange(xyz_N3.shape[0], device=xyz_N3.device) if candidates is None else candidates
    m = pool.shape[0]
    if m == 0 or k <= 0:
        return torch.empty(0, dtype=torch.int64, device=xyz_N3.device)
    ids, _ = voxel_ids(xyz_N3[pool], voxel_size)
    _, ids = torch.unique(ids, return_inverse=True)
    v = int(ids.max()) + 1
    dev = pool.device if generator is None else generator.device  # a CPU generator may drive a CUDA scene
    perm = torch.randperm(m, generator=generator, device=dev).to(pool.device)
    shuffled = perm[torch.argsort(ids[perm], stable=True)]  # grouped by voxel, random order inside each
    counts = torch.bincount(ids, minlength=v)
    starts = torch.cumsum(counts, 0) - counts
    vid_sorted = ids[shuffled]
    round_sorted = torch.arange(m, device=pool.device) - starts[vid_sorted]
    voxel_rank = torch.randperm(v, generator=generator, device=dev).to(pool.device)
    order_key = round_sorted * v + voxel_rank[vid_sorted]
    take = torch.topk(order_key, min(k, m), largest=False, sorted=True).indices
    return pool[shuffled[take]]


def union_truncate_pad(
    score_N: torch.Tensor, k_c: int, branches: Sequence[torch.Tensor], keep_first: torch.Tensor | None = None
) -> Selection:
    """The union and truncation of Eq. C (Sec. Geometry-aware Gaussian Adapter), padded to ``K_c`` slots.

    ``C = keep_first ∪ branches``; if it has more than ``K_c`` members the top-ranked by ``score_N`` are kept, with
    every member of ``keep_first`` ranked ahead of the rest (the voxel-coverage guarantee; the top ``K_c`` of
    ``keep_first`` itself when it alone is larger). Output: descending score (ties: lower index), then invalid tokens
    (index 0, mask False) with a warning naming N and K_c when fewer than ``K_c`` are available.
    """
    device = score_N.device
    n = score_N.shape[0]
    parts = [b.reshape(-1).to(device=device, dtype=torch.int64) for b in branches]
    first = torch.empty(0, dtype=torch.int64, device=device) if keep_first is None else keep_first.to(device)
    first = torch.unique(first)
    rest = torch.unique(torch.cat(parts)) if parts else first[:0]
    if first.numel() and rest.numel():
        in_first = torch.zeros(n, dtype=torch.bool, device=device)
        in_first[first] = True
        rest = rest[~in_first[rest]]
    first_key = _rank_key(score_N[first], first)
    if first_key.shape[0] > k_c:
        first_key = first_key[_top_by_key(first_key, k_c)]
    rest_key = _rank_key(score_N[rest], rest)
    if rest_key.shape[0] > k_c - first_key.shape[0]:
        rest_key = rest_key[_top_by_key(rest_key, k_c - first_key.shape[0])]
    kept_key = torch.sort(torch.cat([first_key, rest_key]), descending=True).values  # one sort of <= K_c keys
    return _pad(_key_index(kept_key), k_c, n)


def _pad(index: torch.Tensor, k_c: int, n: int) -> Selection:
    found = index.shape[0]
    if found < k_c:
        logger.warning(
            "coarse selection: %d candidate(s) for K_c=%d from N=%d Gaussians; padding %d invalid token(s)",
            found,
            k_c,
            n,
            k_c - found,
        )
    out = torch.zeros(k_c, dtype=torch.int64, device=index.device)
    out[:found] = index
    mask = torch.zeros(k_c, dtype=torch.bool, device=index.device)
    mask[:found] = True
    return Selection(out, mask)


# ---------------------------------------------------------------------------------------------------------------------
# Registered variants


def _check(g: SelectorInputs, who: str) -> int:
    n = g.xyz.shape[0] if g.xyz.ndim == 2 else -1
    shapes = {"xyz": (g.xyz, (n, 3)), "scale": (g.scale, (n, 3)), "rotation": (g.rotation, (n, 4))}
    shapes["opacity"] = (g.opacity, (n,))
    if g.similarity is not None:
        shapes["similarity"] = (g.similarity, (n,))
    for field, (t, want) in shapes.items():
        if n < 0 or tuple(t.shape) != want:
            got = {k: list(v[0].shape) for k, v in shapes.items()}
            raise ValueError(f"selector '{who}': inputs must be xyz [N, 3], scale [N, 3], rotation [N, 4], "
                             f"opacity [N] (and similarity [N]); got {got} ({field} is off)")  # fmt: skip
    if g.trajectory is not None and (g.trajectory.ndim != 2 or g.trajectory.shape[1] != 2):
        raise ValueError(f"selector '{who}': trajectory must be [T, 2] ground-plane waypoints, "
                         f"got {list(g.trajectory.shape)}")  # fmt: skip
    return n


def _generator(cfg: SelectorConfig, generator: torch.Generator | None, device: torch.device) -> torch.Generator:
    return generator if generator is not None else torch.Generator(device=device).manual_seed(cfg.seed)


@dataclass
class RandomSelector:
    """``random``: K_c Gaussians uniformly at random without replacement, in draw order."""

    cfg: SelectorConfig
    needs_trajectory: ClassVar[bool] = False
    needs_similarity: ClassVar[bool] = False

    def __call__(self, g: SelectorInputs, generator: torch.Generator | None = None) -> Selection:
        n = _check(g, self.cfg.name)
        gen = _generator(self.cfg, generator, g.xyz.device)
        index = torch.randperm(n, generator=gen, device=gen.device)[: self.cfg.k_c].to(g.xyz.device)
        return _pad(index, self.cfg.k_c, n)


@dataclass
class TopKUniformSelector:
    """``topk_uniform(_similarity)``, the conference selector: ranked top-K plus uniform spatial sampling.

    Budget of K_c: ``round(K_c * uniform_fraction)`` by uniform spatial sampling, the rest ranked; with similarity,
    ``round(K_c * similarity_fraction)`` of the ranked share go to top text-Gaussian similarity, the remainder to top
    Q_i. The branches are drawn disjoint (similarity, then Q, then uniform among the unpicked), so K_c are filled
    whenever N >= K_c. Output ordered by Q_i.
    """

    cfg: SelectorConfig
    use_similarity: bool = False
    needs_trajectory: ClassVar[bool] = False

    @property
    def needs_similarity(self) -> bool:
        return self.use_similarity

    def __post_init__(self) -> None:
        if self.use_similarity and self.cfg.similarity_fraction > 1 - self.cfg.uniform_fraction:
            raise ValueError(
                f"selector '{self.cfg.name}': similarity_fraction ({self.cfg.similarity_fraction}) must fit in the "
                f"ranked share 1 - uniform_fraction ({1 - self.cfg.uniform_fraction})"
            )

    def __call__(self, g: SelectorInputs, generator: torch.Generator | None = None) -> Selection:
        cfg = self.cfg
        if self.use_similarity and g.similarity is None:
            raise ValueError(
                f"selector '{cfg.name}' needs SelectorInputs.similarity ([N] text-Gaussian similarity), got None"
            )
        n = _check(g, cfg.name)
        q_N = quality_score(g.scale, g.rotation, g.opacity)
        k_ranked = cfg.k_c - round(cfg.k_c * cfg.uniform_fraction)
        taken = torch.zeros(n, dtype=torch.bool, device=g.xyz.device)
        branches = []
        if self.use_similarity:
            k_sim = min(round(cfg.k_c * cfg.similarity_fraction), k_ranked)
            branches.append(topk_indices(g.similarity.to(g.xyz.device), k_sim))
            taken[branches[-1]] = True
            k_ranked -= branches[-1].shape[0]
        key_N = _rank_key(q_N).masked_fill_(taken, torch.iinfo(torch.int64).min)
        branches.append(_top_by_key(key_N, min(k_ranked, n - int(taken.sum()))))
        taken[branches[-1]] = True
        k_uniform = cfg.k_c - sum(b.shape[0] for b in branches)
        gen = _generator(cfg, generator, g.xyz.device)
        pool = torch.nonzero(~taken).squeeze(1)
        branches.append(uniform_spatial_indices(g.xyz, k_uniform, cfg.voxel_size, gen, candidates=pool))
        return union_truncate_pad(q_N, cfg.k_c, branches)


def _topk_voxel_union(g: SelectorInputs, score_N: torch.Tensor, cfg: SelectorConfig) -> Selection:
    """Eq. C from one rank key (shared by both branches: it is the costliest pass after the scores)."""
    key_N = _rank_key(score_N)
    top = _key_index(key_N[_top_by_key(key_N, cfg.k_c)])
    best_V = _voxel_best_keys(*voxel_ids(g.xyz, cfg.voxel_size), key_N)
    vox = _key_index(best_V[_top_by_key(best_V, cfg.k_c)])
    if cfg.coverage_first:
        return union_truncate_pad(score_N, cfg.k_c, [top], keep_first=vox)
    return union_truncate_pad(score_N, cfg.k_c, [top, vox])


@dataclass
class VoxelTopKSelector:
    """``voxel_topk``: ``TopK(Q, K_c) ∪ VoxelTopK(Q, K_c)`` on the intrinsic quality alone."""

    cfg: SelectorConfig
    needs_trajectory: ClassVar[bool] = False
    needs_similarity: ClassVar[bool] = False

    def __call__(self, g: SelectorInputs, generator: torch.Generator | None = None) -> Selection:
        _check(g, self.cfg.name)
        return _topk_voxel_union(g, quality_score(g.scale, g.rotation, g.opacity), self.cfg)


@dataclass
class DrivingAwareSelector:
    """``driving_aware`` (Eq. C): ``TopK(S, K_c) ∪ VoxelTopK(S, K_c)`` with S_i mixing Q_i and trajectory relevance.

    The path comes from ``cfg.path``: ``route``, the planned route ahead (``route_path``), or ``extrapolated``, the
    past ego positions carried on at constant velocity; the caller builds it from the current and past poses and the
    dataset's route only, never from recorded future poses (``PathSource``). Without a trajectory (None or zero
    waypoints) T_i = 0 for every Gaussian, so S_i = w_q Q_i / (w_q + w_t) and the ranking is that of Q_i; a warning
    is logged once per process.
    """

    cfg: SelectorConfig
    needs_trajectory: ClassVar[bool] = True
    needs_similarity: ClassVar[bool] = False

    def score(self, g: SelectorInputs) -> torch.Tensor:
        """S_i of every Gaussian."""
        global _warned_no_trajectory
        cfg = self.cfg
        q_N = quality_score(g.scale, g.rotation, g.opacity)
        if g.trajectory is None or g.trajectory.shape[0] == 0:
            if not _warned_no_trajectory:
                logger.warning("selector '%s': no trajectory given, so T_i = 0 and S_i ranks by Q_i alone", cfg.name)
                _warned_no_trajectory = True
            t_N = torch.zeros_like(q_N)
        else:
            t_N = trajectory_relevance(trajectory_distance(g.xyz, g.trajectory), cfg.sigma_traj)
        return driving_score(q_N, t_N, cfg.w_q, cfg.w_t)

    def __call__(self, g: SelectorInputs, generator: torch.Generator | None = None) -> Selection:
        _check(g, self.cfg.name)
        return _topk_voxel_union(g, self.score(g), self.cfg)


@register("selector", "random")
def build_random(cfg: SelectorConfig) -> RandomSelector:
    return RandomSelector(cfg)


@register("selector", "topk_uniform")
def build_topk_uniform(cfg: SelectorConfig) -> TopKUniformSelector:
    return TopKUniformSelector(cfg)


@register("selector", "topk_uniform_similarity")
def build_topk_uniform_similarity(cfg: SelectorConfig) -> TopKUniformSelector:
    return TopKUniformSelector(cfg, use_similarity=True)


@register("selector", "voxel_topk")
def build_voxel_topk(cfg: SelectorConfig) -> VoxelTopKSelector:
    return VoxelTopKSelector(cfg)


@register("selector", "driving_aware")
def build_driving_aware(cfg: SelectorConfig) -> DrivingAwareSelector:
    return DrivingAwareSelector(cfg)


# ---------------------------------------------------------------------------------------------------------------------
# Reference


def driving_aware_reference(g: SelectorInputs, cfg: SelectorConfig) -> np.ndarray:
    """The straightforward driving_aware selector (numpy + a python dict of voxels): the oracle of tests and benchmark.

    Same equations and tie rule (lower index first) as ``driving_aware``, in float32 like the torch path; returns the
    selected indices in output order (descending S_i), without padding.
    """
    xyz = g.xyz.detach().cpu().numpy().astype(np.float32)
    scale = g.scale.detach().cpu().numpy().astype(np.float32)
    rot = g.rotation.detach().cpu().numpy().astype(np.float32)
    opa = g.opacity.detach().cpu().numpy().astype(np.float32)
    n = xyz.shape[0]
    rho = 1 / (1 + np.abs(np.sqrt((rot * rot).sum(axis=1)) - 1))
    raw = np.log1p(opa * (np.abs(scale[:, 0]) + np.abs(scale[:, 1]) + np.abs(scale[:, 2]) + 1) * rho)
    span = raw.max() - raw.min() if n else 0
    q = (raw - raw.min()) / span if span > 0 else np.zeros(n, np.float32)
    d = np.full(n, np.inf, np.float32)
    traj = [] if g.trajectory is None else g.trajectory.detach().cpu().numpy().astype(np.float32)
    for p in traj:
        d = np.minimum(d, np.sqrt((xyz[:, 0] - p[0]) ** 2 + (xyz[:, 1] - p[1]) ** 2))
    t = np.exp(d**2 / np.float32(-2 * cfg.sigma_traj**2))
    s = ((cfg.w_q * q + cfg.w_t * t) / (cfg.w_q + cfg.w_t)).astype(np.float32)

    def rank(i: int) -> tuple[float, int]:
        return (-float(s[i]), i)

    top = sorted(range(n), key=rank)[: cfg.k_c]
    best: dict[tuple[int, int, int], int] = {}
    cells = np.floor(xyz / np.float32(cfg.voxel_size)).astype(np.int64)
    for i in range(n):
        cell = tuple(cells[i])
        if cell not in best or rank(i) < rank(best[cell]):
            best[cell] = i
    vox = sorted(best.values(), key=rank)[: cfg.k_c]
    if cfg.coverage_first:
        chosen = set(vox)
        kept = vox + [i for i in top if i not in chosen][: cfg.k_c - len(vox)]
    else:
        kept = sorted(set(top) | set(vox), key=rank)[: cfg.k_c]
    return np.array(sorted(kept, key=rank), dtype=np.int64)
