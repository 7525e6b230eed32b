"""Target cameras and the low-level conditions C_I, C_D projected into them (Sec. Instruction-controllable 4D Scene
Generation: Low-level Conditions; Spatiotemporal Generation and 4D Editing).

A target is the current camera shifted laterally/longitudinally in the ego frame (spatial generation, "1 m or 2 m")
or the same camera on the future ego pose 1 s / 2 s ahead (temporal generation). Either way the target camera is
expressed in the CURRENT frame's ego coordinates, where that frame's Gaussians live, so the projection is one
rasterisation with ego = world.

Legend: N Gaussians, F frames, H x W target image. Ego frame x forward, y left, z up; camera frame OpenCV
(x right, y down, z forward); ``sensor2ego_44`` maps camera -> ego (``pipelines.data.layout``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from model_zoo.render import Camera, RenderOutput, rasterize


class NoGaussiansInView(ValueError):
    """The target camera sees none of the frame's Gaussians: there is nothing to condition on."""


@dataclass
class Conditions:
    """Sparse condition maps of one target view (C_I, C_D and where they hold)."""

    rgb: np.ndarray
    """``[H, W, 3]`` float32 in [0, 1]: C_I, the Gaussians' colour (un-premultiplied by alpha); 0 outside ``mask``."""
    depth: np.ndarray
    """``[H, W]`` float32 camera-z metres: C_D; 0 outside ``mask``."""
    mask: np.ndarray
    """``[H, W]`` bool: pixels the projected Gaussians cover (accumulated alpha >= the threshold)."""


# ----------------------------------------------------------------------------- target poses


def shifted_camera_pose(sensor2ego_44: np.ndarray, lateral_m: float = 0.0, longitudinal_m: float = 0.0) -> np.ndarray:
    """The camera moved by ``lateral_m`` along ego +y (left) and ``longitudinal_m`` along ego +x (forward); its
    orientation is kept. Returns the new camera -> ego ``[4, 4]``."""
    out = np.array(sensor2ego_44, dtype=np.float64, copy=True)
    out[0, 3] += longitudinal_m
    out[1, 3] += lateral_m
    return out


def horizon_frames(seconds: float, frame_rate_hz: float) -> int:
    """Frames ahead of a temporal target: ``round(seconds * frame_rate_hz)``."""
    if frame_rate_hz <= 0:
        raise ValueError(f"frame_rate_hz must be > 0, got {frame_rate_hz}")
    return round(seconds * frame_rate_hz)


def future_camera_pose(
    ego2world_F44: np.ndarray, frame: int, horizon_frames: int, sensor2ego_44: np.ndarray, *, scene: str = "scene"
) -> np.ndarray:
    """The camera on the ego pose ``horizon_frames`` after ``frame``, seen from ``frame``'s ego frame:
    ``inv(ego2world[frame]) @ ego2world[frame + h] @ sensor2ego`` (camera -> current ego, ``[4, 4]``)."""
    poses = np.asarray(ego2world_F44, dtype=np.float64)
    n = len(poses)
    if not 0 <= frame < n:
        raise ValueError(f"{scene}/frame_{frame:03d}: frame out of range (scene has {n} frames)")
    if horizon_frames < 0 or frame + horizon_frames >= n:
        raise ValueError(
            f"{scene}/frame_{frame:03d}: horizon {horizon_frames} frames reaches frame {frame + horizon_frames}, "
            f"outside the scene's {n} frames"
        )
    future_to_now = np.linalg.inv(poses[frame]) @ poses[frame + horizon_frames]
    return future_to_now @ np.asarray(sensor2ego_44, dtype=np.float64)


def _num(v: float) -> str:
    """Shortest round-tripping text of a number, without a trailing ``.0`` (``2``, ``-1.5``)."""
    s = repr(float(v))
    return s[:-2] if s.endswith(".0") else s


