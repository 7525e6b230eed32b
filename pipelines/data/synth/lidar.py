"""A spinning multi-beam LiDAR ray-cast from the roof mount into the same scene the cameras see.

Beams are spread like a Velodyne HDL-32E (-30.67 to +10.67 degrees elevation); a sweep is
instantaneous (no rolling-shutter motion). Points are returned in the ego frame with
nuScenes-scale intensity (0-255): material reflectivity times a Lambertian incidence term.
"""

from __future__ import annotations

import numpy as np

from pipelines.data.synth.camera import LIDAR_MOUNT
from pipelines.data.synth.raycast import SKY, Primitives, cast, cull
from pipelines.data.synth.scene import Scene
from pipelines.data.synth.textures import surface

MIN_RANGE_M = 1.0
SECTORS = 8
"""Azimuth wedges per sweep (each wedge is culled on its own; 8 keeps every wedge under 180 degrees)."""


def beam_directions(beams: int, azimuth_steps: int) -> np.ndarray:
    """[beams * azimuth_steps, 3] unit directions in the ego frame, beam-major."""
    elev = np.deg2rad(np.linspace(-30.67, 10.67, beams)) if beams > 1 else np.zeros(1)
    azim = np.arange(azimuth_steps) * (2 * np.pi / azimuth_steps)
    e, a = np.meshgrid(elev, azim, indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


def sweep(
    scene: Scene, prims: Primitives, ego2world_44: np.ndarray, dirs_ego_N3: np.ndarray, max_range: float
) -> np.ndarray:
    """[N, 4] (x, y, z, intensity) of the returns within [MIN_RANGE_M, max_range], ego frame."""
    mount = np.asarray(LIDAR_MOUNT)
    origin = ego2world_44[:3, :3] @ mount + ego2world_44[:3, 3]
    dirs = dirs_ego_N3 @ ego2world_44[:3, :3].T
    azim = np.arctan2(dirs_ego_N3[:, 1], dirs_ego_N3[:, 0])
    out = []
    # Azimuth wedges, each cast against the primitives between its two vertical bounding planes.
    for k in range(SECTORS):
        a0, a1 = -np.pi + 2 * np.pi * k / SECTORS, -np.pi + 2 * np.pi * (k + 1) / SECTORS
        sel = (azim >= a0) & ((azim < a1) | (k == SECTORS - 1))
        if not sel.any():
            continue
        planes_ego = np.array([[-np.sin(a0), np.cos(a0), 0.0], [np.sin(a1), -np.cos(a1), 0.0]])
        sub, _ = cull(prims, origin, max_range, planes_ego @ ego2world_44[:3, :3].T)
        hits = cast(origin, dirs[sel], sub, max_range)
        keep = (hits.prim_R != SKY) & (hits.t_R >= MIN_RANGE_M)
        surf = surface(hits, sub, scene.road, seed=scene.index)
        incidence = np.abs((hits.normal_R3 * dirs[sel]).sum(1))
        intensity = 255.0 * surf.reflectivity_R * (0.35 + 0.65 * incidence)
        xyz = mount[None, :] + np.where(keep, hits.t_R, 0.0)[:, None].astype(np.float64) * dirs_ego_N3[sel]
        out.append(np.concatenate([xyz[keep], intensity[keep, None]], axis=1))
    return np.concatenate(out).astype(np.float32).reshape(-1, 4)
