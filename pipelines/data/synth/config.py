"""Config of the ``synthetic_mini`` procedural dataset (``conf/data/synthetic_mini.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Annotated, Any

from annotated_types import Ge, Gt, Interval

from pipelines.data.config import SEED, DatasetConfig
from pipelines.data.layout import WEATHERS, DataError

SCENARIOS = ("curve", "stop", "lane_change", "start", "follow", "cruise")
"""Ego behaviours, one per scene (see ``pipelines.data.synth.scenarios``)."""


SYNTH_TABLES = ("boxes2d", "boxes3d", "cameras", "depth", "ego_poses", "frames", "images", "lidar", "qa", "routes",
                "scenes")  # fmt: skip


@dataclass
class SynthConfig(DatasetConfig):
    """Procedural driving scenes with 6 surround cameras, LiDAR, boxes and QA of every task family."""

    name: str = "synthetic_mini"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    builder: str = "pipelines.data.synth.build.build"
    """Dotted path of the generator."""
    build_command: str | None = "gdwm data synth"
    """Generates it (``gdwm run`` does too, when it is absent)."""
    needs_source: bool = False
    """Generated from the seed: no input directory, so `gdwm run` makes it when absent."""
    planner: str | None = "pipelines.data.synth.config.planned_scenes"
    """Checks the keys and names the scenes without generating anything (``gdwm run --dry-run``)."""
    tables: list[str] = field(default_factory=lambda: list(SYNTH_TABLES))
    """Everything: cameras, images, depth, LiDAR, poses, boxes, QA and planned routes."""
    num_scenes: Annotated[int, Ge(1)] = 4
    """Scenes to generate (``scene-0000`` ...)."""
    num_frames: Annotated[int, Ge(1)] = 10
    """Frames per scene; trajectory QA needs >= 10 (4 history + 6 future) and is skipped below that."""
    frame_rate_hz: Annotated[float, Gt(0)] = 2.0
    """Frame rate (nuScenes keyframes are 2 Hz)."""
    width: Annotated[int, Ge(1)] = 160
    """Image width in pixels (intrinsics are nuScenes' 1600x900 ones scaled to it)."""
    height: Annotated[int, Ge(1)] = 90
    """Image height in pixels."""
    seed: Annotated[int, SEED] = 0
    """Master seed; scene ``i`` draws from ``default_rng([seed, i])``, so a seed fixes every byte."""
    weathers: list[str] = field(default_factory=lambda: list(WEATHERS))
    """Weather variants rendered per frame; must include ``clear`` (the ``images/`` folder)."""
    val_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.25
    """Fraction of scenes (the last ones) whose QA is split ``val``; at least one when num_scenes >= 2."""
    scenarios: list[str] = field(default_factory=lambda: list(SCENARIOS))
    """Ego behaviours to draw from; scenes cycle through a seeded permutation of them."""
    num_vehicles: Annotated[int, Ge(0)] = 10
    """Other vehicles per scene (cars, trucks, buses; fewer when placement finds no free spot)."""
    parked_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.4
    """Fraction of the other vehicles parked at the kerb."""
    num_pedestrians: Annotated[int, Ge(0)] = 6
    """Pedestrians per scene on the sidewalks (plus crossing ones in the ``stop`` scenario)."""
    max_depth_m: Annotated[float, Gt(0)] = 150.0
    """Rays travel at most this far; farther surfaces count as sky (depth 0)."""
    box_range_m: Annotated[float, Gt(0)] = 60.0
    """Vehicles and pedestrians within this ego-xy distance get a 3D box."""
    min_box_pixels: Annotated[int, Ge(0)] = 12
    """Visible pixels an object needs in a camera to get a 2D box there."""
    lidar_beams: Annotated[int, Ge(1)] = 32
    """LiDAR beams (HDL-32E-like elevations from -30.67 to +10.67 degrees)."""
    lidar_azimuth_steps: Annotated[int, Ge(1)] = 360
    """LiDAR azimuth samples per sweep."""
    lidar_range_m: Annotated[float, Gt(0)] = 70.0
    """LiDAR maximum range; farther returns are dropped."""
    fog_visibility_m: Annotated[float, Gt(0)] = 40.0
    """Fog: distance at which the scene keeps exp(-1) of its contrast."""
    qa_per_task: Annotated[int, Ge(0)] = 4
    """At most this many QA of each of rdp, vg2d and vg3d per frame."""
    min_referent_pixels: Annotated[int, Ge(0)] = 8
    """Grounding QA (vg2d, vg3d) ask only about objects whose 2D box is at least this wide and high in the stored
    image (one patch of the tiny vision tower at the default 160x90)."""
    plan_horizon_s: Annotated[float, Gt(0)] = 2.0
    """Planning QA look this far ahead; frames without that much future get none."""
    num_workers: Annotated[int, Ge(0)] = 0
    """Processes rendering scenes in parallel: 0 = one per CPU (at most one per scene), 1 = in-process."""


def _check(ok: bool, key: str, rule: str, value: Any) -> None:
    if not ok:
        raise DataError(f"data.{key} must be {rule}, got {value!r}")


def planned_scenes(cfg: Any) -> list[str]:
    """The scene ids ``build`` writes for ``cfg`` (``scene-0000`` ...), after the same checks; writes nothing."""
    cfg = coerce_config(cfg)
    validate(cfg)
    return [f"scene-{i:04d}" for i in range(cfg.num_scenes)]


def coerce_config(cfg: Any) -> SynthConfig:
    """A ``SynthConfig`` from itself, a Hydra ``DictConfig`` or a mapping (lists become plain lists)."""
    if isinstance(cfg, SynthConfig):
        return cfg
    get = cfg.get if hasattr(cfg, "get") else (lambda k, d: getattr(cfg, k, d))
    kwargs = {}
    for f in fields(SynthConfig):
        if f.name == "root":  # an interpolation of the caller's config; build() gets the root explicitly
            continue
        value = get(f.name, None)
        if value is None:
            continue
        kwargs[f.name] = list(value) if f.name in ("weathers", "scenarios") else value
    return SynthConfig(**kwargs)


def validate(cfg: SynthConfig) -> None:
    """Reject values the generator cannot honour; messages name the ``data.<key>``."""
    for key in ("num_scenes", "num_frames"):
        _check(isinstance(getattr(cfg, key), int) and getattr(cfg, key) >= 1, key, ">= 1", getattr(cfg, key))
    for key in ("width", "height"):
        _check(isinstance(getattr(cfg, key), int) and getattr(cfg, key) >= 16, key, ">= 16 pixels", getattr(cfg, key))
    _check(isinstance(cfg.seed, int) and cfg.seed >= 0, "seed", ">= 0", cfg.seed)
    _check(cfg.frame_rate_hz > 0, "frame_rate_hz", "> 0", cfg.frame_rate_hz)
    _check(0 <= cfg.val_fraction < 1, "val_fraction", "in [0, 1)", cfg.val_fraction)
    _check(0 <= cfg.parked_fraction <= 1, "parked_fraction", "in [0, 1]", cfg.parked_fraction)
    for key in ("num_vehicles", "num_pedestrians", "qa_per_task", "num_workers", "min_referent_pixels"):
        _check(getattr(cfg, key) >= 0, key, ">= 0", getattr(cfg, key))
    for key in ("min_box_pixels", "lidar_beams", "lidar_azimuth_steps"):
        _check(getattr(cfg, key) >= 1, key, ">= 1", getattr(cfg, key))
    for key in ("box_range_m", "lidar_range_m", "fog_visibility_m", "plan_horizon_s"):
        _check(getattr(cfg, key) > 0, key, "> 0", getattr(cfg, key))
    # Depth PNGs hold at most 65535 / 256 m.
    _check(0 < cfg.max_depth_m <= 255.0, "max_depth_m", "in (0, 255] (uint16 depth PNG range)", cfg.max_depth_m)
    unknown = [w for w in cfg.weathers if w not in WEATHERS]
    _check(not unknown, "weathers", f"a subset of {list(WEATHERS)}", cfg.weathers)
    _check("clear" in cfg.weathers, "weathers", "a list that includes 'clear' (the images/ folder)", cfg.weathers)
    _check(len(set(cfg.weathers)) == len(cfg.weathers), "weathers", "a list without repeats", cfg.weathers)
    bad = [s for s in cfg.scenarios if s not in SCENARIOS]
    _check(bool(cfg.scenarios) and not bad, "scenarios", f"a non-empty subset of {list(SCENARIOS)}", cfg.scenarios)
