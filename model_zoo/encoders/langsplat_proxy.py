"""``encoder/langsplat_proxy``: region-level "language" features, the stand-in for LangSplat's 3-d language Gaussians.

The paper's conference model (and the journal ablation's "Distillation ✗" arm) reads LangSplat features: CLIP
embeddings of SAM masks, constant over each mask, compressed per scene to 3 dims and frozen. Neither CLIP nor SAM
weights ship with gdwm (nothing is downloaded), so this encoder keeps what sets those features apart from the
foundation encoder's per-pixel ones, on CPU:

* regions, not pixels: a graph-based segmentation (Felzenszwalb, OpenCV contrib) stands in for SAM's masks, and the
  feature is constant over each region (LangSplat's mask-level features);
* a different descriptor than ``daisy``: per region, its mean and spread of colour (CIE Lab) and its
  magnitude-weighted gradient-orientation histogram, lifted by a fixed random orthogonal map to ``d_f`` and
  L2-normalised, as CLIP's region embedding is;
* the 3-d compression is the distill stage's ``feature_tokenizer=langsplat3`` (a scene-wise autoencoder, as
  LangSplat's).

It is a stand-in: its regions carry appearance statistics, not CLIP's open-vocabulary semantics.

Legend: ``H, W`` image size, ``R`` regions, ``D`` region descriptor length ``6 + bins + 2``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from model_zoo.encoders.base import EncoderSettings, FoundationEncoder
from model_zoo.encoders.daisy import orthogonal_projection
from model_zoo.registry import register


@dataclass
class LangSplatProxyConfig:
    d_f: int = 64
    """Output feature dimension (width of the fixed random orthogonal lift of the region descriptor)."""
    sigma: float = 0.5
    """Gaussian smoothing (px) before the graph segmentation."""
    k: float = 300.0
    """Scale of the graph segmentation: larger values give larger regions."""
    min_size: int = 20
    """Smallest region in pixels (smaller ones are merged into a neighbour)."""
    bins: int = 8
    """Gradient-orientation bins of the region descriptor (unsigned orientations over [0, pi))."""
    seed: int = 1
    """Seed of the fixed lift (differs from daisy's default, so the two never share a projection)."""


class LangSplatProxyEncoder(FoundationEncoder):
    """Frozen region encoder: ``encode(rgb [H, W, 3] uint8) -> [H, W, d_f]``, constant and unit-norm per region."""

    name = "langsplat_proxy"

    def __init__(self, cfg: LangSplatProxyConfig) -> None:
        super().__init__()
        if cfg.sigma < 0 or cfg.k <= 0 or min(cfg.min_size, cfg.bins, cfg.d_f) < 1:
            raise ValueError(f"langsplat_proxy: sigma >= 0, k > 0 and min_size, bins, d_f >= 1 required, got {cfg}")
        self.cfg = cfg
        self.d_f = cfg.d_f
        self.d_region = 6 + cfg.bins + 2
        self.register_buffer("proj", orthogonal_projection(self.d_region, cfg.d_f, cfg.seed), persistent=False)
        self.freeze()

    def regions(self, rgb_HW3: np.ndarray) -> np.ndarray:
        """``[H, W]`` int64 region ids ``0 .. R-1`` (the SAM-mask stand-in)."""
        # Created per call: OpenCV objects do not pickle, and encoders ship to Ray workers.
        seg = cv2.ximgproc.segmentation.createGraphSegmentation(self.cfg.sigma, self.cfg.k, self.cfg.min_size)
        labels = seg.processImage(np.ascontiguousarray(rgb_HW3[..., ::-1]))  # OpenCV images are BGR
        _, ids = np.unique(labels, return_inverse=True)
        return ids.reshape(labels.shape).astype(np.int64)

    def descriptors(self, rgb_HW3: np.ndarray, ids_HW: np.ndarray) -> np.ndarray:
        """``[R, D]`` region descriptors: Lab mean (centred on neutral grey) and spread, the normalised gradient-
        orientation histogram (centred on uniform), log mean gradient magnitude, and a constant channel."""
        r = int(ids_HW.max()) + 1
        ids = ids_HW.reshape(-1)
        count = np.bincount(ids, minlength=r).astype(np.float64)[:, None]
        lab = cv2.cvtColor(rgb_HW3, cv2.COLOR_RGB2LAB).reshape(-1, 3).astype(np.float64) / 255.0
        mean = np.stack([np.bincount(ids, lab[:, c], r) for c in range(3)], 1) / count
        sq = np.stack([np.bincount(ids, lab[:, c] ** 2, r) for c in range(3)], 1) / count
        std = np.sqrt(np.maximum(sq - mean**2, 0.0))
        gray = cv2.cvtColor(rgb_HW3, cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0
        gx, gy = cv2.Sobel(gray, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_64F, 0, 1, ksize=3)
        mag = np.hypot(gx, gy).reshape(-1)
        theta = np.mod(np.arctan2(gy, gx).reshape(-1), np.pi)
        b = np.minimum((theta / np.pi * self.cfg.bins).astype(np.int64), self.cfg.bins - 1)
        hist = np.bincount(ids * self.cfg.bins + b, mag, r * self.cfg.bins).reshape(r, self.cfg.bins)
        total = hist.sum(1, keepdims=True)
        hist = np.where(total > 1e-9, hist / np.maximum(total, 1e-9), 1.0 / self.cfg.bins) - 1.0 / self.cfg.bins
        mean_mag = np.log1p(total / count)
        const = np.full((r, 1), 0.1)
        return np.concatenate([mean - 0.5, std, hist, mean_mag, const], axis=1)

    def _encode(self, rgb_HW3: np.ndarray, out_hw: tuple[int, int]) -> torch.Tensor:
        ids_HW = self.regions(rgb_HW3)
        region_RC = F.normalize(torch.from_numpy(self.descriptors(rgb_HW3, ids_HW)).float() @ self.proj, dim=-1)
        if out_hw != ids_HW.shape:  # nearest: a region's feature stays constant, never blended across masks
            ids_HW = cv2.resize(ids_HW.astype(np.int32), (out_hw[1], out_hw[0]), interpolation=cv2.INTER_NEAREST)
        return region_RC[torch.from_numpy(ids_HW.astype(np.int64))]

    def valid_mask(self, H: int, W: int, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        """Every pixel belongs to a region."""
        return torch.ones((H, W) if out_hw is None else tuple(out_hw), dtype=torch.bool)


@register("encoder", "langsplat_proxy")
def build_langsplat_proxy(cfg: LangSplatProxyConfig | EncoderSettings | None = None) -> LangSplatProxyEncoder:
    """The LangSplat stand-in; ``LangSplatProxyConfig()`` is its CPU flavor."""
    if isinstance(cfg, EncoderSettings):  # the lift keeps its own seed, so it never shares daisy's projection
        cfg = LangSplatProxyConfig(d_f=cfg.d_f)
    return LangSplatProxyEncoder(LangSplatProxyConfig() if cfg is None else cfg)
