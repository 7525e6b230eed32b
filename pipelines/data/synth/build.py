"""``build``: generate the ``synthetic_mini`` dataset into the NuScenes-GSQA layout.

Per scene: the procedural scene (``scenarios``), then per frame the primitives at that time,
6 camera G-buffers (RGB per weather, depth, instance ids -> 2D boxes), a LiDAR sweep and the
3D boxes; finally the scene's QA from the rows as written. Scenes are independent and every
random draw is seeded by (seed, scene, frame, camera, weather), so a seed fixes every byte.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.data.layout import (
    ROUTES_FILE,
    DataError,
    DatasetWriter,
    content_params,
    depth_relpath,
    flat_pose,
    image_relpath,
    lidar_relpath,
)
from pipelines.data.synth.camera import LIDAR_MOUNT, make_rig
from pipelines.data.synth.config import SynthConfig, coerce_config, validate
from pipelines.data.synth.lidar import beam_directions, sweep
from pipelines.data.synth.planning import WINDOW
from pipelines.data.synth.qa import FrameTruth, SceneTruth, scene_qa
from pipelines.data.synth.render import GBuffer, render_gbuffer, shade_clear
from pipelines.data.synth.route import planned_route
from pipelines.data.synth.scenarios import generate_scene, lateral_truth
from pipelines.data.synth.scene import Scene
from pipelines.data.synth.weather import render_weather

log = logging.getLogger(__name__)
SOURCE = "synthetic_mini"
GENERATOR_VERSION = 3
"""Bump when the generator's output changes for the same config."""
_BASE_TIME_US = 1_600_000_000_000_000


def _f32(values) -> list[float]:
    """Values rounded to float32, so rows, QA and the stored tables agree bit for bit."""
    return [float(v) for v in np.asarray(values, dtype=np.float32).reshape(-1)]


def num_val_scenes(num_scenes: int, val_fraction: float) -> int:
    """Scenes in ``val`` (the last ones): round(n * fraction), at least 1 if n >= 2 and fraction > 0, at most n - 1."""
    if num_scenes < 2 or val_fraction <= 0:
        return 0
    return min(num_scenes - 1, max(1, round(num_scenes * val_fraction)))


def _boxes3d(scene: Scene, frame: int, ego2world: np.ndarray, max_range: float) -> list[dict]:
    world2ego = np.linalg.inv(ego2world)
    ego_yaw = float(scene.ego_state.yaw_T[frame])
    rows = []
    for actor, st in zip(scene.actors, scene.actor_states, strict=True):
        x, y = st.xy_T2[frame]
        center = world2ego @ np.array([x, y, actor.size[2] / 2, 1.0])
        if np.hypot(center[0], center[1]) > max_range:
            continue
        yaw = float(np.arctan2(np.sin(st.yaw_T[frame] - ego_yaw), np.cos(st.yaw_T[frame] - ego_yaw)))
        vel = world2ego[:2, :2] @ st.velocity_T2[frame]
        rows.append(
            {
                "scene_id": scene.scene_id,
                "frame_idx": frame,
                "instance_id": actor.instance_id,
                "category": actor.category,
                "attribute": actor.attribute(float(st.speed_T[frame])),
                "center": _f32(center[:3]),
                "size": _f32(actor.size),
                "yaw": _f32([yaw])[0],
                "velocity": _f32(vel),
            }
        )
    return rows


def _boxes2d(scene: Scene, frame: int, camera: str, gb: GBuffer, annotated: set[str], min_pixels: int) -> list[dict]:
    """Tight boxes of each annotated agent's visible pixels (x2, y2 exclusive)."""
    ids = gb.actor_HW.reshape(-1)
    counts = np.bincount(ids[ids >= 0], minlength=len(scene.actors))
    rows = []
    for a in np.flatnonzero(counts >= min_pixels):
        actor = scene.actors[a]
        if actor.instance_id not in annotated:
            continue
        ys, xs = np.nonzero(gb.actor_HW == a)
        rows.append(
            {
                "scene_id": scene.scene_id,
                "frame_idx": frame,
                "camera": camera,
                "instance_id": actor.instance_id,
                "box": _f32([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]),
                "visible_fraction": _f32([min(1.0, counts[a] / max(int(gb.coverage_A[a]), 1))])[0],
            }
        )
    return rows


def _frame_token(seed: int, scene_id: str, frame: int) -> str:
    return hashlib.sha1(f"{SOURCE}/{seed}/{scene_id}/{frame}".encode()).hexdigest()[:32]


