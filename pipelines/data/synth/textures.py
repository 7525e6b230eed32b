"""Procedural surface appearance: albedo, LiDAR reflectivity and night-time emission per hit.

Textures are functions of world or primitive-local coordinates (asphalt grain, lane markings,
zebra crossings, sidewalk tiles, facade windows, wheels, glass, foliage), so every view of a
surface agrees and images carry the detail a 3DGS fit needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipelines.data.synth.materials import REFLECTIVITY, Material
from pipelines.data.synth.raycast import GROUND, Hits, Primitives
from pipelines.data.synth.road import CARRIAGEWAY_HALF, KERB_OUTER, LANE_WIDTH, PARKING_OUTER, SIDEWALK_OUTER, Road

GLASS = np.array([0.10, 0.13, 0.17])
WHITE_PAINT = np.array([0.86, 0.86, 0.84])
YELLOW_PAINT = np.array([0.86, 0.70, 0.16])


@dataclass
class Surface:
    albedo_R3: np.ndarray
    reflectivity_R: np.ndarray
    """Diffuse LiDAR reflectivity in [0, 1]."""
    emissive_R3: np.ndarray
    """Light emitted at night (lit windows, lamps, vehicle lights); 0 elsewhere."""


def _hash(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Uniform [0, 1) per integer lattice point (an integer hash, so no RNG state is involved)."""
    h = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + seed * 2246822519) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    return ((h ^ (h >> 16)) & 0xFFFFFF) / float(1 << 24)


