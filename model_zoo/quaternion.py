"""Unit quaternions (w, x, y, z) in torch: the Hamilton product and rotation matrices, for the rasterizer and the
reconstruction's per-instance poses. (``pipelines.data.layout`` keeps its numpy pair: the data layer imports no
model code.)"""

from __future__ import annotations

import torch
from torch import Tensor


def quat_mul(a_N4: Tensor, b_N4: Tensor) -> Tensor:
    """Hamilton product ``a * b`` row by row (``[N, 4]`` each, or broadcastable)."""
    w1, x1, y1, z1 = a_N4.unbind(-1)
    w2, x2, y2, z2 = b_N4.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def quat_to_rotmat(quats_N4: Tensor) -> Tensor:
    """Rotation matrices ``R_N33`` from (w, x, y, z) quaternions, normalised here."""
    w, x, y, z = torch.nn.functional.normalize(quats_N4, dim=-1).unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )  # fmt: skip
    return R.reshape(*quats_N4.shape[:-1], 3, 3)
