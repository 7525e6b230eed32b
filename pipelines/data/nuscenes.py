"""nuScenes v1.0 -> NuScenes-GSQA layout converter (``gdwm data convert-nuscenes source=DIR``).

``source`` is a nuScenes root: ``<version>/*.json`` tables plus the ``samples/`` files they name.
One frame per keyframe sample, in ``next`` order. Per frame:

- ego pose: the ``LIDAR_TOP`` keyframe's ego pose; boxes and LiDAR are in that ego frame;
- LiDAR: ``LIDAR_TOP`` points moved from the lidar to the ego frame;
- images: each camera keyframe resized to ``width x height``; intrinsics scaled to match;
- boxes3d: annotations in the ego frame, size (l, w, h), velocity from neighbouring annotations;
- boxes2d: each box projected with the camera's *own* ego pose (cameras fire up to ~40 ms from the
  lidar), clipped at the near plane and to the image.

Limits: ``cameras`` holds one sensor->ego per scene, so a camera's stored extrinsics relative to
the frame's (lidar-time) ego pose are off by the ego motion between the two timestamps; raw
nuScenes has no QA (the qa table is empty) and the official train/val lists live in the devkit,
so ``val_fraction`` splits scenes by name instead (``dataset.json`` records the split).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from annotated_types import Ge, Interval

from pipelines.data.config import DatasetConfig
from pipelines.data.layout import (
    CAMERAS,
    DataError,
    DatasetWriter,
    content_params,
    flat_pose,
    image_relpath,
    lidar_relpath,
)
from pipelines.data.nuscenes_boxes import box3d_row, corners_world, project_box, scale_intrinsics
from pipelines.data.nuscenes_sensors import lidar_to_ego, read_image_rgb, read_lidar, resize
from pipelines.data.nuscenes_tables import NuScenesTables
from pipelines.data.scene_splits import split_scenes

log = logging.getLogger(__name__)

KEYFRAME_HZ = 2.0  # nominal nuScenes keyframe rate, used for one-sample scenes


@dataclass
class NuScenesConfig(DatasetConfig):
    """Conversion of a nuScenes v1.0 release (tables read with ``json``, no devkit)."""

    name: str = "nuscenes"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    builder: str = "pipelines.data.nuscenes.build"
    """Dotted path of the converter."""
    build_command: str | None = "gdwm data convert-nuscenes"
    """Converts it from ``source=DIR``."""
    version: str = "v1.0-mini"
    """Table folder under the source: ``v1.0-mini`` or ``v1.0-trainval``."""
    cameras: list[str] = field(default_factory=lambda: list(CAMERAS))
    """Cameras to convert (nuScenes channel names)."""
    width: Annotated[int, Ge(1)] = 400
    """Stored image width; 400x225 is a quarter of nuScenes' 1600x900 (same 16:9), readable for grounding."""
    height: Annotated[int, Ge(1)] = 225
    """Stored image height; intrinsics are scaled to it."""
    max_scenes: Annotated[int, Ge(0)] = 0
    """Convert at most this many scenes (after ``scenes``, in name order); 0 = all."""
    scenes: list[str] = field(default_factory=list)
    """Scene names to convert (e.g. ``scene-0061``); empty = every scene of the version."""
    lidar: bool = True
    """Write ``LIDAR_TOP`` points per frame."""
    val_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.2
    """Share of the converted scenes (the last, by name) recorded as ``val`` in ``dataset.json``."""


@dataclass
class _Camera:
    K_33: np.ndarray  # of the stored (resized) image
    sensor2ego_44: np.ndarray
    calibration_token: str
    source_size: tuple[int, int]  # (width, height) of the raw images


def build(cfg: NuScenesConfig, root: Path, source: str | None, overwrite: bool = False) -> Path:
    """Convert ``source`` (a nuScenes root) into a dataset at ``root``; returns the published root."""
    _check_config(cfg)
    if source is None:
        raise DataError(f"source= is required: the nuScenes root holding {cfg.version}/ and samples/")
    src = Path(source).expanduser().resolve()
    if not src.is_dir():
        raise DataError(f"source={source}: no such directory")
    tables = NuScenesTables(src, cfg.version)
    scenes = _select_scenes(tables, cfg)
    names = sorted(s["name"] for s in scenes)
    params = content_params(cfg, NuScenesConfig)  # the conversion options; the nuScenes files are source=
    with DatasetWriter(root, cfg.name, source=f"{src} ({cfg.version})", overwrite=overwrite, params=params) as w:
        for scene in scenes:
            _SceneWriter(w, tables, cfg, scene).write()
        w.extra_meta = {
            "format": "nuscenes",
            "version": cfg.version,
            "image_size": [cfg.width, cfg.height],
            "ego_pose": "LIDAR_TOP keyframe ego pose; boxes3d and lidar are in this ego frame",
            "boxes2d": "projected with each camera's own ego pose, near-plane clipped, hull intersected with image",
            "velocity": "from neighbouring annotations (nuScenes box_velocity); 0 where unknown",
            "qa": "none: raw nuScenes has no QA",
            "scene_splits": split_scenes(names, cfg.val_fraction),
            "scene_tokens": {s["name"]: s["token"] for s in scenes},  # benchmarks' QA name scenes by token
            "modalities": {"images": True, "cameras": True, "lidar": cfg.lidar, "boxes": True, "gaussians": False},
        }
    return w.root


def _check_config(cfg: NuScenesConfig) -> None:
    for cam in cfg.cameras:
        if cam not in CAMERAS:
            raise DataError(f"cameras=: unknown camera '{cam}' (valid: {', '.join(CAMERAS)})")
    if not cfg.cameras:
        raise DataError(f"cameras=: empty (valid: {', '.join(CAMERAS)})")
    if cfg.width <= 0 or cfg.height <= 0:
        raise DataError(f"width={cfg.width} height={cfg.height}: image size must be positive")


