"""Camera rendering: a G-buffer per camera (depth, albedo, normals, instances) and clear-day shading.

Depth is metric z-depth along the optical axis (0 for sky). The image is cast in pixel blocks,
each against only the primitives inside its own frustum (4x less work than one frustum per
camera on a street view). Shading is Lambertian under a sun plus a sky-light ambient term; the
sky is a vertical gradient with faint clouds. Legend: H x W pixels, A agents.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from pipelines.data.synth.camera import Camera
from pipelines.data.synth.raycast import SKY, Primitives, cast, cull
from pipelines.data.synth.scene import Scene
from pipelines.data.synth.textures import surface, value_noise


@dataclass
class GBuffer:
    depth_HW: np.ndarray
    """Metric z-depth, 0 where the ray met nothing within range (sky)."""
    dist_HW: np.ndarray
    """Distance along the ray, inf for sky."""
    dirs_HW3: np.ndarray
    """Unit ray directions, world frame."""
    point_HW3: np.ndarray
    normal_HW3: np.ndarray
    albedo_HW3: np.ndarray
    emissive_HW3: np.ndarray
    sky_HW: np.ndarray
    actor_HW: np.ndarray
    """Index into ``scene.actors`` of the visible agent per pixel, -1 for none."""
    coverage_A: np.ndarray
    """Pixels each agent would cover with nothing in front of it (for visible fractions)."""


TILES = (2, 4)
"""Rows x columns of pixel blocks, each ray-cast against only the primitives in its own frustum."""


def _blocks(n: int, parts: int) -> list[slice]:
    edges = np.linspace(0, n, min(parts, n) + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges)]


def render_gbuffer(scene: Scene, prims: Primitives, cam: Camera, ego2world_44: np.ndarray, max_depth: float) -> GBuffer:
    h, w = cam.height, cam.width
    cam2world = ego2world_44 @ cam.sensor2ego_44
    origin, rot = cam2world[:3, 3], cam2world[:3, :3]
    dirs_cam = cam.rays_cam_HW3
    dirs = dirs_cam @ rot.T
    n_actors = len(scene.actors)
    depth = np.zeros((h, w), dtype=np.float32)
    dist = np.full((h, w), np.inf)
    point, normal = np.zeros((h, w, 3)), np.zeros((h, w, 3))
    albedo, emissive = np.zeros((h, w, 3)), np.zeros((h, w, 3))
    sky = np.ones((h, w), dtype=bool)
    actor = np.full((h, w), -1, dtype=np.int64)
    coverage = np.zeros(n_actors, dtype=np.int64)
    for rows in _blocks(h, TILES[0]):
        for cols in _blocks(w, TILES[1]):
            d_cam = dirs_cam[rows, cols].reshape(-1, 3)
            # z-depth <= max_depth allows rays up to max_depth / cos(angle to the optical axis).
            max_t = max_depth / float(d_cam[:, 2].min())
            sub, _ = cull(prims, origin, max_t, cam.frustum_planes(rows, cols) @ rot.T)
            hits = cast(origin, dirs[rows, cols].reshape(-1, 3), sub, max_t, num_actors=n_actors)
            z = np.where(hits.prim_R == SKY, 0.0, hits.t_R * d_cam[:, 2])
            blank = (hits.prim_R == SKY) | (z > max_depth)
            hits.prim_R = np.where(blank, SKY, hits.prim_R)
            surf = surface(hits, sub, scene.road, seed=scene.index)
            shape = (rows.stop - rows.start, cols.stop - cols.start)
            depth[rows, cols] = np.where(blank, 0.0, z).reshape(shape)
            dist[rows, cols] = np.where(blank, np.inf, hits.t_R).reshape(shape)
            point[rows, cols] = hits.point_R3.reshape(*shape, 3)
            normal[rows, cols] = hits.normal_R3.reshape(*shape, 3)
            albedo[rows, cols] = surf.albedo_R3.reshape(*shape, 3)
            emissive[rows, cols] = surf.emissive_R3.reshape(*shape, 3)
            sky[rows, cols] = blank.reshape(shape)
            ids = np.where(hits.prim_R >= 0, sub.actor_P[np.maximum(hits.prim_R, 0)], -1)
            actor[rows, cols] = ids.reshape(shape)
            if hits.coverage_RA is not None:
                coverage += hits.coverage_RA.sum(axis=0)
    return GBuffer(depth, dist, dirs, point, normal, albedo, emissive, sky, actor, coverage)


def sky_colour(dirs_N3: np.ndarray, seed: int) -> np.ndarray:
    """Clear sky: pale at the horizon, deeper blue above, faint clouds."""
    up = np.clip(dirs_N3[..., 2], 0.0, 1.0)[..., None]
    horizon, zenith = np.array([0.80, 0.86, 0.94]), np.array([0.33, 0.52, 0.84])
    base = horizon + (zenith - horizon) * np.sqrt(up)
    # Clouds: noise on the direction projected onto a plane 1 km up (far enough to look static).
    k = 1000.0 / np.maximum(dirs_N3[..., 2], 0.05)
    cloud = value_noise(dirs_N3[..., 0] * k, dirs_N3[..., 1] * k, 400.0, seed)
    cover = np.clip((cloud - 0.55) * 2.5, 0.0, 1.0)[..., None] * (up > 0)
    return base * (1 - 0.6 * cover) + 0.95 * 0.6 * cover


def shade_clear(gb: GBuffer, sun_dir: np.ndarray, seed: int) -> np.ndarray:
    """[H, W, 3] float RGB in [0, 1] under a clear sky."""
    n_dot_l = np.clip((gb.normal_HW3 * sun_dir).sum(-1), 0.0, 1.0)[..., None]
    ambient = 0.42 * (0.75 + 0.25 * gb.normal_HW3[..., 2:3])
    rgb = gb.albedo_HW3 * (ambient + 0.72 * n_dot_l)
    rgb = np.where(gb.sky_HW[..., None], sky_colour(gb.dirs_HW3, seed), rgb)
    return np.clip(rgb, 0.0, 1.0)
