"""3D → 2D EWA projection of Gaussians (Zwicker et al. 2001, EWA splatting; Kerbl et al. 2023, 3DGS Eq. 5-6).

Legend: N Gaussians; ``means_N3`` world centres, ``scales_N3`` std devs, ``quats_N4`` (w, x, y, z),
``means2d_N2`` pixel coordinates, ``conic_N3`` the inverse 2D covariance as (a, b, c) = [[a, b], [b, c]],
``box_N4`` the inclusive pixel range (u0, u1, v0, v1) a Gaussian can touch. H x W images, D value channels.

The torch and dense backends share this file's projection, culling and constants, so they differ only in how they
composite; gsplat follows the same conventions (see ``gsplat_backend.py`` for where it differs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from model_zoo.quaternion import quat_to_rotmat
from model_zoo.render.camera import Camera

ALPHA_MIN = 1.0 / 255.0
"""A Gaussian whose alpha at a pixel is below this is skipped there (3DGS)."""
ALPHA_MAX = 0.99
"""Per-pixel alpha is clamped to this, so transmittance never hits 0 (3DGS; gsplat uses 0.999)."""
T_MIN = 1e-4
"""Front-to-back compositing stops before the Gaussian that would take transmittance below this (3DGS)."""
FOV_CLAMP = 0.3
"""The Jacobian is evaluated with x/z, y/z clamped to the image plus 0.3 x half its extent (3DGS, gsplat)."""


def covariance_3d(scales_N3: Tensor, quats_N4: Tensor) -> Tensor:
    """World covariance ``Sigma = R S S^T R^T`` (3DGS Eq. 6), ``[N, 3, 3]``."""
    M = quat_to_rotmat(quats_N4) * scales_N3[..., None, :]
    return M @ M.transpose(-1, -2)


@dataclass
class Projected:
    """Screen-space Gaussians for one camera; every field has one row per input Gaussian."""

    means2d_N2: Tensor
    conic_N3: Tensor
    depth_N: Tensor
    """Camera-frame z (differentiable w.r.t. the means)."""
    opacity_N: Tensor
    valid_N: Tensor
    """Inside (near, far), non-degenerate 2D covariance, opacity >= ALPHA_MIN: may contribute on the image plane."""
    visible_N: Tensor
    """Valid and its footprint box covers at least one pixel centre: the Gaussians that get rasterized."""
    box_N4: Tensor
    """Inclusive pixel range (u0, u1, v0, v1) of the footprint, clipped to the image (int64, no grad)."""


def project_gaussians(
    means_N3: Tensor, scales_N3: Tensor, quats_N4: Tensor, opacities_N: Tensor, camera: Camera, eps2d: float
) -> Projected:
    """EWA projection: ``Sigma' = J W Sigma W^T J^T + eps2d I`` (3DGS Eq. 5, with 3DGS's low-pass ``eps2d``).

    ``J`` is the Jacobian of the pinhole projection ``u = K [x/z, y/z, 1]`` at the camera-space mean ``t = W mean``.
    The footprint is the ellipse where ``o exp(-d^T conic d / 2) >= ALPHA_MIN``, i.e. ``k^2 = 2 ln(o / ALPHA_MIN)``
    standard deviations (<= 3.33 sigma; gsplat >= 1.5 bounds it the same way): outside it a Gaussian is skipped
    anyway, so binning by it loses nothing and every backend produces the same image.
    """
    K, w2c = camera.K_33, camera.world2cam_44
    R_w, t_w = w2c[:3, :3], w2c[:3, 3]
    t_N3 = means_N3 @ R_w.T + t_w
    z = t_N3[:, 2]
    z_ok = (z > camera.near) & (z < camera.far)
    # Culled rows still flow through autograd: keep them finite so their (zero) gradients stay 0, never NaN.
    z_safe = torch.where(z_ok, z, torch.ones_like(z))
    x, y = t_N3[:, 0], t_N3[:, 1]

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = (K[0, 0] * x + K[0, 1] * y) / z_safe + cx
    v = (K[1, 1] * y) / z_safe + cy
    means2d_N2 = torch.stack([u, v], dim=-1)

    tan_x, tan_y = 0.5 * camera.width / fx, 0.5 * camera.height / fy
    xz = torch.clamp(x / z_safe, -(cx / fx + FOV_CLAMP * tan_x), (camera.width - cx) / fx + FOV_CLAMP * tan_x)
    yz = torch.clamp(y / z_safe, -(cy / fy + FOV_CLAMP * tan_y), (camera.height - cy) / fy + FOV_CLAMP * tan_y)
    inv_z, zero = 1.0 / z_safe, torch.zeros_like(z_safe)
    Jp_N23 = torch.stack([inv_z, zero, -xz * inv_z, zero, inv_z, -yz * inv_z], dim=-1).reshape(-1, 2, 3)
    J_N23 = K[:2, :2] @ Jp_N23
    M_N33 = quat_to_rotmat(quats_N4) * scales_N3[:, None, :]
    TM_N23 = J_N23 @ R_w @ M_N33  # Sigma' - eps2d I = (J W R S)(J W R S)^T
    cov_N22 = TM_N23 @ TM_N23.transpose(-1, -2)
    a, b, c = cov_N22[:, 0, 0] + eps2d, cov_N22[:, 0, 1], cov_N22[:, 1, 1] + eps2d
    det = a * c - b * b
    det_ok = det > 0
    det_safe = torch.where(det_ok, det, torch.ones_like(det))
    conic_N3 = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    with torch.no_grad():
        valid = z_ok & det_ok & (opacities_N >= ALPHA_MIN)
        k = torch.sqrt(2.0 * torch.log(opacities_N.clamp(min=ALPHA_MIN) / ALPHA_MIN))
        # A hair of slack so rounding never drops a pixel whose alpha is exactly at the threshold.
        rx = k * torch.sqrt(a.clamp(min=0)) * (1 + 1e-4) + 1e-3
        ry = k * torch.sqrt(c.clamp(min=0)) * (1 + 1e-4) + 1e-3
        W, H = camera.width, camera.height
        # Pixel-centre index ranges in [-1, W] first, so a box entirely off one side reads as empty.
        u0 = torch.ceil((u - rx - 0.5).clamp(-1, W)).long()
        u1 = torch.floor((u + rx - 0.5).clamp(-1, W)).long()
        v0 = torch.ceil((v - ry - 0.5).clamp(-1, H)).long()
        v1 = torch.floor((v + ry - 0.5).clamp(-1, H)).long()
        hits = (u0 <= u1) & (u0 <= W - 1) & (u1 >= 0) & (v0 <= v1) & (v0 <= H - 1) & (v1 >= 0)
        visible = valid & hits
        box_N4 = torch.stack([u0.clamp(0, W - 1), u1.clamp(0, W - 1), v0.clamp(0, H - 1), v1.clamp(0, H - 1)], dim=-1)

    return Projected(means2d_N2, conic_N3, z, opacities_N, valid, visible, box_N4)


class Splatted(NamedTuple):
    """What a backend returns: sums over Gaussians of ``w_i * value`` and of ``w_i`` (no background)."""

    values_HWD: Tensor
    """``sum_i w_i v_i`` for the D value channels (colours, then features)."""
    depth_HW: Tensor
    """``sum_i w_i z_i`` (un-normalised)."""
    alpha_HW: Tensor
    """``sum_i w_i``."""
    n_visible: int
