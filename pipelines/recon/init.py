"""Initial Gaussians from the scene's aggregated LiDAR (paper: Large-scale 3D Gaussian Reconstruction).

Legend: P LiDAR points, N Gaussians, V views. World frame = the dataset's ego2world target frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipelines.data.layout import DataError
from pipelines.data.reader import Scene


@dataclass
class View:
    """One (frame, camera) image with its pose."""

    frame: int
    camera: str
    K_33: np.ndarray
    world2cam_44: np.ndarray
    rgb_HW3: np.ndarray  # float32 in [0, 1]
    lidar_depth_HW: np.ndarray  # metres, 0 = no LiDAR return


def _inside_boxes(points_P3: np.ndarray, boxes: list[dict]) -> np.ndarray:
    """Points (ego frame) inside any of the boxes (slightly inflated)."""
    inside = np.zeros(len(points_P3), dtype=bool)
    for b in boxes:
        c, (l, w, h), yaw = np.asarray(b["center"]), b["size"], b["yaw"]
        d = points_P3 - c
        cs, sn = np.cos(-yaw), np.sin(-yaw)
        x, y = cs * d[:, 0] - sn * d[:, 1], sn * d[:, 0] + cs * d[:, 1]
        inside |= (np.abs(x) <= l / 2 + 0.2) & (np.abs(y) <= w / 2 + 0.2) & (np.abs(d[:, 2]) <= h / 2 + 0.2)
    return inside


def box_pose(box: dict) -> np.ndarray:
    """4x4 box -> ego transform (yaw about z, centre)."""
    c, sn = np.cos(box["yaw"]), np.sin(box["yaw"])
    m = np.eye(4)
    m[:2, :2] = [[c, -sn], [sn, c]]
    m[:3, 3] = box["center"]
    return m


@dataclass
class SceneLidar:
    static_P3: np.ndarray
    """Returns of the static scene, world frame."""
    dynamic: dict[str, np.ndarray]
    """Moving instance id -> its returns in the box's own frame (accumulated over frames)."""
    poses: dict[int, dict[str, np.ndarray]]
    """frame -> instance id -> 4x4 box -> world pose (instances present in that frame)."""


def aggregate_lidar(scene: Scene, split_moving: bool, moving_speed: float) -> SceneLidar:
    """Every frame's LiDAR in the world frame; returns on moving objects go to per-instance box frames.

    A static field would smear a moving car along its path; in its own box frame it is rigid (Street-Gaussians
    style), so each frame renders it at that frame's box pose.
    """
    static, dynamic, poses = [], {}, {}
    moving_ids = set()
    if split_moving:
        for f in scene.frames():
            moving_ids |= {b["instance_id"] for b in f.boxes3d() if np.hypot(*b["velocity"]) > moving_speed}
    for f in scene.frames():
        pts = f.lidar()[:, :3].astype(np.float64)
        poses[f.idx] = {}
        for b in f.boxes3d():
            if b["instance_id"] not in moving_ids:
                continue
            inside = _inside_boxes(pts, [b])
            box2ego = box_pose(b)
            poses[f.idx][b["instance_id"]] = f.ego2world @ box2ego
            local = (pts[inside] - box2ego[:3, 3]) @ box2ego[:3, :3]
            dynamic.setdefault(b["instance_id"], []).append(local)
            pts = pts[~inside]
        static.append(pts @ f.ego2world[:3, :3].T + f.ego2world[:3, 3])
    if sum(len(c) for c in static) + sum(len(c) for cs in dynamic.values() for c in cs) == 0:
        raise DataError(f"{scene.id}: no LiDAR points (reconstruction is LiDAR-initialised)")
    dyn = {k: np.concatenate(v) for k, v in dynamic.items() if sum(len(c) for c in v)}
    return SceneLidar(np.concatenate(static), dyn, poses)


def voxel_downsample(points_P3: np.ndarray, voxel: float, cap: int, seed: int) -> np.ndarray:
    """One point per occupied voxel (the first by a seeded shuffle), then at most ``cap`` points."""
    rng = np.random.default_rng(seed)
    pts = points_P3[rng.permutation(len(points_P3))]
    _, first = np.unique(np.floor(pts / voxel).astype(np.int64), axis=0, return_index=True)
    pts = pts[np.sort(first)]
    if len(pts) > cap:
        pts = pts[rng.choice(len(pts), cap, replace=False)]
    return pts