class _SceneSink:
    """Writes a scene's files straight into the dataset's temp dir and keeps its table rows.

    Lets worker processes render scenes in parallel; the parent adds the rows in scene order,
    so tables do not depend on which worker finished first.
    """

    def __init__(self, tmp: Path):
        self.files = DatasetWriter.files_into(tmp)  # publishing stays with the parent's writer
        self.rows: list[tuple[str, dict]] = []

    def add(self, table: str, **row) -> None:
        self.rows.append((table, row))

    def extend(self, table: str, rows: list[dict]) -> None:
        self.rows.extend((table, r) for r in rows)

    def write_image(self, rel: str, rgb_HW3: np.ndarray) -> None:
        self.files.write_image(rel, rgb_HW3)

    def write_depth(self, rel: str, depth_HW: np.ndarray) -> None:
        self.files.write_depth(rel, depth_HW)

    def write_lidar(self, rel: str, points_N4: np.ndarray) -> None:
        self.files.write_lidar(rel, points_N4)


def _scene_job(cfg: SynthConfig, index: int, tmp: Path, split: str, horizon: int) -> tuple[dict, list, int]:
    """Generate, render and write scene ``index``; returns (scenario facts and the planned route, table rows, QA
    count)."""
    scene = generate_scene(cfg, index)
    sink = _SceneSink(tmp)
    n_qa = _write_scene(sink, cfg, scene, split, horizon)
    route = np.round(planned_route(scene), 3).tolist()
    return {"scenario": scene.scenario, **scene.meta, "route": route}, sink.rows, n_qa


def _write_scene(w: _SceneSink, cfg: SynthConfig, scene: Scene, split: str, horizon: int) -> int:
    """Render and write one scene; returns its QA count."""
    sid = scene.scene_id
    rig = make_rig(cfg.width, cfg.height)
    lidar_dirs = beam_directions(cfg.lidar_beams, cfg.lidar_azimuth_steps)
    w.add(
        "scenes",
        scene_id=sid,
        name=sid,
        num_frames=cfg.num_frames,
        frame_rate_hz=cfg.frame_rate_hz,
        description=scene.description,
        weathers=list(cfg.weathers),
        source=SOURCE,
    )
    for cam in rig:
        w.add(
            "cameras",
            scene_id=sid,
            camera=cam.name,
            width=cam.width,
            height=cam.height,
            fx=cam.fx,
            fy=cam.fy,
            cx=cam.cx,
            cy=cam.cy,
            sensor2ego=flat_pose(cam.sensor2ego_44),
        )
    truths = []
    poses = []
    for f in range(cfg.num_frames):
        ego2world = scene.ego2world(f)
        stored_pose = _f32(ego2world)
        poses.append(stored_pose)
        timestamp = _BASE_TIME_US + scene.index * 3_600_000_000 + round(f * 1e6 / cfg.frame_rate_hz)
        w.add("frames", scene_id=sid, frame_idx=f, timestamp_us=timestamp, token=_frame_token(cfg.seed, sid, f))
        w.add("ego_poses", scene_id=sid, frame_idx=f, ego2world=stored_pose)
        prims = scene.primitives(f)
        rows3d = _boxes3d(scene, f, ego2world, cfg.box_range_m)
        annotated = {r["instance_id"] for r in rows3d}
        rows2d = []
        for ci, cam in enumerate(rig):
            gb = render_gbuffer(scene, prims, cam, ego2world, cfg.max_depth_m)
            clear = shade_clear(gb, scene.sun_dir, scene.index)
            for wi, weather in enumerate(cfg.weathers):
                rng = np.random.default_rng([cfg.seed, scene.index, f, ci, wi])
                rgb = render_weather(weather, gb, clear, scene, ego2world, cfg.fog_visibility_m, rng)
                w.write_image(image_relpath(sid, cam.name, f, weather), rgb)
            w.write_depth(depth_relpath(sid, cam.name, f), gb.depth_HW)
            rows2d += _boxes2d(scene, f, cam.name, gb, annotated, cfg.min_box_pixels)
        w.write_lidar(lidar_relpath(sid, f), sweep(scene, prims, ego2world, lidar_dirs, cfg.lidar_range_m))
        w.extend("boxes3d", rows3d)
        w.extend("boxes2d", rows2d)
        truths.append(FrameTruth(f, rows3d, rows2d))
    truth = SceneTruth(
        scene_id=sid,
        split=split,
        width=cfg.width,
        height=cfg.height,
        rate_hz=cfg.frame_rate_hz,
        ego2world_F44=np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4),
        frames=truths,
        looks={a.instance_id: (a.kind, a.colour) for a in scene.actors},
        direction_truth=lambda f, h: lateral_truth(scene, f, h),
    )
    rows = scene_qa(truth, cfg.seed, scene.index, cfg.qa_per_task, horizon, cfg.min_referent_pixels)
    w.extend("qa", rows)
    return len(rows)


