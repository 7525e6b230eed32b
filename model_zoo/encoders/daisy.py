"""``encoder/daisy``: dense DAISY descriptors (OpenCV contrib) projected to ``d_f`` -- the CPU foundation encoder.

On CPU, E_F is a real, frozen, deterministic dense descriptor. DAISY is computed on the grayscale image
at keypoints every ``step`` px (rows/columns ``0, step, 2*step, ...``), a constant "flatness" channel is appended
(so textureless patches get a defined direction instead of a zero vector), the ``[h, w, D + 1]`` map is multiplied
by a fixed random orthogonal matrix drawn from ``seed`` (data-independent, unlike PCA), upsampled bilinearly to
every pixel and L2-normalised per pixel. Its defaults are the tiny/CPU flavor, tuned for 160x90 images.

Legend: ``H, W`` image size, ``h, w`` keypoint grid size, ``D`` DAISY length ``(q_radius * q_theta + 1) * q_hist``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from model_zoo.encoders.base import EncoderSettings, FoundationEncoder, upsample_grid
from model_zoo.registry import register


@dataclass
class DaisyConfig:
    d_f: int = 64
    """Output feature dimension (width of the random orthogonal projection)."""
    step: int = 4
    """Keypoint grid spacing in pixels; descriptors are computed at rows/columns 0, step, 2*step, ..."""
    radius: float = 8.0
    """Radius of the DAISY sampling pattern in pixels; pixels whose grid neighbours are closer to the border are
    invalid."""
    q_radius: int = 2
    """Number of rings of histograms around the centre."""
    q_theta: int = 8
    """Number of histograms per ring."""
    q_hist: int = 8
    """Number of orientation bins per histogram."""
    flat_level: float = 0.02
    """Value of the appended constant channel: patches whose (unnormalised) DAISY norm is well below it read as
    flat. A 0..255 edge of full contrast gives a norm of about 1."""
    seed: int = 0
    """Seed of the fixed projection matrix."""


def orthogonal_projection(d_in: int, d_out: int, seed: int) -> torch.Tensor:
    """``[d_in, d_out]`` random matrix with orthonormal columns (rows when ``d_out > d_in``), Haar-distributed.

    Drawn from its own ``torch.Generator``, so it depends on ``seed`` only (never on data or the global RNG).
    """
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(max(d_in, d_out), min(d_in, d_out), generator=g, dtype=torch.float64)
    q, r = torch.linalg.qr(a)
    q = q * torch.sign(torch.diagonal(r))  # sign fix makes the QR factor unique, hence Haar
    return (q if d_in >= d_out else q.T).to(torch.float32)


class DaisyEncoder(FoundationEncoder):
    """Frozen dense DAISY encoder: ``encode(rgb [H, W, 3] uint8) -> [H, W, d_f]`` unit-norm float32."""

    name = "daisy"

    def __init__(self, cfg: DaisyConfig) -> None:
        super().__init__()
        if cfg.step < 1 or cfg.radius <= 0 or min(cfg.q_radius, cfg.q_theta, cfg.q_hist, cfg.d_f) < 1:
            raise ValueError(f"daisy: step, radius, q_radius, q_theta, q_hist and d_f must be positive, got {cfg}")
        self.cfg = cfg
        self.d_f = cfg.d_f
        self.d_daisy = (cfg.q_radius * cfg.q_theta + 1) * cfg.q_hist
        # Derived from cfg, so kept out of state_dicts.
        self.register_buffer("proj", orthogonal_projection(self.d_daisy + 1, cfg.d_f, cfg.seed), persistent=False)
        self.freeze()

    def grid_hw(self, H: int, W: int) -> tuple[int, int]:
        """Keypoint grid size ``(h, w)`` for an ``H x W`` image."""
        return (H - 1) // self.cfg.step + 1, (W - 1) // self.cfg.step + 1

    def descriptors(self, rgb_HW3: np.ndarray) -> torch.Tensor:
        """Raw DAISY descriptors on the keypoint grid, ``[h, w, D]`` float32."""
        gray = cv2.cvtColor(rgb_HW3, cv2.COLOR_RGB2GRAY)
        H, W = gray.shape
        h, w = self.grid_hw(H, W)
        s = self.cfg.step
        kps = [cv2.KeyPoint(float(x * s), float(y * s), 1.0) for y in range(h) for x in range(w)]
        # Created per call (about a microsecond): OpenCV objects do not pickle, and encoders ship to Ray workers.
        daisy = cv2.xfeatures2d.DAISY_create(
            radius=float(self.cfg.radius),
            q_radius=self.cfg.q_radius,
            q_theta=self.cfg.q_theta,
            q_hist=self.cfg.q_hist,
            norm=cv2.xfeatures2d.DAISY_NRM_NONE,  # keep contrast: flat patches fall back to the flatness channel
        )
        kept, desc = daisy.compute(gray, kps)
        if desc is None or len(kept) != h * w or desc.shape != (h * w, self.d_daisy):
            got = None if desc is None else desc.shape
            raise RuntimeError(f"daisy: OpenCV returned descriptors {got} for {h * w} keypoints on a {H}x{W} image")
        return torch.from_numpy(desc).reshape(h, w, self.d_daisy)

    def _encode(self, rgb_HW3: np.ndarray, out_hw: tuple[int, int]) -> torch.Tensor:
        H, W = rgb_HW3.shape[:2]
        desc_hwD = self.descriptors(rgb_HW3)
        flat_hw1 = torch.full((*desc_hwD.shape[:2], 1), self.cfg.flat_level, dtype=desc_hwD.dtype)
        grid_hwC = torch.cat([desc_hwD, flat_hw1], dim=-1) @ self.proj
        ry, rx = out_hw[0] / H, out_hw[1] / W
        # keypoint at image pixel k*step lands at output pixel (k*step + 0.5) * r - 0.5
        feat_HWC = upsample_grid(
            grid_hwC, out_hw, (0.5 * ry - 0.5, 0.5 * rx - 0.5), (self.cfg.step * ry, self.cfg.step * rx)
        )
        return F.normalize(feat_HWC, dim=-1, eps=1e-12)

    def _valid_1d(self, n_img: int, n_out: int) -> torch.Tensor:
        s, r = self.cfg.step, self.cfg.radius
        n_grid = (n_img - 1) // s + 1
        x = (torch.arange(n_out, dtype=torch.float64) + 0.5) * n_img / n_out - 0.5  # image coordinate
        g = (x / s).clamp(0, n_grid - 1)
        lo, hi = g.floor() * s, g.ceil() * s
        return (lo >= r) & (hi <= n_img - 1 - r)

    def valid_mask(self, H: int, W: int, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        """Pixels whose interpolating keypoints all lie at least ``radius`` px inside the image."""
        Ho, Wo = (H, W) if out_hw is None else out_hw
        return self._valid_1d(H, Ho)[:, None] & self._valid_1d(W, Wo)[None, :]


@register("encoder", "daisy")
def build_daisy(cfg: DaisyConfig | EncoderSettings | None = None) -> DaisyEncoder:
    """The DAISY encoder; ``DaisyConfig()`` is its tiny/CPU flavor."""
    if isinstance(cfg, EncoderSettings):
        cfg = DaisyConfig(d_f=cfg.d_f, seed=cfg.seed)
    return DaisyEncoder(DaisyConfig() if cfg is None else cfg)