def nn_scales(points_N3: np.ndarray, k: int = 3) -> np.ndarray:
    """[N] mean distance to the k nearest neighbours: the initial isotropic scale (as 3DGS does)."""
    dist, _ = cKDTree(points_N3).query(points_N3, k=k + 1)
    return np.clip(dist[:, 1:].mean(axis=1), 0.01, 2.0)


def project_colors(points_N3: np.ndarray, views: list[View], world_of=None) -> np.ndarray:
    """[N, 3] mean colour of each point over the views it projects into (no occlusion test: LiDAR sits by the
    cameras). ``world_of(frame)`` maps the points into the world at that frame (None: absent then)."""
    acc = np.zeros((len(points_N3), 3))
    cnt = np.zeros(len(points_N3))
    for v in views:
        pts = points_N3 if world_of is None else world_of(v.frame)
        if pts is None:
            continue
        cam = pts @ v.world2cam_44[:3, :3].T + v.world2cam_44[:3, 3]
        z = cam[:, 2]
        front = z > 0.1
        uv = cam[front, :2] / z[front, None] @ v.K_33[:2, :2].T + v.K_33[:2, 2]
        h, w = v.rgb_HW3.shape[:2]
        u, vv = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
        idx = np.flatnonzero(front)[ok]
        acc[idx] += v.rgb_HW3[vv[ok], u[ok]]
        cnt[idx] += 1
    colors = np.full((len(points_N3), 3), 0.5)
    seen = cnt > 0
    colors[seen] = acc[seen] / cnt[seen, None]
    return colors


@dataclass
class InitialGaussians:
    points_N3: np.ndarray  # world (static) or box frame (dynamic)
    colors_N3: np.ndarray
    scales_N: np.ndarray
    instance_N: np.ndarray  # index into ``instances``, -1 static
    instances: list[str]


def initial_gaussians(lidar: SceneLidar, views: list[View], voxel: float, cap: int, seed: int) -> InitialGaussians:
    """Down-sampled LiDAR → centres; colours from the images; scales from nearest neighbours (3DGS init)."""
    instances = sorted(lidar.dynamic)
    dyn = [voxel_downsample(lidar.dynamic[k], voxel / 2, cap, seed) for k in instances]
    n_dyn = sum(len(d) for d in dyn)
    static = voxel_downsample(lidar.static_P3, voxel, max(cap - n_dyn, 1), seed)
    parts = [(static, project_colors(static, views), nn_scales(static), -1)]
    for i, (k, pts) in enumerate(zip(instances, dyn, strict=True)):

        def world_of(frame: int, pts=pts, k=k) -> np.ndarray | None:
            pose = lidar.poses.get(frame, {}).get(k)
            return None if pose is None else pts @ pose[:3, :3].T + pose[:3, 3]

        scales = nn_scales(pts) if len(pts) > 3 else np.full(len(pts), 0.1)
        parts.append((pts, project_colors(pts, views, world_of), scales, i))
    return InitialGaussians(
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
        np.concatenate([np.full(len(p[0]), p[3]) for p in parts]),
        instances,
    )


def lidar_depth_image(points_world_P3: np.ndarray, K_33: np.ndarray, world2cam_44: np.ndarray, h: int, w: int):
    """[H, W] nearest LiDAR depth per pixel (0 where none): the sparse depth supervision."""
    cam = points_world_P3 @ world2cam_44[:3, :3].T + world2cam_44[:3, 3]
    cam = cam[cam[:, 2] > 0.5]
    uv = cam[:, :2] / cam[:, 2:3] @ K_33[:2, :2].T + K_33[:2, 2]
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full(h * w, np.inf)
    np.minimum.at(depth, v[ok] * w + u[ok], cam[ok, 2])
    depth[np.isinf(depth)] = 0.0
    return depth.reshape(h, w).astype(np.float32)


def load_views(scene: Scene) -> list[View]:
    """Every (frame, camera) view of the scene with world->camera poses and sparse LiDAR depth."""
    views = []
    for f in scene.frames():
        # Per-frame LiDAR is the honest depth supervision for that frame's images.
        pts = f.lidar()[:, :3].astype(np.float64)
        pts_world = pts @ f.ego2world[:3, :3].T + f.ego2world[:3, 3]
        for name, cam in scene.cameras.items():
            cam2world = f.ego2world @ cam.sensor2ego_44
            world2cam = np.linalg.inv(cam2world)
            rgb = f.image(name).astype(np.float32) / 255.0
            h, w = rgb.shape[:2]
            views.append(
                View(f.idx, name, cam.K_33, world2cam, rgb, lidar_depth_image(pts_world, cam.K_33, world2cam, h, w))
            )
    return views