def _usable_cpus() -> int:
    """CPUs this process may run on (a Ray worker or a cgroup may allow fewer than the machine has)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def build(cfg: Any, root: str | Path, source: str | None = None, overwrite: bool = False) -> Path:
    """Generate ``synthetic_mini`` at ``root`` (published atomically) and return ``root``.

    ``cfg`` is a ``SynthConfig`` or the composed ``data`` node. The generator reads no input,
    so ``source`` must be None.
    """
    if source is not None:
        raise DataError(f"synthetic_mini reads no input data: source must be None, got {source!r}")
    cfg = coerce_config(cfg)
    validate(cfg)
    root = Path(root)
    horizon = max(1, round(cfg.plan_horizon_s * cfg.frame_rate_hz))
    skipped = {}
    if cfg.num_frames < WINDOW:
        skipped["traj"] = f"needs data.num_frames >= {WINDOW} (4 history + 6 future frames), got {cfg.num_frames}"
    if cfg.num_frames <= horizon:
        skipped["plan"] = (
            f"needs data.num_frames > {horizon} (plan_horizon_s x frame_rate_hz frames of future), got {cfg.num_frames}"
        )
    for task, why in skipped.items():
        log.warning("synthetic_mini: no %s QA: %s", task, why)
    n_val = num_val_scenes(cfg.num_scenes, cfg.val_fraction)
    t0 = time.perf_counter()
    scenarios = []
    workers = min(cfg.num_scenes, cfg.num_workers or _usable_cpus())
    params = content_params(cfg, SynthConfig, skip=("num_workers",))  # every byte follows from these
    with DatasetWriter(root, name=cfg.name, source=SOURCE, overwrite=overwrite, params=params) as w:
        assert w.tmp is not None
        jobs = [
            (cfg, i, w.tmp, "val" if i >= cfg.num_scenes - n_val else "train", horizon) for i in range(cfg.num_scenes)
        ]
        if workers > 1:
            # spawn, not fork: the caller may hold threads (Ray, torch) that fork would copy half-alive.
            ctx = multiprocessing.get_context("spawn")
            pool = ProcessPoolExecutor(workers, mp_context=ctx)
            try:
                results = list(pool.map(_scene_job, *zip(*jobs, strict=True)))
            finally:  # interrupted (SIGTERM, Ctrl-C, a failed scene): drop the queued scenes, then the temp dir goes
                pool.shutdown(wait=True, cancel_futures=True)
        else:
            results = [_scene_job(*job) for job in jobs]
        routes = {}
        for (_, i, _, split, _), (facts, rows, n_qa) in zip(jobs, results, strict=True):
            routes[f"scene-{i:04d}"] = facts.pop("route")
            for table, row in rows:
                w.add(table, **row)
            scenarios.append(facts)
            log.info("synthetic_mini: scene-%04d (%s, %s) %d QA", i, facts["scenario"], split, n_qa)
        log.info("synthetic_mini: %d scenes in %.1f s (%d workers)", cfg.num_scenes, time.perf_counter() - t0, workers)
        w.extra_meta["generator"] = {
            "name": SOURCE,
            "version": GENERATOR_VERSION,
            "config": {
                k: v
                for k, v in asdict(cfg).items()
                if k not in ("root", "builder", "build_command", "summarizer", "num_workers", "tables")
            },
            "resolution": [cfg.width, cfg.height],
            "scenarios": [f["scenario"] for f in scenarios],
            "scene_facts": {f"scene-{i:04d}": f for i, f in enumerate(scenarios)},
            "val_scenes": [f"scene-{i:04d}" for i in range(cfg.num_scenes - n_val, cfg.num_scenes)],
            "plan_horizon_frames": horizon,
            "lidar_mount": list(LIDAR_MOUNT),
            "skipped_tasks": skipped,
        }
        # a file, not a dataset.json key: the dataset fingerprint (and so every stage key) covers it
        w.path(ROUTES_FILE).write_text(json.dumps(routes, sort_keys=True))
    return root
