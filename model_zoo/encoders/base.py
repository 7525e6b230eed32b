"""Frozen foundation encoder E_F (Eq. F_v = E_F(I_v), Sec. Foundation-feature Gaussian Tokenizer).

An encoder maps one RGB image to a dense feature map at the image's own resolution (or a requested one): it
describes the image on its native grid (DAISY keypoints every ``step`` px, Qwen3-VL patch tokens), and the grid is
upsampled bilinearly to every pixel, each grid value sitting at the pixel position it describes (see
:func:`upsample_grid`). Encoders are frozen (no parameter requires grad, always in eval mode) and deterministic.

Legend: ``H, W`` image size, ``h, w`` encoder grid size, ``C`` feature channels (``d_f``).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn


@dataclass
class EncoderSettings:
    """What a pipeline sets of whichever encoder it picks: ``registry.build("encoder", name, EncoderSettings(...))``.

    Each variant's builder takes the fields its own config has and keeps its defaults for the rest, so the caller
    never branches on the name; a variant's own config (``DaisyConfig``, ...) is still accepted for every knob.
    """

    d_f: int = 64
    """Feature dimension, for variants that choose theirs (a checkpoint fixes the Qwen tower's)."""
    seed: int = 0
    """Seed of the fixed random projection, for variants whose projection follows the run's seed."""
    path: str | None = None
    """Local checkpoint directory, for variants that load one."""
    tiny: bool = False
    """The variant's tiny random flavor (tests, smoke runs), for variants that have one."""


def as_rgb_uint8(rgb_HW3: np.ndarray | torch.Tensor, who: str) -> np.ndarray:
    """The image as a C-contiguous ``[H, W, 3]`` uint8 numpy array; anything else is an error naming ``who``."""
    shape = tuple(rgb_HW3.shape)
    dtype = rgb_HW3.dtype
    if len(shape) != 3 or shape[2] != 3 or dtype not in (np.uint8, torch.uint8) or shape[0] < 1 or shape[1] < 1:
        raise ValueError(f"{who}: expected an RGB image [H, W, 3] uint8, got shape {list(shape)} dtype {dtype}")
    if isinstance(rgb_HW3, torch.Tensor):
        rgb_HW3 = rgb_HW3.detach().cpu().numpy()
    return np.ascontiguousarray(rgb_HW3)


def interp_matrix(n_out: int, n_in: int, origin: float, stride: float) -> torch.Tensor:
    """``[n_out, n_in]`` linear-interpolation weights: grid sample ``k`` sits at output pixel ``origin + k * stride``.

    Output pixels outside the first/last sample take the border sample (clamped), as ``F.interpolate`` does.
    """
    pos = (torch.arange(n_out, dtype=torch.float64) - origin) / stride
    pos = pos.clamp(0, n_in - 1)
    lo = pos.floor().long()
    hi = (lo + 1).clamp(max=n_in - 1)
    frac = pos - lo
    m = torch.zeros(n_out, n_in, dtype=torch.float64)
    rows = torch.arange(n_out)
    m[rows, lo] += 1 - frac
    m[rows, hi] += frac
    return m


def upsample_grid(
    grid_hwC: torch.Tensor, out_hw: tuple[int, int], origin_yx: tuple[float, float], stride_yx: tuple[float, float]
) -> torch.Tensor:
    """Bilinear upsampling of a feature grid to ``[H, W, C]`` float32, separable and exact.

    Grid cell ``(i, j)`` describes output pixel ``(origin_y + i * stride_y, origin_x + j * stride_x)``. For patch
    tokens covering ``S``-pixel cells, ``origin = S / 2 - 0.5`` and ``stride = S`` reproduce
    ``F.interpolate(..., mode="bilinear", align_corners=False)``; for keypoints on pixels ``0, s, 2s, ...``,
    ``origin = 0`` and ``stride = s``.
    """
    H, W = out_hw
    h, w, _ = grid_hwC.shape
    my_Hh = interp_matrix(H, h, origin_yx[0], stride_yx[0]).to(grid_hwC.device, torch.float32)
    mx_Ww = interp_matrix(W, w, origin_yx[1], stride_yx[1]).to(grid_hwC.device, torch.float32)
    return torch.einsum("Hh,hwc,Ww->HWc", my_Hh, grid_hwC.to(torch.float32), mx_Ww)


class FoundationEncoder(nn.Module, abc.ABC):
    """E_F: a frozen, deterministic dense image encoder.

    Subclasses set ``name`` and ``d_f``, build their modules, call :meth:`freeze`, and implement :meth:`_encode`
    and :meth:`valid_mask`.
    """

    name: str
    """Registered variant name, used in error messages and provenance."""
    d_f: int
    """Feature dimension of the encoded map."""

    def freeze(self) -> FoundationEncoder:
        self.requires_grad_(False)
        return super().train(False)

    def train(self, mode: bool = True) -> FoundationEncoder:
        # A frozen encoder stays in eval mode even when a parent module is put in training mode.
        return super().train(False)

    @torch.no_grad()
    def encode(self, rgb_HW3: np.ndarray | torch.Tensor, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        """Dense features ``[H, W, d_f]`` float32 of an RGB uint8 image ``[H, W, 3]``.

        ``out_hw`` (default: the image size) renders the map at another resolution, e.g. the resolution the
        Gaussians are rendered at; a full-resolution map of a large ``d_f`` can be many GiB.
        """
        rgb = as_rgb_uint8(rgb_HW3, self.name)
        out_hw = (rgb.shape[0], rgb.shape[1]) if out_hw is None else (int(out_hw[0]), int(out_hw[1]))
        feat_HWC = self._encode(rgb, out_hw)
        assert feat_HWC.shape == (*out_hw, self.d_f) and feat_HWC.dtype == torch.float32, (
            f"{self.name}: encoder returned {tuple(feat_HWC.shape)} {feat_HWC.dtype}, expected {(*out_hw, self.d_f)}"
        )
        return feat_HWC

    def forward(self, rgb_HW3: np.ndarray | torch.Tensor, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        return self.encode(rgb_HW3, out_hw)

    def encode_views(self, rgb_VHW3: np.ndarray | torch.Tensor, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        """Stacked views ``[V, H, W, 3]`` -> ``[V, H, W, d_f]`` (one :meth:`encode` per view)."""
        return torch.stack([self.encode(rgb_VHW3[v], out_hw) for v in range(len(rgb_VHW3))])

    @abc.abstractmethod
    def _encode(self, rgb_HW3: np.ndarray, out_hw: tuple[int, int]) -> torch.Tensor:
        """Features ``[*out_hw, d_f]`` float32 of a validated ``[H, W, 3]`` uint8 image."""

    @abc.abstractmethod
    def valid_mask(self, H: int, W: int, out_hw: tuple[int, int] | None = None) -> torch.Tensor:
        """Bool ``[*out_hw]`` (default ``[H, W]``): where the map of an ``H x W`` image holds a defined feature."""