def target_name(lateral_m: float = 0.0, longitudinal_m: float = 0.0, future_s: float | None = None) -> str:
    """Metric name of a target (``gen/<target>/...``): ``shift_1m``, ``shift_-2m`` (lateral), ``shift_long_2m``,
    ``shift_1m_long_2m`` (both), ``future_1s``, ``future_2s``."""
    if future_s is not None:
        if lateral_m or longitudinal_m:
            raise ValueError(
                f"a target is a spatial shift or a future horizon, got lateral={lateral_m} m, "
                f"longitudinal={longitudinal_m} m and future={future_s} s"
            )
        return f"future_{_num(future_s)}s"
    parts = []
    if lateral_m or not longitudinal_m:
        parts.append(f"shift_{_num(lateral_m)}m")
    if longitudinal_m:
        parts.append(f"long_{_num(longitudinal_m)}m" if parts else f"shift_long_{_num(longitudinal_m)}m")
    return "_".join(parts)


# ----------------------------------------------------------------------------- projection


def ego_camera(K_33: np.ndarray, sensor2ego_44: np.ndarray, width: int, height: int) -> Camera:
    """The rasterizer camera of a view whose "world" is the current ego frame.

    Same path as ``pipelines.recon.init.load_views`` (``world2cam = inv(ego2world @ sensor2ego)``) with
    ``ego2world = I``.
    """
    ego2world = np.eye(4)  # the current ego frame is the world of the frame's Gaussians
    world2cam = np.linalg.inv(ego2world @ np.asarray(sensor2ego_44, dtype=np.float64))
    return Camera.from_numpy(K_33, world2cam, width, height)


def render_ego(
    gaussians: dict[str, np.ndarray],
    K_33: np.ndarray,
    sensor2ego_44: np.ndarray,
    width: int,
    height: int,
    backend: str = "auto",
) -> RenderOutput:
    """Rasterize ego-frame Gaussians (the layout's schema: activated values) into a camera given camera -> ego."""
    t = {k: torch.from_numpy(np.array(gaussians[k], dtype=np.float32)) for k in ("xyz", "scale", "rotation", "color")}
    opacity = torch.as_tensor(np.asarray(gaussians["opacity"], dtype=np.float32).reshape(-1))
    with torch.no_grad():
        return rasterize(
            t["xyz"].reshape(-1, 3),
            t["scale"].reshape(-1, 3),
            t["rotation"].reshape(-1, 4),
            opacity,
            t["color"].reshape(-1, 3),
            ego_camera(K_33, sensor2ego_44, width, height),
            backend=backend,
        )


def low_level_conditions(
    gaussians: dict[str, np.ndarray],
    K_33: np.ndarray,
    sensor2ego_44: np.ndarray,
    width: int,
    height: int,
    *,
    scene: str,
    frame: int,
    alpha_threshold: float = 0.5,
    target: str | None = None,
    backend: str = "auto",
) -> Conditions:
    """C_I and C_D: the frame's ego-frame Gaussians rasterized into the target camera.

    ``mask`` = accumulated alpha >= ``alpha_threshold``; inside it ``rgb`` is the composited colour divided by alpha
    (so coverage does not darken the cue, as depth is normalised), outside it both maps are 0. ``target`` names the
    pose in errors (default: the camera's ego position). A target with no Gaussians in view -> ``NoGaussiansInView``.
    """
    if not 0.0 < alpha_threshold <= 1.0:
        raise ValueError(f"{scene}/frame_{frame:03d}: alpha_threshold must be in (0, 1], got {alpha_threshold}")
    out = render_ego(gaussians, K_33, sensor2ego_44, width, height, backend)
    if out.n_visible == 0:
        if target is None:
            x, y, z = np.asarray(sensor2ego_44, dtype=np.float64)[:3, 3]
            target = f"camera at ego ({x:.2f}, {y:.2f}, {z:.2f}) m"
        raise NoGaussiansInView(f"{scene}/frame_{frame:03d}: no Gaussians in view of the target camera ({target})")
    alpha = out.alpha.numpy()
    mask = alpha >= alpha_threshold
    rgb = np.where(mask[..., None], out.rgb.numpy() / np.maximum(alpha, 1e-6)[..., None], 0.0)
    depth = np.where(mask, out.depth.numpy(), 0.0)
    return Conditions(np.clip(rgb, 0.0, 1.0).astype(np.float32), depth.astype(np.float32), mask)
