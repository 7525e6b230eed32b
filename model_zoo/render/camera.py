"""A pinhole camera for the rasterizer (OpenCV convention).

Legend: ``K_33`` intrinsics in pixels, ``world2cam_44`` a rigid world→camera transform.
Camera frame: x right, y down, z forward; the centre of pixel (u, v) is at (u + 0.5, v + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class Camera:
    """One view: intrinsics, extrinsics, image size and the clipping planes (camera-z, metres)."""

    K_33: torch.Tensor
    """Intrinsics in pixels ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``."""
    world2cam_44: torch.Tensor
    """World → OpenCV camera frame (x right, y down, z forward)."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    near: float = 0.05
    """Gaussians with camera z <= near are culled."""
    far: float = 1000.0
    """Gaussians with camera z >= far are culled."""

    def __post_init__(self) -> None:
        if tuple(self.K_33.shape) != (3, 3):
            raise ValueError(f"Camera.K_33 must have shape (3, 3), got {tuple(self.K_33.shape)}")
        if tuple(self.world2cam_44.shape) != (4, 4):
            raise ValueError(f"Camera.world2cam_44 must have shape (4, 4), got {tuple(self.world2cam_44.shape)}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or value <= 0:
                raise ValueError(f"Camera.{name} must be a positive int, got {value!r}")
        if not 0 < self.near < self.far:
            raise ValueError(f"Camera needs 0 < near < far, got near={self.near}, far={self.far}")
        if not (bool(torch.isfinite(self.K_33).all()) and bool(torch.isfinite(self.world2cam_44).all())):
            raise ValueError("Camera.K_33 / world2cam_44 contain NaN or inf")

    @staticmethod
    def from_numpy(K_33, world2cam_44, width: int, height: int, **kw) -> Camera:
        """Build a camera from array-likes; matrices become float32 tensors."""
        K = torch.as_tensor(np.asarray(K_33, dtype=np.float32))
        w2c = torch.as_tensor(np.asarray(world2cam_44, dtype=np.float32))
        return Camera(K, w2c, int(width), int(height), **kw)

    def to(self, device: torch.device | str, dtype: torch.dtype) -> Camera:
        """The same camera with its matrices on ``device`` in ``dtype``."""
        return Camera(
            self.K_33.to(device=device, dtype=dtype),
            self.world2cam_44.to(device=device, dtype=dtype),
            self.width,
            self.height,
            self.near,
            self.far,
        )
