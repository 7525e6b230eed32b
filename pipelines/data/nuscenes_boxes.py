"""nuScenes annotations -> our 3D boxes (current ego frame) and 2D boxes (per camera image).

nuScenes boxes are global: centre, size (w, l, h), rotation box->world (w, x, y, z); the box's own
x axis runs along its length. Ours: centre/yaw/velocity in the frame's ego frame, size (l, w, h).
Legend: N points, 8 corners.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from pipelines.data.layout import pose_matrix
from pipelines.data.nuscenes_tables import NuScenesTables

NEAR_M = 0.1  # near plane for 2D projection: corners closer than this are clipped away, not projected
MAX_VELOCITY_DT_S = 1.5  # as nuScenes' box_velocity: neighbours further apart in time give no velocity

# Unit cube corners (x along length, y along width, z up), bottom face then top face.
_UNIT_CORNERS_83 = np.array(
    [[x, y, z] for z in (-0.5, 0.5) for x, y in ((0.5, 0.5), (0.5, -0.5), (-0.5, -0.5), (-0.5, 0.5))]
)
_EDGES = (
    [(i, (i + 1) % 4) for i in range(4)] + [(4 + i, 4 + (i + 1) % 4) for i in range(4)] + [(i, i + 4) for i in range(4)]
)


def box_to_world(ann: dict) -> np.ndarray:
    """4x4 box->world pose of a sample_annotation."""
    return pose_matrix(ann["rotation"], ann["translation"])


def size_lwh(ann: dict) -> np.ndarray:
    width, length, height = ann["size"]
    return np.array([length, width, height], dtype=np.float64)


def corners_world(ann: dict) -> np.ndarray:
    """[8, 3] corners in world coordinates."""
    m = box_to_world(ann)
    return (_UNIT_CORNERS_83 * size_lwh(ann)) @ m[:3, :3].T + m[:3, 3]


def yaw_of(rotation_33: np.ndarray) -> float:
    """Heading of a box's length axis about z."""
    return math.atan2(rotation_33[1, 0], rotation_33[0, 0])


def annotation_velocity(tables: NuScenesTables, ann: dict) -> np.ndarray:
    """Global velocity [3] from the neighbouring annotations (central difference where both exist),
    NaN where there is none or they are too far apart in time (nuScenes' box_velocity)."""
    has_prev, has_next = bool(ann.get("prev")), bool(ann.get("next"))
    if not (has_prev or has_next):
        return np.full(3, np.nan)
    first = tables.get("sample_annotation", ann["prev"], ann["token"]) if has_prev else ann
    last = tables.get("sample_annotation", ann["next"], ann["token"]) if has_next else ann
    dt = 1e-6 * (tables.timestamp_us(last) - tables.timestamp_us(first))
    max_dt = MAX_VELOCITY_DT_S * (2 if has_prev and has_next else 1)
    if not 0 < dt <= max_dt:
        return np.full(3, np.nan)
    return (np.asarray(last["translation"], dtype=np.float64) - np.asarray(first["translation"])) / dt


def box3d_row(tables: NuScenesTables, ann: dict, world2ego_44: np.ndarray) -> dict:
    """BOXES3D fields (without scene/frame) of one annotation in the ego frame given by ``world2ego``."""
    m = world2ego_44 @ box_to_world(ann)
    velocity = world2ego_44[:3, :3] @ annotation_velocity(tables, ann)
    velocity = np.nan_to_num(velocity, nan=0.0)  # unknown velocity is stored as 0
    return {
        "instance_id": ann["instance_token"],
        "category": tables.category(ann),
        "attribute": tables.attribute(ann),
        "center": [float(v) for v in m[:3, 3]],
        "size": [float(v) for v in size_lwh(ann)],
        "yaw": yaw_of(m[:3, :3]),
        "velocity": [float(velocity[0]), float(velocity[1])],
    }


def project_box(
    corners_cam_83: np.ndarray, K_33: np.ndarray, width: int, height: int
) -> tuple[list[float], float] | None:
    """2D box [x1, y1, x2, y2] and visible fraction of a box seen by a camera, or None if not visible.

    The box is clipped at the near plane, its projected hull intersected with the image; the visible
    fraction is the hull's area inside the image over its whole area.
    """
    pts = _clip_near(corners_cam_83)
    if len(pts) < 3:
        return None
    uv = (pts @ np.asarray(K_33).T)[:, :2] / pts[:, 2:3]
    hull = cv2.convexHull(uv.astype(np.float32))
    full_area = cv2.contourArea(hull)
    if full_area <= 0:
        return None
    image = np.array([[0, 0], [width, 0], [width, height], [0, height]], dtype=np.float32)
    area, inside = cv2.intersectConvexConvex(hull, image)
    if area <= 0 or inside is None:
        return None
    inside = inside.reshape(-1, 2)
    x1, y1 = inside.min(axis=0)
    x2, y2 = inside.max(axis=0)
    if x2 <= x1 or y2 <= y1:
        return None
    return [float(x1), float(y1), float(x2), float(y2)], float(min(1.0, area / full_area))


def _clip_near(corners_83: np.ndarray) -> np.ndarray:
    """Vertices of the box cut by the plane z = NEAR_M, keeping the part in front of the camera."""
    z = corners_83[:, 2]
    pts = [corners_83[i] for i in range(8) if z[i] >= NEAR_M]
    for a, b in _EDGES:
        if (z[a] >= NEAR_M) != (z[b] >= NEAR_M):
            t = (NEAR_M - z[a]) / (z[b] - z[a])
            pts.append(corners_83[a] + t * (corners_83[b] - corners_83[a]))
    return np.asarray(pts).reshape(-1, 3)


def scale_intrinsics(K_33: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy) with OpenCV's pixel-centre convention (as cv2.resize)."""
    K = np.asarray(K_33, dtype=np.float64).copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K
