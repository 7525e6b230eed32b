"""The procedural scene model: agents and static props built from analytic primitives.

Agent frame: x forward, y left, z up, origin on the ground under the centre of the agent's
3D box (so the box centre is at z = h / 2). A ``Part`` is one primitive in that frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from pipelines.data.synth.materials import CLOTHING_COLOURS, SKIN, VEHICLE_COLOURS, Material
from pipelines.data.synth.motion import Motion, State
from pipelines.data.synth.raycast import PrimitiveBuilder, Primitives
from pipelines.data.synth.road import Road

CATEGORY = {
    "car": "vehicle.car",
    "truck": "vehicle.truck",
    "bus": "vehicle.bus.rigid",
    "pedestrian": "human.pedestrian.adult",
}
EGO_SIZE = (4.8, 1.9, 1.6)
EGO_CENTER_X = 1.3
"""The ego frame's origin is the rear axle; its body centre sits this far ahead of it."""
MOVING_SPEED = 0.3
"""m/s above which an agent counts as moving (attribute ``*.moving``)."""


@dataclass(frozen=True)
class Part:
    shape: str
    """``box`` | ``cyl`` | ``sphere``."""
    center: tuple[float, float, float]
    """Box/sphere centre; cylinder bottom-cap centre (agent frame)."""
    size: tuple[float, float, float]
    """Box: full extents (l, w, h); cylinder: (r, r, height); sphere: (r, r, r)."""
    material: Material
    colour: tuple[float, float, float]


@dataclass
class Actor:
    """A vehicle or pedestrian with a 3D box, a colour name and a closed-form motion."""

    instance_id: str
    kind: str
    """``car`` | ``truck`` | ``bus`` | ``pedestrian``."""
    colour: str
    """Paint (vehicles) or shirt (pedestrians) colour name, as QA answers say it."""
    size: tuple[float, float, float]
    """Box length (x), width (y), height (z), metres."""
    motion: Motion
    parts: list[Part]
    parked: bool = False

    @property
    def category(self) -> str:
        return CATEGORY[self.kind]

    def attribute(self, speed: float) -> str:
        if self.kind == "pedestrian":
            return "pedestrian.moving" if speed > MOVING_SPEED else "pedestrian.standing"
        if self.parked:
            return "vehicle.parked"
        return "vehicle.moving" if speed > MOVING_SPEED else "vehicle.stopped"


@dataclass
class Prop:
    """Static scenery (building, tree, street light) placed at a world xy and yaw."""

    kind: str
    xy: tuple[float, float]
    yaw: float
    parts: list[Part]


@dataclass
class Scene:
    scene_id: str
    index: int
    scenario: str
    description: str
    road: Road
    ego: Motion
    actors: list[Actor]
    props: list[Prop]
    times: np.ndarray
    """Frame times, seconds."""
    sun_dir: np.ndarray
    """Unit vector towards the sun (world)."""
    lamps_L3: np.ndarray
    """Street-lamp positions (world), the light sources at night."""
    meta: dict = field(default_factory=dict)
    """Scenario facts (ego speed and lane, bend, lane-change timing) for ``dataset.json``."""

    @cached_property
    def ego_state(self) -> State:
        return self.ego.state(self.road, self.times)

    @cached_property
    def actor_states(self) -> list[State]:
        return [a.motion.state(self.road, self.times) for a in self.actors]

    def ego2world(self, frame: int) -> np.ndarray:
        st = self.ego_state
        c, s = np.cos(st.yaw_T[frame]), np.sin(st.yaw_T[frame])
        m = np.eye(4)
        m[:2, :2] = [[c, -s], [s, c]]
        m[:2, 3] = st.xy_T2[frame]
        return m

    @cached_property
    def _static(self) -> PrimitiveBuilder:
        pb = PrimitiveBuilder()
        for prop in self.props:
            _add_parts(pb, prop.parts, np.asarray(prop.xy), prop.yaw, actor=-1)
        return pb

    def primitives(self, frame: int) -> Primitives:
        """All primitives at a frame; ``actor_P`` indexes ``self.actors``."""
        pb = PrimitiveBuilder()
        pb.extend(self._static)
        for i, (actor, st) in enumerate(zip(self.actors, self.actor_states, strict=True)):
            _add_parts(pb, actor.parts, st.xy_T2[frame], float(st.yaw_T[frame]), actor=i)
        return pb.build()


def _add_parts(pb: PrimitiveBuilder, parts: list[Part], xy: np.ndarray, yaw: float, actor: int) -> None:
    c, s = np.cos(yaw), np.sin(yaw)
    for p in parts:
        x, y, z = p.center
        wx, wy = xy[0] + c * x - s * y, xy[1] + s * x + c * y
        if p.shape == "box":
            pb.box((wx, wy, z), (p.size[0] / 2, p.size[1] / 2, p.size[2] / 2), yaw, p.material, p.colour, actor)
        elif p.shape == "cyl":
            pb.cylinder((wx, wy, z), p.size[2], p.size[0], p.material, p.colour, actor)
        else:
            pb.sphere((wx, wy, z), p.size[0], p.material, p.colour, actor)


# ----------------------------------------------------------------------------- agent bodies


def vehicle_parts(kind: str, size: tuple[float, float, float], colour: str) -> list[Part]:
    """Body parts of a car (body + cabin), truck (cab + cargo box) or bus (one box)."""
    length, width, height = size
    rgb = VEHICLE_COLOURS[colour]
    if kind == "car":
        body_top = 0.55 * height
        return [
            Part("box", (0.0, 0.0, (0.05 + body_top) / 2), (length, width, body_top - 0.05), Material.PAINT, rgb),
            Part(
                "box",
                (-0.08 * length, 0.0, (body_top + height) / 2),
                (0.55 * length, 0.86 * width, height - body_top),
                Material.CABIN,
                rgb,
            ),
        ]
    if kind == "truck":
        cab_len = 0.24 * length
        cargo_len = length - cab_len - 0.15
        return [
            Part(
                "box",
                (length / 2 - cab_len / 2, 0.0, (0.05 + 0.78 * height) / 2),
                (cab_len, width, 0.78 * height - 0.05),
                Material.CABIN,
                rgb,
            ),
            Part(
                "box",
                (-length / 2 + cargo_len / 2, 0.0, (0.6 + height) / 2),
                (cargo_len, width, height - 0.6),
                Material.CARGO,
                (0.82, 0.82, 0.80),
            ),
        ]
    return [Part("box", (0.0, 0.0, (0.05 + height) / 2), (length, width, height - 0.05), Material.BUS, rgb)]


def pedestrian_parts(height: float, colour: str) -> list[Part]:
    """A body cylinder (shirt above the hips, trousers below, by texture) and a head sphere."""
    head_r = 0.12
    return [
        Part("cyl", (0.0, 0.0, 0.0), (0.25, 0.25, height - 2 * head_r), Material.CLOTH, CLOTHING_COLOURS[colour]),
        Part("sphere", (0.0, 0.0, height - head_r), (head_r, head_r, head_r), Material.SKIN, SKIN),
    ]