def value_noise(x: np.ndarray, y: np.ndarray, cell: float, seed: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1) with lattice spacing ``cell``."""
    gx, gy = np.asarray(x) / cell, np.asarray(y) / cell
    ix, iy = np.floor(gx), np.floor(gy)
    fx, fy = gx - ix, gy - iy
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    v00, v10 = _hash(ix, iy, seed), _hash(ix + 1, iy, seed)
    v01, v11 = _hash(ix, iy + 1, seed), _hash(ix + 1, iy + 1, seed)
    return (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy


def ground(road: Road, x: np.ndarray, y: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """([N, 3] albedo, [N] reflectivity) of the ground at world xy."""
    s, lat = road.to_road(x, y)
    a = np.abs(lat)
    grain = 0.06 * (value_noise(x, y, 0.35, seed) - 0.5) + 0.05 * (value_noise(x, y, 3.0, seed + 1) - 0.5)
    albedo = np.empty((len(s), 3))
    refl = np.full(len(s), REFLECTIVITY[Material.GROUND], dtype=np.float32)
    grass = a > SIDEWALK_OUTER
    albedo[:] = (0.27 + grain)[:, None]
    parking = (a > CARRIAGEWAY_HALF) & (a <= PARKING_OUTER)
    albedo[parking] = (0.32 + grain[parking])[:, None]
    kerb = (a > PARKING_OUTER) & (a <= KERB_OUTER)
    albedo[kerb] = 0.70
    walk = (a > KERB_OUTER) & (a <= SIDEWALK_OUTER)
    grout = (np.mod(s, 1.5) < 0.06) | (np.mod(a - KERB_OUTER, 1.5) < 0.06)
    albedo[walk] = (np.where(grout[walk], 0.45, 0.60) + grain[walk])[:, None]
    green = np.array([0.24, 0.40, 0.15]) * (0.75 + 0.5 * value_noise(x, y, 0.8, seed + 2))[:, None]
    albedo[grass] = green[grass]
    refl[kerb | walk] = 0.25
    refl[grass] = 0.15

    # Markings: double yellow centre line, dashed lane dividers, solid edge lines, parking bays, zebras.
    road_area = a <= CARRIAGEWAY_HALF
    yellow = road_area & (np.abs(a - 0.14) < 0.06)
    white = road_area & (np.abs(a - LANE_WIDTH) < 0.075) & (np.mod(s, 9.0) < 3.0)
    white |= np.abs(a - (CARRIAGEWAY_HALF - 0.15)) < 0.075
    white |= parking & (a > CARRIAGEWAY_HALF + 0.2) & (np.mod(s, 6.0) < 0.12)
    for s0 in road.crosswalks:
        white |= road_area & (s >= s0) & (s <= s0 + 4.0) & (np.mod(lat, 1.0) < 0.5)
    albedo[white] = WHITE_PAINT + grain[white, None] * 0.5
    albedo[yellow] = YELLOW_PAINT + grain[yellow, None] * 0.5
    refl[white | yellow] = 0.80
    return np.clip(albedo, 0.0, 1.0), refl


def surface(hits: Hits, prims: Primitives, road: Road, seed: int) -> Surface:
    """Albedo, reflectivity and emission of every hit (sky rows get zeros)."""
    n = len(hits.t_R)
    albedo = np.zeros((n, 3))
    refl = np.zeros(n, dtype=np.float32)
    emis = np.zeros((n, 3))
    is_ground = hits.prim_R == GROUND
    if is_ground.any():
        albedo[is_ground], refl[is_ground] = ground(
            road, hits.point_R3[is_ground, 0], hits.point_R3[is_ground, 1], seed
        )
    obj = np.flatnonzero(hits.prim_R >= 0)
    if not len(obj):
        return Surface(albedo, refl, emis)
    k = hits.prim_R[obj]
    mat = prims.material_P[k]
    col = prims.colour_P3[k].astype(np.float64)
    refl[obj] = REFLECTIVITY[mat]
    local = hits.local_R3[obj]
    z = hits.point_R3[obj, 2]
    nb = prims.counts[0]
    # Box face and in-face coordinates: u runs along the face, from its left edge.
    half = np.ones((len(obj), 3))
    is_box = k < nb
    half[is_box] = prims.box_half_B3[k[is_box]]
    q = np.abs(local) / half
    axis = np.where(is_box, np.argmax(q, axis=1), -1)
    side = (axis == 0) | (axis == 1)
    u = np.where(axis == 0, local[:, 1] + half[:, 1], local[:, 0] + half[:, 0])
    top_z = np.where(is_box, z - local[:, 2] + half[:, 2], z)  # world z of the box top

    out = col.copy()
    glow = np.zeros_like(out)

    m = mat == Material.BUILDING
    if m.any():
        bay, floor_ = np.floor(u[m] / 2.6), np.floor(z[m] / 3.2)
        fu, fz = np.mod(u[m], 2.6) / 2.6, np.mod(z[m], 3.2) / 3.2
        window = side[m] & (fu > 0.2) & (fu < 0.8) & (fz > 0.3) & (fz < 0.8)
        tint = 0.9 + 0.2 * value_noise(u[m], z[m], 4.0, seed + 3)
        face = col[m] * tint[:, None]
        face[axis[m] == 2] *= 0.7
        pane = GLASS + 0.08 * _hash(bay, floor_, seed + 4)[:, None]
        out[m] = np.where(window[:, None], pane, face)
        lit = window & (_hash(bay + 7, floor_, seed + 5) > 0.7)
        glow[m] = np.where(lit[:, None], [0.8, 0.65, 0.4], 0.0)
        refl[obj[m]] = np.where(window, 0.05, refl[obj[m]])

    m = mat == Material.PAINT
    if m.any():
        hl = half[m]
        lx, ly = local[m, 0], local[m, 1]
        dxw = np.minimum(np.abs(lx - (hl[:, 0] - 0.8)), np.abs(lx + (hl[:, 0] - 0.8)))
        r2 = dxw**2 + (z[m] - 0.33) ** 2
        wheel = (axis[m] == 1) & (r2 < 0.33**2)
        hub = wheel & (r2 < 0.14**2)
        bumper = side[m] & (z[m] < 0.3)
        lamp = (axis[m] == 0) & (np.abs(ly) > hl[:, 1] - 0.45) & (np.abs(ly) < hl[:, 1] - 0.1)
        lamp &= (z[m] > 0.55) & (z[m] < 0.75)
        front = lamp & (lx > 0)
        rear = lamp & (lx < 0)
        c = col[m] * np.where(bumper, 0.45, 1.0)[:, None]
        c[wheel] = 0.05
        c[hub] = 0.55
        c[front] = [0.95, 0.95, 0.85]
        c[rear] = [0.75, 0.05, 0.05]
        out[m] = c
        glow[m] = np.where(front[:, None], [1.0, 1.0, 0.85], np.where(rear[:, None], [0.9, 0.05, 0.05], 0.0))

    m = mat == Material.CABIN
    if m.any():
        bottom = top_z[m] - 2 * half[m, 2]
        glass = side[m] & (z[m] < top_z[m] - 0.08) & (z[m] > np.maximum(bottom + 0.08, top_z[m] - 1.1))
        pillar = (axis[m] == 1) & (np.abs(local[m, 0]) > half[m, 0] - 0.12)
        out[m] = np.where((glass & ~pillar)[:, None], GLASS, col[m])
        refl[obj[m]] = np.where(glass & ~pillar, 0.05, refl[obj[m]])

    m = mat == Material.BUS
    if m.any():
        band = side[m] & (z[m] > 1.2) & (z[m] < top_z[m] - 0.5)
        pillar = (axis[m] == 1) & (np.mod(u[m], 1.3) < 0.14)
        glass = band & ~pillar
        out[m] = np.where(glass[:, None], GLASS, col[m] * np.where(z[m] < 0.35, 0.5, 1.0)[:, None])
        glow[m] = np.where(glass[:, None], [0.45, 0.45, 0.38], 0.0)  # lit cabin
        refl[obj[m]] = np.where(glass, 0.05, refl[obj[m]])

    m = mat == Material.CARGO
    if m.any():
        rib = side[m] & (np.mod(u[m], 0.6) < 0.06)
        out[m] = col[m] * np.where(rib, 0.8, 1.0)[:, None]

    m = (mat == Material.TRUNK) | (mat == Material.FOLIAGE)
    if m.any():
        lp = local[m]
        # Three axis-aligned projections average into blotches with no preferred direction.
        grain = sum(value_noise(lp[:, i], lp[:, j], 0.3, seed + 6 + i) for i, j in ((0, 1), (1, 2), (0, 2))) / 3
        out[m] = col[m] * (0.55 + 0.9 * grain)[:, None]

    m = mat == Material.CLOTH
    if m.any():
        c = col[m].copy()
        c[z[m] < 0.9] = [0.15, 0.16, 0.22]  # trousers
        c[z[m] < 0.08] = [0.05, 0.05, 0.05]  # shoes
        out[m] = c

    m = mat == Material.SKIN
    if m.any():
        out[m] = np.where((local[m, 2] > 0.04)[:, None], [0.18, 0.12, 0.08], col[m])  # hair

    m = mat == Material.LAMP
    if m.any():
        glow[m] = [1.0, 0.92, 0.7]

    albedo[obj] = np.clip(out, 0.0, 1.0)
    emis[obj] = glow
    return Surface(albedo, refl, emis)