def _select_scenes(tables: NuScenesTables, cfg: NuScenesConfig) -> list[dict]:
    by_name = {s["name"]: s for s in tables.scenes()}
    if cfg.scenes:
        unknown = [n for n in cfg.scenes if n not in by_name]
        if unknown:
            raise DataError(f"scenes=: unknown scene(s) {unknown} in {cfg.version} (has {sorted(by_name)})")
        chosen = [by_name[n] for n in dict.fromkeys(cfg.scenes)]
    else:
        chosen = list(by_name.values())
    return chosen[: cfg.max_scenes] if cfg.max_scenes > 0 else chosen


class _SceneWriter:
    """Writes one scene; keeps its camera models (the layout has one calibration per camera and scene)."""

    def __init__(self, w: DatasetWriter, tables: NuScenesTables, cfg: NuScenesConfig, scene: dict):
        self.w, self.t, self.cfg, self.scene = w, tables, cfg, scene
        self.sid: str = scene["name"]
        self.cameras: dict[str, _Camera] = {}

    def write(self) -> None:
        samples = self.t.samples(self.scene)
        span_s = 1e-6 * (samples[-1]["timestamp"] - samples[0]["timestamp"])
        self.w.add(
            "scenes",
            scene_id=self.sid,
            name=self.sid,
            num_frames=len(samples),
            frame_rate_hz=(len(samples) - 1) / span_s if span_s > 0 else KEYFRAME_HZ,
            description=self.scene.get("description", ""),
            weathers=["clear"],  # the real images; no synthetic weather variants
            source=f"nuscenes/{self.t.version}",
        )
        for idx, sample in enumerate(samples):
            self._frame(idx, sample)
        log.info("%s: %d frames", self.sid, len(samples))

    def _frame(self, idx: int, sample: dict) -> None:
        t, w, sid, where = self.t, self.w, self.sid, f"{self.sid}/frame_{idx:03d}"
        lidar_sd = t.keyframe(sample, "LIDAR_TOP", where)
        ego2world = t.ego2world(lidar_sd)
        w.add("frames", scene_id=sid, frame_idx=idx, timestamp_us=int(sample["timestamp"]), token=sample["token"])
        w.add("ego_poses", scene_id=sid, frame_idx=idx, ego2world=flat_pose(ego2world))
        if self.cfg.lidar:
            points = read_lidar(t.source / lidar_sd["filename"], f"{where} LIDAR_TOP")
            w.write_lidar(lidar_relpath(sid, idx), lidar_to_ego(points, t.sensor2ego(lidar_sd)))
        anns = t.annotations(sample)
        world2ego = np.linalg.inv(ego2world)
        w.extend("boxes3d", [{"scene_id": sid, "frame_idx": idx, **box3d_row(t, a, world2ego)} for a in anns])
        corners = [(a["instance_token"], corners_world(a)) for a in anns]
        for cam in self.cfg.cameras:
            sd = t.keyframe(sample, cam, where)
            rgb = read_image_rgb(t.source / sd["filename"], f"{where} {cam}")
            camera = self._camera(cam, sd, (rgb.shape[1], rgb.shape[0]), f"{where} {cam}")
            w.write_image(image_relpath(sid, cam, idx), resize(rgb, self.cfg.width, self.cfg.height))
            # The image was taken at the camera's timestamp: project with that ego pose, not the lidar's.
            world2cam = np.linalg.inv(camera.sensor2ego_44) @ np.linalg.inv(t.ego2world(sd))
            for instance, corners_83 in corners:
                cam_83 = corners_83 @ world2cam[:3, :3].T + world2cam[:3, 3]
                seen = project_box(cam_83, camera.K_33, self.cfg.width, self.cfg.height)
                if seen is not None:
                    w.add(
                        "boxes2d",
                        scene_id=sid,
                        frame_idx=idx,
                        camera=cam,
                        instance_id=instance,
                        box=seen[0],
                        visible_fraction=seen[1],
                    )

    def _camera(self, cam: str, sd: dict, size: tuple[int, int], where: str) -> _Camera:
        """The scene's model of ``cam``, made (and its cameras row added) at its first image, checked after."""
        known = self.cameras.get(cam)
        if known is not None:
            if sd["calibrated_sensor_token"] != known.calibration_token:
                raise DataError(f"{where}: calibration changes within the scene (the layout keeps one per scene)")
            if size != known.source_size:
                first = f"{known.source_size[0]}x{known.source_size[1]}"
                raise DataError(f"{where}: image is {size[0]}x{size[1]}, the scene's first {cam} image {first}")
            return known
        calib = self.t.calibration(sd)
        k_raw = np.asarray(calib.get("camera_intrinsic") or [], dtype=np.float64)
        if k_raw.shape != (3, 3):
            raise DataError(f"{where}: calibrated_sensor {calib['token']} has no 3x3 camera_intrinsic")
        K = scale_intrinsics(k_raw, self.cfg.width / size[0], self.cfg.height / size[1])
        camera = self.cameras[cam] = _Camera(K, self.t.sensor2ego(sd), calib["token"], size)
        self.w.add(
            "cameras",
            scene_id=self.sid,
            camera=cam,
            width=self.cfg.width,
            height=self.cfg.height,
            fx=K[0, 0],
            fy=K[1, 1],
            cx=K[0, 2],
            cy=K[1, 2],
            sensor2ego=flat_pose(camera.sensor2ego_44),
        )
        return camera
