"""Ground truth for generated views: re-render a synthetic_mini frame from any camera pose.

The generator is a pure function of (config, scene index), so the RGB and depth a camera shifted by 1 m would
have seen can be rendered exactly as the dataset's own views were (same shading, same weather noise per camera).
Only synthetic_mini has this; real datasets have ground truth at the recorded poses only.
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipelines.data.layout import CAMERAS, WEATHERS, DataError
from pipelines.data.synth.camera import make_rig
from pipelines.data.synth.config import SynthConfig, coerce_config
from pipelines.data.synth.render import render_gbuffer, shade_clear
from pipelines.data.synth.scenarios import generate_scene
from pipelines.data.synth.scene import Scene
from pipelines.data.synth.weather import render_weather

SOURCE = "synthetic_mini"


def generator_config(root: str | Path) -> SynthConfig:
    """The ``SynthConfig`` a synthetic_mini root was built with (from its ``dataset.json``)."""
    meta_path = Path(root) / "dataset.json"
    if not meta_path.is_file():
        raise DataError(f"{root}: not a gdwm dataset (dataset.json missing)")
    meta = json.loads(meta_path.read_text())
    if meta.get("source") != SOURCE:
        raise DataError(
            f"{root}: novel-view ground truth exists only for {SOURCE} datasets (this one is '{meta.get('source')}')"
        )
    return coerce_config(meta["generator"]["config"])


@lru_cache(maxsize=8)
def _scene(cfg_json: str, index: int) -> Scene:
    return generate_scene(coerce_config(json.loads(cfg_json)), index)


def render_view(
    root: str | Path,
    scene_id: str,
    frame: int,
    camera: str,
    sensor2ego_44: np.ndarray | None = None,
    weather: str = "clear",
) -> tuple[np.ndarray, np.ndarray]:
    """``(rgb [H, W, 3] uint8, depth [H, W] float32 metres)`` of ``camera`` at ``frame``, moved to ``sensor2ego_44``
    (the recorded pose when None). ``scene_id`` must be one of the root's ``scene-NNNN``."""
    cfg = generator_config(root)
    where = f"{scene_id}/frame_{frame:03d} {camera}"
    if camera not in CAMERAS:
        raise DataError(f"{where}: unknown camera (cameras: {list(CAMERAS)})")
    if weather not in WEATHERS or weather not in cfg.weathers:
        raise DataError(f"{where}: unknown weather '{weather}' (dataset has {list(cfg.weathers)})")
    try:
        index = int(scene_id.removeprefix("scene-"))
    except ValueError:
        raise DataError(f"{where}: not a synthetic_mini scene id (expected scene-NNNN)") from None
    if not (0 <= index < cfg.num_scenes and 0 <= frame < cfg.num_frames):
        raise DataError(f"{where}: out of range ({cfg.num_scenes} scenes x {cfg.num_frames} frames)")
    scene = _scene(json.dumps(cfg.__dict__, sort_keys=True, default=list), index)
    ci = CAMERAS.index(camera)
    cam = make_rig(cfg.width, cfg.height)[ci]
    if sensor2ego_44 is not None:
        cam = replace(cam, sensor2ego_44=np.asarray(sensor2ego_44, dtype=np.float64))
    ego2world = scene.ego2world(frame)
    gb = render_gbuffer(scene, scene.primitives(frame), cam, ego2world, cfg.max_depth_m)
    clear = shade_clear(gb, scene.sun_dir, scene.index)
    # the same noise stream as the stored view of this camera (build.py), so a zero shift reproduces it exactly
    rng = np.random.default_rng([cfg.seed, scene.index, frame, ci, list(cfg.weathers).index(weather)])
    rgb = render_weather(weather, gb, clear, scene, ego2world, cfg.fog_visibility_m, rng)
    rgb = np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)  # as DatasetWriter stores it
    return rgb, gb.depth_HW.astype(np.float32)
