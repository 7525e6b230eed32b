"""Raw nuScenes sensor files: camera JPEGs and ``LIDAR_TOP`` ``.pcd.bin`` sweeps. Errors name ``where``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.data.layout import DataError, read_image_file

LIDAR_FLOATS = 5  # x, y, z, intensity, ring index; float32, lidar frame


def read_image_rgb(path: Path, where: str) -> np.ndarray:
    """[H, W, 3] uint8 RGB of a JPEG/PNG; missing, truncated or undecodable files are DataErrors."""
    return cv2.cvtColor(read_image_file(path, where), cv2.COLOR_BGR2RGB)


def resize(rgb_HW3: np.ndarray, width: int, height: int) -> np.ndarray:
    # INTER_AREA: the anti-aliased choice for downscaling.
    return cv2.resize(rgb_HW3, (width, height), interpolation=cv2.INTER_AREA)


def read_lidar(path: Path, where: str) -> np.ndarray:
    """[N, 5] float32 points of a ``.pcd.bin`` in the lidar frame."""
    if not path.is_file():
        raise DataError(f"{where}: missing LiDAR file {path}")
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % LIDAR_FLOATS:
        raise DataError(f"{where}: LiDAR file {path} holds {raw.size} floats, not a multiple of {LIDAR_FLOATS}")
    return raw.reshape(-1, LIDAR_FLOATS)


def lidar_to_ego(points_N5: np.ndarray, sensor2ego_44: np.ndarray) -> np.ndarray:
    """[N, 4] (x, y, z, intensity) in the ego frame."""
    xyz = points_N5[:, :3].astype(np.float64) @ sensor2ego_44[:3, :3].T + sensor2ego_44[:3, 3]
    return np.concatenate([xyz, points_N5[:, 3:4].astype(np.float64)], axis=1).astype(np.float32)
