"""Camera rendering: a G-buffer per camera (depth, albedo, normals, instances) and clear-day shading.

Depth is metric z-depth along the optical axis (0 for sky). Shading is Lambertian under a sun
plus a sky-light ambient term; the sky is a vertical gradient with faint clouds. Legend: H x W
pixels, A agents.
"""

from __future__ import annotations

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


def render_gbuffer(scene: Scene, prims: Primitives, cam: Camera, ego2world_44: np.ndarray, max_depth: float) -> GBuffer:
    cam2world = ego2world_44 @ cam.sensor2ego_44
    origin = cam2world[:3, 3]
    dirs_cam = cam.rays_cam_HW3.reshape(-1, 3)
    dirs = dirs_cam @ cam2world[:3, :3].T
    # Cull with a margin: z-depth <= max_depth means ray length up to max_depth / cos(half_fov).
    max_t = max_depth / float(dirs_cam[:, 2].min())
    sub, _ = cull(prims, origin, max_t, cam2world[:3, 2], cam.half_fov)
    hits = cast(origin, dirs, sub, max_t, num_actors=len(scene.actors))
    depth = np.where(hits.prim_R == SKY, 0.0, hits.t_R * dirs_cam[:, 2])
    sky = (hits.prim_R == SKY) | (depth > max_depth)
    depth = np.where(sky, 0.0, depth)
    hits.prim_R = np.where(sky, SKY, hits.prim_R)
    surf = surface(hits, sub, scene.road, seed=scene.index)
    actor = np.where(hits.prim_R >= 0, sub.actor_P[np.maximum(hits.prim_R, 0)], -1)
    coverage = hits.coverage_RA.sum(axis=0) if hits.coverage_RA is not None else np.zeros(0, dtype=np.int64)
    h, w = cam.height, cam.width
    return GBuffer(
        depth.reshape(h, w).astype(np.float32),
        np.where(sky, np.inf, hits.t_R).reshape(h, w),
        dirs.reshape(h, w, 3),
        hits.point_R3.reshape(h, w, 3),
        hits.normal_R3.reshape(h, w, 3),
        surf.albedo_R3.reshape(h, w, 3),
        surf.emissive_R3.reshape(h, w, 3),
        sky.reshape(h, w),
        actor.reshape(h, w),
        coverage,
    )


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
