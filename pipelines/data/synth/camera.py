"""The nuScenes-like surround rig: 6 cameras around the roof edge and a roof LiDAR.

Intrinsics are nuScenes' (1600x900, fx ~1266, the back camera ~809) scaled to the stored
size, principal point at the image centre. Pixel (row i, column j) covers [j, j+1) x [i, i+1)
in K's pixel frame, so its ray passes through (j + 0.5, i + 0.5), as 3DGS rasterizers assume.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from pipelines.data.layout import CAMERAS

# name: (x, y, z) on the ego (metres, rear-axle origin), yaw (degrees, + = left), fx at 1600x900.
RIG = {
    "CAM_FRONT": ((1.70, 0.00, 1.51), 0.0, 1266.4),
    "CAM_FRONT_RIGHT": ((1.55, -0.49, 1.50), -55.0, 1260.8),
    "CAM_BACK_RIGHT": ((1.05, -0.48, 1.56), -110.0, 1259.5),
    "CAM_BACK": ((0.03, 0.00, 1.58), 180.0, 809.2),
    "CAM_BACK_LEFT": ((1.05, 0.48, 1.56), 110.0, 1256.7),
    "CAM_FRONT_LEFT": ((1.52, 0.49, 1.51), 55.0, 1272.6),
}
LIDAR_MOUNT = (0.94, 0.0, 1.84)
"""LiDAR origin on the ego (nuScenes' LIDAR_TOP)."""


@dataclass(frozen=True)
class Camera:
    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    sensor2ego_44: np.ndarray
    """OpenCV camera (x right, y down, z forward) -> ego."""

    @property
    def K_33(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @cached_property
    def rays_cam_HW3(self) -> np.ndarray:
        """Unit ray directions through the pixel centres, camera frame."""
        j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d = np.stack([(j - self.cx) / self.fx, (i - self.cy) / self.fy, np.ones_like(j)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def frustum_planes(self, rows: slice, cols: slice) -> np.ndarray:
        """[4, 3] inward unit normals (camera frame) of the frustum through a pixel block's outer edges."""
        a0, a1 = (cols.start - self.cx) / self.fx, (cols.stop - self.cx) / self.fx
        b0, b1 = (rows.start - self.cy) / self.fy, (rows.stop - self.cy) / self.fy
        # Inside means a0 <= x/z <= a1 and b0 <= y/z <= b1.
        n = np.array([[1.0, 0.0, -a0], [-1.0, 0.0, a1], [0.0, 1.0, -b0], [0.0, -1.0, b1]])
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def make_rig(width: int, height: int) -> list[Camera]:
    """The 6 cameras in the layout's ``CAMERAS`` order, intrinsics scaled to width x height."""
    out = []
    for name in CAMERAS:
        xyz, yaw_deg, fx = RIG[name]
        yaw = np.deg2rad(yaw_deg)
        forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        m = np.eye(4)
        m[:3, :3] = np.stack([right, down, forward], axis=1)
        m[:3, 3] = xyz
        # nuScenes' fx and fy are equal at 1600x900; scaling keeps square pixels only at 16:9.
        out.append(Camera(name, width, height, fx * width / 1600, fx * height / 900, width / 2, height / 2, m))
    return out
