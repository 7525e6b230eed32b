"""Weather variants of a rendered frame, relit from its G-buffer (deterministic per frame and camera).

- ``rain``: overcast light (no sun term), darker wet ground, grey sky, slanted streaks.
- ``fog``: overcast light blended towards grey with exp(-distance / visibility).
- ``night``: faint moonlight, the ego's headlights (cones ahead), street lamps with inverse-square
  falloff, and emission from lit windows, lamps and vehicle lights.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipelines.data.synth.render import GBuffer
from pipelines.data.synth.scene import Scene

FOG_GREY = np.array([0.70, 0.72, 0.74])
HEADLIGHTS_EGO = ((3.6, 0.7, 0.7), (3.6, -0.7, 0.7))


def _overcast(gb: GBuffer, scale: float) -> np.ndarray:
    return gb.albedo_HW3 * scale * (0.75 + 0.25 * gb.normal_HW3[..., 2:3])


def rain(gb: GBuffer, rng: np.random.Generator) -> np.ndarray:
    h, w = gb.sky_HW.shape
    rgb = _overcast(gb, 0.62)
    ground = (gb.normal_HW3[..., 2] > 0.99) & (gb.point_HW3[..., 2] < 0.01) & ~gb.sky_HW
    rgb[ground] *= 0.8  # wet asphalt reads darker
    up = np.clip(gb.dirs_HW3[..., 2:3], 0.0, 1.0)
    rgb = np.where(gb.sky_HW[..., None], 0.50 + 0.08 * up, rgb)
    haze = np.exp(-np.where(gb.sky_HW, np.inf, gb.dist_HW) / 120.0)[..., None]
    rgb = rgb * haze + 0.5 * (1 - haze)
    streaks = np.zeros((h, w), dtype=np.float32)
    n = max(1, h * w // 120)
    length = max(2.0, 0.06 * h)
    x0 = rng.uniform(0, w, n)
    y0 = rng.uniform(-length, h, n)
    lens = length * rng.uniform(0.6, 1.4, n)
    for x, y, ln in zip(x0, y0, lens, strict=True):
        p1 = (round(x), round(y))
        p2 = (round(x - 0.25 * ln), round(y + ln))
        cv2.line(streaks, p1, p2, 1.0, 1, cv2.LINE_AA)
    a = 0.35 * streaks[..., None]
    return np.clip(rgb * (1 - a) + 0.85 * a, 0.0, 1.0)


def fog(gb: GBuffer, visibility_m: float) -> np.ndarray:
    rgb = _overcast(gb, 0.8)
    f = np.exp(-np.where(gb.sky_HW, np.inf, gb.dist_HW) / visibility_m)[..., None]
    return np.clip(rgb * f + FOG_GREY * (1 - f), 0.0, 1.0)


def night(gb: GBuffer, scene: Scene, ego2world_44: np.ndarray) -> np.ndarray:
    p = gb.point_HW3.reshape(-1, 3)
    nrm = gb.normal_HW3.reshape(-1, 3)
    light = np.full((len(p), 3), 0.02)  # moonlight
    fwd = ego2world_44[:3, 0]
    for pos in HEADLIGHTS_EGO:
        src = ego2world_44[:3, :3] @ np.asarray(pos) + ego2world_44[:3, 3]
        v = p - src
        d = np.maximum(np.linalg.norm(v, axis=1), 1e-3)
        cos_a = (v @ fwd) / d
        cone = np.clip((cos_a - np.cos(np.deg2rad(35))) / (np.cos(np.deg2rad(8)) - np.cos(np.deg2rad(35))), 0, 1)
        # Headlights graze the road; a floor on the incidence term keeps the lit patch visible.
        lam = 0.3 + 0.7 * np.clip(-(nrm * v).sum(1) / d, 0, 1)
        light += (1.3 * cone * lam / (1 + (d / 14.0) ** 2))[:, None] * [1.0, 1.0, 0.92]
    lamp_light = np.zeros(len(p))
    for lamp in scene.lamps_L3:
        vx, vy, vz = p[:, 0] - lamp[0], p[:, 1] - lamp[1], p[:, 2] - lamp[2]
        d2 = np.maximum(vx * vx + vy * vy + vz * vz, 1e-6)
        lam = np.clip(-(nrm[:, 0] * vx + nrm[:, 1] * vy + nrm[:, 2] * vz), 0, None) / np.sqrt(d2)
        lamp_light += lam / (1 + d2 / 25.0)
    light += 0.8 * lamp_light[:, None] * [1.0, 0.85, 0.6]
    rgb = gb.albedo_HW3.reshape(-1, 3) * light + 0.9 * gb.emissive_HW3.reshape(-1, 3)
    rgb = rgb.reshape(gb.albedo_HW3.shape)
    up = np.clip(gb.dirs_HW3[..., 2:3], 0.0, 1.0)
    sky = np.array([0.03, 0.04, 0.08]) * (1 - up) + np.array([0.005, 0.01, 0.03]) * up
    return np.clip(np.where(gb.sky_HW[..., None], sky, rgb), 0.0, 1.0)


def render_weather(
    weather: str,
    gb: GBuffer,
    clear_rgb: np.ndarray,
    scene: Scene,
    ego2world_44: np.ndarray,
    visibility_m: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """[H, W, 3] float RGB in [0, 1] of one weather variant."""
    if weather == "clear":
        return clear_rgb
    if weather == "rain":
        return rain(gb, rng)
    if weather == "fog":
        return fog(gb, visibility_m)
    return night(gb, scene, ego2world_44)
