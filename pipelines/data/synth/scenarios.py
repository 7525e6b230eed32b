"""Seeded scene generation: the ego scenario, traffic, pedestrians and street scenery.

Scene ``i`` draws everything from ``numpy.random.default_rng([seed, i])`` and plays scenario
``scenarios[(i + seed) % len(scenarios)]``, so the default 4 scenes cover a bend, a stop,
a lane change and a start-up, and every seed gives different numbers:

- ``curve``: the road bends (radius 70-90 m); the ego keeps its lane and speed.
- ``stop``: a car waits before a zebra crossing; the ego brakes to a standstill behind it.
- ``lane_change``: a stopped truck blocks the ego lane; the ego changes lanes before it.
- ``start``: the ego pulls away from (almost) standstill behind a car that also starts.
- ``follow``: the ego brakes to the speed of a slower car ahead.
- ``cruise``: straight road, steady speed, nothing close ahead in the ego lane.

Agents never overlap each other or the ego at any time (placement rejects candidates whose
footprints, grown by a margin, intersect anyone's over the clip).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from pipelines.data.synth.config import SynthConfig
from pipelines.data.synth.materials import (
    BUS_COLOURS,
    CLOTHING_COLOURS,
    FACADE_COLOURS,
    FOLIAGE,
    LAMP,
    POLE,
    TRUCK_COLOURS,
    TRUNK,
    VEHICLE_COLOURS,
    Material,
)
from pipelines.data.synth.motion import Motion, State
from pipelines.data.synth.road import (
    BUILDING_SETBACK,
    EGO_LANES,
    LANE_WIDTH,
    ONCOMING_LANES,
    PARKING_L,
    Road,
)
from pipelines.data.synth.scene import EGO_CENTER_X, EGO_SIZE, Actor, Part, Prop, Scene, pedestrian_parts, vehicle_parts

EGO_FRONT = EGO_CENTER_X + EGO_SIZE[0] / 2
SIZES = {  # (length, width, height) ranges
    "car": ((4.0, 4.9), (1.75, 1.95), (1.42, 1.62)),
    "truck": ((6.5, 8.5), (2.3, 2.5), (2.8, 3.4)),
    "bus": ((10.0, 12.0), (2.5, 2.6), (3.0, 3.3)),
}
_MARGIN = 1.0  # metres kept free around every footprint


def _size(rng: np.random.Generator, kind: str) -> tuple[float, float, float]:
    return tuple(round(float(rng.uniform(*r)), 2) for r in SIZES[kind])  # type: ignore[return-value]


def _colour(rng: np.random.Generator, kind: str) -> str:
    names = {"car": tuple(VEHICLE_COLOURS), "truck": TRUCK_COLOURS, "bus": BUS_COLOURS}[kind]
    return str(rng.choice(names))


class _Placer:
    """Keeps footprints of placed agents over the clip and rejects overlapping candidates."""

    def __init__(self, road: Road, times: np.ndarray):
        self.road = road
        self.times = times
        self.placed: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def footprint(self, st: State, size, centre_x: float = 0.0):
        c, s = np.cos(st.yaw_T), np.sin(st.yaw_T)
        xy = st.xy_T2 + centre_x * np.stack([c, s], 1)
        return xy, st.yaw_T, np.array([size[0] / 2 + _MARGIN / 2, size[1] / 2 + _MARGIN / 2])

    def fits(self, fp) -> bool:
        return not any(_obb_overlap(fp, other).any() for other in self.placed)

    def add(self, fp) -> None:
        self.placed.append(fp)

    def try_add(self, motion: Motion, size) -> bool:
        fp = self.footprint(motion.state(self.road, self.times), size)
        if self.fits(fp):
            self.add(fp)
            return True
        return False


def _obb_overlap(a, b) -> np.ndarray:
    """[T] whether two oriented rectangles (xy_T2, yaw_T, half_2) intersect (separating axis test)."""
    (pa, ya, ha), (pb, yb, hb) = a, b
    ua, va = np.stack([np.cos(ya), np.sin(ya)], 1), np.stack([-np.sin(ya), np.cos(ya)], 1)
    ub, vb = np.stack([np.cos(yb), np.sin(yb)], 1), np.stack([-np.sin(yb), np.cos(yb)], 1)
    d = pb - pa
    separated = np.zeros(len(pa), dtype=bool)
    for ax in (ua, va, ub, vb):
        ra = ha[0] * np.abs((ua * ax).sum(1)) + ha[1] * np.abs((va * ax).sum(1))
        rb = hb[0] * np.abs((ub * ax).sum(1)) + hb[1] * np.abs((vb * ax).sum(1))
        separated |= np.abs((d * ax).sum(1)) > ra + rb
    return ~separated


@dataclass(frozen=True)
class _Spawn:
    kind: str
    colour: str
    size: tuple[float, float, float]
    motion: Motion
    parked: bool = False


@dataclass
class _Script:
    """What a scenario fixes before the random traffic: the ego, the road and the agents it needs."""

    ego: Motion
    lane: float
    what: str
    curvature: float = 0.0
    crosswalks: tuple[float, ...] = ()
    spawns: list[_Spawn] = field(default_factory=list)
    meta: dict = field(default_factory=dict)


def _pedestrian(rng: np.random.Generator, motion: Motion) -> _Spawn:
    height = round(float(rng.uniform(1.6, 1.9)), 2)
    return _Spawn("pedestrian", str(rng.choice(tuple(CLOTHING_COLOURS))), (0.5, 0.5, height), motion)


def _script(rng: np.random.Generator, scenario: str, duration: float, rate_hz: float) -> _Script:
    lane = float(rng.choice(EGO_LANES))
    if scenario == "curve":
        radius = float(rng.uniform(70.0, 90.0))
        bend = float(rng.choice([-1.0, 1.0]))
        v = float(rng.uniform(7.0, 9.0))
        side = "left" if bend > 0 else "right"
        what = f"the road bends {side} (radius {radius:.0f} m); the ego keeps {v:.1f} m/s"
        script = _Script(Motion(0.0, lane, v), lane, what, curvature=bend / radius)
        script.meta.update(radius_m=round(radius, 1), bend=side)
    elif scenario == "stop":
        v0 = float(rng.uniform(7.0, 9.0))
        t_stop = float(rng.uniform(0.45, 0.6)) * duration
        size = _size(rng, "car")
        s_lead = v0 * t_stop / 2 + EGO_FRONT + float(rng.uniform(3.0, 5.0)) + size[0] / 2
        zebra = s_lead + size[0] / 2 + 1.5
        what = f"the ego brakes from {v0:.1f} m/s to a stop behind a car waiting at a zebra crossing"
        script = _Script(Motion(0.0, lane, v0, accel=-v0 / t_stop, v_end=0.0), lane, what, crosswalks=(zebra,))
        script.spawns.append(_Spawn("car", _colour(rng, "car"), size, Motion(s_lead, lane)))
        for k, side in enumerate((1.0, -1.0)):
            start = side * float(rng.uniform(7.5, 10.0))
            script.spawns.append(_pedestrian(rng, Motion(zebra + 1.0 + 2.0 * k, start, vlat=-side * 1.2)))
    elif scenario == "lane_change":
        left = bool(rng.integers(2))
        lane = EGO_LANES[1] if left else EGO_LANES[0]
        v = float(rng.uniform(7.0, 9.0))
        # Start on a frame so some planning windows hold the whole manoeuvre.
        lc_start = max(1, round(0.25 * duration * rate_hz)) / rate_hz
        lc_duration = 1.5
        offset = LANE_WIDTH if left else -LANE_WIDTH
        size = _size(rng, "truck")
        s_obs = v * (lc_start + lc_duration) + EGO_FRONT + float(rng.uniform(6.0, 12.0)) + size[0] / 2
        side = "left" if left else "right"
        what = f"a stopped truck blocks the ego lane; the ego changes lanes to the {side} at {v:.1f} m/s"
        ego = Motion(0.0, lane, v, lc_offset=offset, lc_start=lc_start, lc_duration=lc_duration)
        script = _Script(ego, lane, what)
        script.spawns.append(_Spawn("truck", _colour(rng, "truck"), size, Motion(s_obs, lane)))
        script.meta.update(direction=side, lc_start_s=lc_start, lc_duration_s=lc_duration)
    elif scenario == "start":
        v0 = float(rng.uniform(0.0, 1.0))
        a = float(rng.uniform(1.5, 2.2))
        ego = Motion(0.0, lane, v0, accel=a, v_end=float(rng.uniform(8.0, 10.0)))
        size = _size(rng, "car")
        s_lead = EGO_FRONT + float(rng.uniform(6.0, 9.0)) + size[0] / 2
        what = f"the ego pulls away from {v0:.1f} m/s behind a car that starts moving"
        script = _Script(ego, lane, what)
        lead = Motion(s_lead, lane, 0.5, accel=a + 0.6, v_end=12.0)  # always pulls away from the ego
        script.spawns.append(_Spawn("car", _colour(rng, "car"), size, lead))
    elif scenario == "follow":
        v0 = float(rng.uniform(9.0, 11.0))
        v_lead = float(rng.uniform(3.0, 5.0))
        a = float(rng.uniform(1.5, 2.5))
        size = _size(rng, "car")
        closing = (v0 - v_lead) ** 2 / (2 * a)  # gap the ego eats while braking to the lead's speed
        s_lead = EGO_FRONT + closing + float(rng.uniform(6.0, 10.0)) + size[0] / 2
        what = f"the ego brakes from {v0:.1f} m/s to follow a car driving {v_lead:.1f} m/s"
        script = _Script(Motion(0.0, lane, v0, accel=-a, v_end=v_lead), lane, what)
        script.spawns.append(_Spawn("car", _colour(rng, "car"), size, Motion(s_lead, lane, v_lead)))
    else:  # cruise
        v = float(rng.uniform(7.0, 10.0))
        script = _Script(Motion(0.0, lane, v), lane, f"straight road; the ego keeps {v:.1f} m/s")
    if scenario in ("curve", "cruise") and rng.random() < 0.5:
        size = _size(rng, "car")
        s_lead = EGO_FRONT + float(rng.uniform(30.0, 45.0)) + size[0] / 2
        script.spawns.append(_Spawn("car", _colour(rng, "car"), size, Motion(s_lead, lane, script.ego.v0)))
    ego = script.ego
    script.meta.update(ego_speed_mps=round(ego.v0, 2), ego_accel_mps2=round(ego.accel, 2), ego_lane_offset_m=lane)
    return script


def _traffic(rng: np.random.Generator, cfg: SynthConfig, free_lanes: list[float], s_lo: float, s_hi: float):
    """Candidate spawns for one other vehicle: parked at the kerb or driving in a free lane (yields retries)."""
    kind = str(rng.choice(["car", "truck", "bus"], p=[0.65, 0.2, 0.15]))
    size, colour = _size(rng, kind), _colour(rng, kind)
    parked = bool(rng.random() < cfg.parked_fraction)
    for _attempt in range(30):
        s0 = float(rng.uniform(s_lo, s_hi))
        if parked:
            side = float(rng.choice([-1.0, 1.0]))
            motion = Motion(s0, side * PARKING_L, facing=0.0 if side < 0 else np.pi)
        else:
            lat = float(rng.choice(free_lanes))
            speed = float(rng.uniform(6.0, 11.0))
            motion = Motion(s0, lat, speed if lat < 0 else -speed)
        yield _Spawn(kind, colour, size, motion, parked)


def _sidewalk_pedestrian(rng: np.random.Generator, s_lo: float, s_hi: float):
    """Candidate spawns for one pedestrian walking along or standing on a sidewalk (yields retries)."""
    height = round(float(rng.uniform(1.6, 1.9)), 2)
    colour = str(rng.choice(tuple(CLOTHING_COLOURS)))
    for _attempt in range(30):
        lat = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(10.4, 12.2))
        s0 = float(rng.uniform(s_lo, s_hi))
        if rng.random() < 0.7:
            motion = Motion(s0, lat, float(rng.choice([-1.0, 1.0])) * float(rng.uniform(1.0, 1.6)))
        else:
            motion = Motion(s0, lat, facing=float(rng.uniform(-np.pi, np.pi)))
        yield _Spawn("pedestrian", colour, (0.5, 0.5, height), motion)


def generate_scene(cfg: SynthConfig, index: int) -> Scene:
    """Scene ``index`` of the dataset configured by ``cfg`` (pure function of cfg.seed and index)."""
    rng = np.random.default_rng([cfg.seed, index])
    scenario = cfg.scenarios[(index + cfg.seed) % len(cfg.scenarios)]
    times = np.arange(cfg.num_frames, dtype=np.float64) / cfg.frame_rate_hz
    duration = max(float(times[-1]), 1.0 / cfg.frame_rate_hz)
    scene_id = f"scene-{index:04d}"
    script = _script(rng, scenario, duration, cfg.frame_rate_hz)
    road = Road(script.curvature, script.crosswalks)

    placer = _Placer(road, np.linspace(0.0, duration, 4 * max(cfg.num_frames, 2)))
    ego_state = script.ego.state(road, placer.times)
    placer.add(placer.footprint(ego_state, EGO_SIZE, EGO_CENTER_X))
    placed = [sp for sp in script.spawns if placer.try_add(sp.motion, sp.size)]
    s_end = float(ego_state.s_T.max())
    s_lo, s_hi = -40.0, s_end + 70.0
    # Random traffic never uses the ego's lanes, so it cannot contradict the scenario's plan.
    free_lanes = [
        x for x in (*EGO_LANES, *ONCOMING_LANES) if x not in (script.lane, script.lane + script.ego.lc_offset)
    ]
    candidates = [_traffic(rng, cfg, free_lanes, s_lo, s_hi) for _ in range(cfg.num_vehicles)]
    candidates += [_sidewalk_pedestrian(rng, -20.0, s_end + 50.0) for _ in range(cfg.num_pedestrians)]
    for tries in candidates:
        for sp in tries:  # the first candidate that fits; the generator then stops drawing
            if placer.try_add(sp.motion, sp.size):
                placed.append(sp)
                break

    counter: Counter = Counter()
    actors = []
    for sp in placed:
        counter[sp.kind] += 1
        parts = (
            pedestrian_parts(sp.size[2], sp.colour)
            if sp.kind == "pedestrian"
            else vehicle_parts(sp.kind, sp.size, sp.colour)
        )
        iid = f"{scene_id}-{sp.kind}-{counter[sp.kind]:02d}"
        actors.append(Actor(iid, sp.kind, sp.colour, sp.size, sp.motion, parts, sp.parked))

    props, lamps = _scenery(rng, road, s_lo - 30.0, s_hi + 50.0)
    elev, azim = np.deg2rad(rng.uniform(30.0, 60.0)), rng.uniform(-np.pi, np.pi)
    sun = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    n_veh = sum(a.kind != "pedestrian" for a in actors)
    description = (
        f"{scenario}: {script.what}; {n_veh} vehicles, {len(actors) - n_veh} pedestrians, "
        f"{sum(p.kind == 'building' for p in props)} buildings, {sum(p.kind == 'tree' for p in props)} trees"
    )
    return Scene(
        scene_id, index, scenario, description, road, script.ego, actors, props, times, sun, lamps, script.meta
    )


def _scenery(rng: np.random.Generator, road: Road, s_lo: float, s_hi: float) -> tuple[list[Prop], np.ndarray]:
    """Buildings, trees and street lights along both sides between arc lengths s_lo and s_hi."""
    props: list[Prop] = []
    lamps = []

    def place(kind: str, s: float, lat: float, parts: list[Part]) -> None:
        xy = road.to_world(np.array(s), np.array(lat))
        props.append(Prop(kind, (float(xy[0]), float(xy[1])), float(road.heading(np.array(s))), parts))

    for side in (-1.0, 1.0):
        s = s_lo + float(rng.uniform(0.0, 6.0))
        while s < s_hi:
            width, depth, height = rng.uniform(8.0, 20.0), rng.uniform(8.0, 14.0), rng.uniform(6.0, 22.0)
            colour = FACADE_COLOURS[int(rng.integers(len(FACADE_COLOURS)))]
            part = Part("box", (0.0, 0.0, height / 2), (width, depth, height), Material.BUILDING, colour)
            place("building", s + width / 2, side * (BUILDING_SETBACK + depth / 2), [part])
            s += width + float(rng.uniform(2.0, 8.0))
        s = s_lo + float(rng.uniform(0.0, 8.0))
        while s < s_hi:
            if rng.random() < 0.8:
                trunk_r, trunk_h, crown_r = rng.uniform(0.15, 0.22), rng.uniform(2.2, 3.2), rng.uniform(1.4, 2.1)
                shade = rng.uniform(0.8, 1.2)
                parts = [
                    Part("cyl", (0.0, 0.0, 0.0), (trunk_r, trunk_r, trunk_h), Material.TRUNK, TRUNK),
                    Part(
                        "sphere",
                        (0.0, 0.0, trunk_h + 0.6 * crown_r),
                        (crown_r,) * 3,
                        Material.FOLIAGE,
                        tuple(min(1.0, c * shade) for c in FOLIAGE),
                    ),
                ]
                place("tree", s, side * 13.2, parts)
            s += float(rng.uniform(8.0, 14.0))
        # Street lights every 30 m; the arm reaches over the road (towards -side in the prop frame).
        s = s_lo + (15.0 if side > 0 else 0.0)
        while s < s_hi:
            lat = side * 9.9
            parts = [
                Part("cyl", (0.0, 0.0, 0.0), (0.12, 0.12, 7.5), Material.POLE, POLE),
                Part("box", (0.0, -side * 1.0, 7.4), (0.2, 2.0, 0.15), Material.POLE, POLE),
                Part("box", (0.0, -side * 1.8, 7.27), (0.5, 0.3, 0.12), Material.LAMP, LAMP),
            ]
            place("street_light", s, lat, parts)
            xy = road.to_world(np.array(s), np.array(lat - side * 1.8))
            lamps.append((float(xy[0]), float(xy[1]), 7.2))
            s += 30.0
    return props, np.asarray(lamps, dtype=np.float64).reshape(-1, 3)


def lateral_truth(scene: Scene, frame: int, horizon: int) -> str | None:
    """What the scene does laterally between frame and frame+horizon; None while a lane change is cut by the window."""
    if scene.road.curvature != 0.0:
        return "turn left" if scene.road.curvature > 0 else "turn right"
    ego = scene.ego
    if ego.lc_offset == 0.0:
        return "go straight"
    t0, t1 = scene.times[frame], scene.times[frame + horizon]
    a, b = ego.lc_start, ego.lc_start + ego.lc_duration
    if t0 <= a and b <= t1:
        return "change lane left" if ego.lc_offset > 0 else "change lane right"
    if b <= t0 or a >= t1:
        return "go straight"
    return None
