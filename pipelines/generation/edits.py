"""Instruction-controllable 4D editing (Sec. Spatiotemporal Generation and 4D Editing).

Every edit's instruction text (``edit_instruction``) goes into the prompt the LLM turns into C_L, the editing intent
of Eq. v_hat (``pipelines.generation.samples.edited_example``). Vehicle edits also change the frame's Gaussians
before the low-level conditions are projected from them, so a removed, moved, stopped or inserted vehicle has one
geometry in every target view and frame. Weather is no geometry edit: it leaves the Gaussians alone and reaches the
generator through C_L only.

Legend: N Gaussians, T trajectory points. Gaussians are dicts in the layout's schema (ego frame: ``xyz``,
``scale``, ``rotation`` wxyz, ``opacity``, ``color``, ``feature``), one row per Gaussian. Boxes are the dataset's
``boxes3d`` rows in the same ego frame: ``center`` [3], ``size`` (length along the box x, width along y, height
along z), ``yaw`` about ego z, ``instance_id``. A box's own frame has its origin at the centre, x along its heading.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from pipelines.data.layout import WEATHERS, transform_gaussians
from pipelines.recon.init import box_pose

# ----------------------------------------------------------------------------- Gaussian sets


def _select(g: dict[str, np.ndarray], mask_N: np.ndarray) -> dict[str, np.ndarray]:
    return {k: np.asarray(v)[mask_N] for k, v in g.items()}


def _concat(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows of ``a`` then rows of ``b``; both must have the same fields with the same widths."""
    if set(a) != set(b):
        raise ValueError(f"cannot merge Gaussian sets with fields {sorted(a)} and {sorted(b)}")
    for k in a:
        sa, sb = np.shape(a[k])[1:], np.shape(b[k])[1:]
        if sa != sb:
            raise ValueError(f"cannot merge Gaussian sets: field '{k}' has row shape {sa} and {sb}")
    return {k: np.concatenate([np.asarray(a[k]), np.asarray(b[k]).astype(np.asarray(a[k]).dtype)]) for k in a}


def _with_rows(g: dict[str, np.ndarray], mask_N: np.ndarray, rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``g`` with its ``mask_N`` rows replaced by ``rows`` (same order); the other rows are the same values."""
    out = {}
    for k, v in g.items():
        v = np.array(v, copy=True)
        v[mask_N] = rows[k]
        out[k] = v
    return out


# ----------------------------------------------------------------------------- boxes


def gaussians_in_box(xyz_N3: np.ndarray, box: dict, margin: float = 0.1) -> np.ndarray:
    """[N] bool: centres inside the oriented box grown by ``margin`` metres on every side."""
    local = (np.asarray(xyz_N3, dtype=np.float64) - np.asarray(box["center"], dtype=np.float64)) @ box_pose(box)[:3, :3]
    half = np.asarray(box["size"], dtype=np.float64) / 2 + margin
    return np.all(np.abs(local) <= half, axis=1)


def extract_vehicle(gaussians: dict[str, np.ndarray], box: dict, margin: float = 0.1) -> dict[str, np.ndarray]:
    """The Gaussians inside ``box``, expressed in the box's own frame (a donor for ``insert_vehicle``)."""
    inside = _select(gaussians, gaussians_in_box(gaussians["xyz"], box, margin))
    return transform_gaussians(inside, np.linalg.inv(box_pose(box)))


def remove_vehicle(gaussians: dict[str, np.ndarray], box: dict, margin: float = 0.1) -> dict[str, np.ndarray]:
    """The Gaussians without those inside ``box``; the others keep their values and order."""
    return _select(gaussians, ~gaussians_in_box(gaussians["xyz"], box, margin))


def insert_vehicle(
    gaussians: dict[str, np.ndarray], donor_box_frame: dict[str, np.ndarray], box: dict
) -> dict[str, np.ndarray]:
    """``gaussians`` followed by the donor's Gaussians (given in their box frame) placed at ``box``'s pose."""
    return _concat(gaussians, transform_gaussians(donor_box_frame, box_pose(box)))


def path_point(trajectory_T: np.ndarray, distance_m: float) -> tuple[np.ndarray, float]:
    """(point, heading) at arc length ``distance_m`` along a polyline ``[T, 2|3]``; clamped to its ends.

    The heading (radians about z) is that of the segment the point lies on (the next one at a vertex, the last one
    at the end); zero-length segments are skipped.
    """
    pts = np.asarray(trajectory_T, dtype=np.float64)
    seg = np.diff(pts, axis=0)
    length = np.linalg.norm(seg[:, :2], axis=1)
    keep = length > 1e-9
    if not keep.any():
        raise ValueError(f"trajectory {pts.tolist()} has no segment of positive length")
    starts, seg, length = pts[:-1][keep], seg[keep], length[keep]
    cum = np.concatenate([[0.0], np.cumsum(length)])
    d = float(np.clip(distance_m, 0.0, cum[-1]))
    i = min(int(np.searchsorted(cum, d, side="right")) - 1, len(seg) - 1)
    frac = (d - cum[i]) / length[i]
    return starts[i] + frac * seg[i], math.atan2(seg[i, 1], seg[i, 0])


def moved_box(box: dict, trajectory_T: np.ndarray, speed_mps: float, t_s: float) -> dict:
    """``box`` driven ``speed_mps * t_s`` metres along the path (box centre, then the trajectory points), facing
    the path.

    The path starts at the box centre, so the motion is continuous at t = 0 (a trajectory that itself begins at
    the centre adds nothing). Distance is arc length in the ground plane. ``[T, 2]`` points keep the centre's
    height; ``[T, 3]`` points are centre positions (height interpolated). Past the last point the vehicle stays
    there.
    """
    pts = np.asarray(trajectory_T, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3) or len(pts) == 0:
        raise ValueError(f"trajectory must have shape [T, 2] or [T, 3] with T >= 1, got {list(pts.shape)}")
    center = np.asarray(box["center"], dtype=np.float64)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.full((len(pts), 1), center[2])], axis=1)
    point, heading = path_point(np.concatenate([center[None], pts]), speed_mps * t_s)
    return {**box, "center": [float(v) for v in point], "yaw": heading}


def move_vehicle(
    gaussians: dict[str, np.ndarray],
    box: dict,
    trajectory_T: np.ndarray,
    speed_mps: float,
    t_s: float,
    margin: float = 0.1,
) -> dict[str, np.ndarray]:
    """The box's Gaussians carried rigidly to ``moved_box(box, trajectory_T, speed_mps, t_s)``: centres rotated
    about the box centre by the heading change and translated, orientations composed with that rotation. The other
    Gaussians are untouched and every row keeps its index."""
    mask = gaussians_in_box(gaussians["xyz"], box, margin)
    old_to_new = box_pose(moved_box(box, trajectory_T, speed_mps, t_s)) @ np.linalg.inv(box_pose(box))
    return _with_rows(gaussians, mask, transform_gaussians(_select(gaussians, mask), old_to_new))


def stop_vehicle(
    gaussians: dict[str, np.ndarray],
    box: dict | None,
    reference_gaussians: dict[str, np.ndarray],
    reference_box: dict,
    reference_to_ego_44: np.ndarray,
    margin: float = 0.1,
) -> dict[str, np.ndarray]:
    """A moving vehicle that stops: it keeps its (world) pose of a reference frame f in this later frame.

    The later frame's Gaussians inside its ``box`` (None: the vehicle is absent then) are removed, and the
    reference frame's Gaussians inside ``reference_box`` are inserted, carried into this frame's ego coordinates by
    ``reference_to_ego_44`` = ``inv(ego2world[later]) @ ego2world[f]``.
    """
    kept = gaussians if box is None else remove_vehicle(gaussians, box, margin)
    parked = _select(reference_gaussians, gaussians_in_box(reference_gaussians["xyz"], reference_box, margin))
    return _concat(kept, transform_gaussians(parked, np.asarray(reference_to_ego_44, dtype=np.float64)))


# ----------------------------------------------------------------------------- typed edits

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_TUPLE = rf"\(\s*{_NUM}(?:\s*,\s*{_NUM}){{1,2}}\s*\)"


def _num(v: float) -> str:
    """Shortest round-tripping text of a number, without a trailing ``.0``."""
    s = repr(float(v))
    return s[:-2] if s.endswith(".0") else s


def _tuple_text(p: tuple[float, ...]) -> str:
    return "(" + ", ".join(_num(v) for v in p) + ")"


def _parse_tuple(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in re.findall(_NUM, text))


def _point(p, what: str, sizes: tuple[int, ...] = (2, 3)) -> tuple[float, ...]:
    t = tuple(float(v) for v in p)
    if len(t) not in sizes or not all(math.isfinite(v) for v in t):
        raise ValueError(f"{what} must be {' or '.join(map(str, sizes))} finite numbers, got {list(p)}")
    return t


@dataclass(frozen=True)
class RemoveVehicle:
    """Take a vehicle out of the scene."""

    op: ClassVar[str] = "remove"
    instance_id: str
    """The vehicle's ``boxes3d`` instance id."""


@dataclass(frozen=True)
class MoveVehicle:
    """Drive a vehicle along an ego-frame trajectory at a constant speed (see ``moved_box``)."""

    op: ClassVar[str] = "move"
    instance_id: str
    """The vehicle's ``boxes3d`` instance id."""
    trajectory: tuple[tuple[float, ...], ...]
    """Waypoints ``(x, y)`` or ``(x, y, z)`` in the edited frame's ego coordinates, metres; the path starts at the
    box centre."""
    speed_mps: float
    """Speed along the path, m/s (>= 0)."""

    def __post_init__(self) -> None:
        pts = tuple(_point(p, f"move {self.instance_id}: trajectory point") for p in self.trajectory)
        if not pts or len({len(p) for p in pts}) != 1:
            raise ValueError(f"move {self.instance_id}: trajectory needs >= 1 point, all 2-D or all 3-D, got {pts}")
        if not (math.isfinite(self.speed_mps) and self.speed_mps >= 0):
            raise ValueError(f"move {self.instance_id}: speed_mps must be a finite number >= 0, got {self.speed_mps}")
        object.__setattr__(self, "trajectory", pts)
        object.__setattr__(self, "speed_mps", float(self.speed_mps))


@dataclass(frozen=True)
class StopVehicle:
    """A moving vehicle stops: it keeps its pose of a reference frame in the later frames (see ``stop_vehicle``)."""

    op: ClassVar[str] = "stop"
    instance_id: str
    """The vehicle's ``boxes3d`` instance id."""


@dataclass(frozen=True)
class InsertVehicle:
    """Insert a copy of a vehicle of the frame (its Gaussians in its box) at a new pose."""

    op: ClassVar[str] = "insert"
    donor_id: str
    """Instance id of the vehicle copied (its box's size is kept)."""
    center: tuple[float, ...]
    """New box centre ``(x, y)`` (the donor's height) or ``(x, y, z)``, ego frame, metres."""
    yaw: float = 0.0
    """New heading about ego z, radians."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _point(self.center, f"insert {self.donor_id}: center"))
        if not math.isfinite(self.yaw):
            raise ValueError(f"insert {self.donor_id}: yaw must be a finite number, got {self.yaw}")
        object.__setattr__(self, "yaw", float(self.yaw))


@dataclass(frozen=True)
class Weather:
    """Change the weather (global appearance and visibility); the geometry is left as it is."""

    op: ClassVar[str] = "weather"
    name: str
    """One of the layout's ``WEATHERS``."""

    def __post_init__(self) -> None:
        if self.name not in WEATHERS:
            raise ValueError(f"unknown weather '{self.name}' (one of {list(WEATHERS)})")


Edit = RemoveVehicle | MoveVehicle | StopVehicle | InsertVehicle | Weather
EDITS: dict[str, type] = {c.op: c for c in (RemoveVehicle, MoveVehicle, StopVehicle, InsertVehicle, Weather)}


def edit_instruction(edit: Edit) -> str:
    """The instruction text of ``edit``, the editing intent carried by C_L; ``parse_edit`` reads it back."""
    match edit:
        case RemoveVehicle(instance_id=i):
            return f"Remove vehicle {i} from the scene."
        case MoveVehicle(instance_id=i, trajectory=t, speed_mps=v):
            return f"Move vehicle {i} along the path {' -> '.join(_tuple_text(p) for p in t)} at {_num(v)} m/s."
        case StopVehicle(instance_id=i):
            return f"Stop vehicle {i} and keep it where it is."
        case InsertVehicle(donor_id=d, center=c, yaw=y):
            return f"Insert a copy of vehicle {d} at {_tuple_text(c)} with yaw {_num(y)} rad."
        case Weather(name=n):
            return f"Change the weather to {n}."
    raise TypeError(f"not an edit: {edit!r} (edits: {sorted(EDITS)})")


_TEXT = [
    (re.compile(r"remove vehicle (?P<id>.+?) from the scene\.?", re.I), lambda m: RemoveVehicle(m["id"])),
    (re.compile(r"stop vehicle (?P<id>.+?) and keep it where it is\.?", re.I), lambda m: StopVehicle(m["id"])),
    (
        re.compile(
            rf"move vehicle (?P<id>.+?) along the path (?P<path>{_TUPLE}(?:\s*->\s*{_TUPLE})*) at (?P<v>{_NUM}) m/s\.?",
            re.I,
        ),
        lambda m: MoveVehicle(m["id"], tuple(_parse_tuple(p) for p in re.findall(_TUPLE, m["path"])), float(m["v"])),
    ),
    (
        re.compile(rf"insert a copy of vehicle (?P<id>.+?) at (?P<c>{_TUPLE}) with yaw (?P<y>{_NUM}) rad\.?", re.I),
        lambda m: InsertVehicle(m["id"], _parse_tuple(m["c"]), float(m["y"])),
    ),
    (re.compile(r"change the weather to (?P<w>\S+?)\.?", re.I), lambda m: Weather(m["w"].lower())),
]


def edit_to_dict(edit: Edit) -> dict:
    """``{"op": ..., <fields>}``, JSON-ready; ``parse_edit`` reads it back."""
    d = asdict(edit)
    for k, v in d.items():
        if isinstance(v, tuple):
            d[k] = [list(p) if isinstance(p, tuple) else p for p in v]
    return {"op": edit.op, **d}


def parse_edit(instruction: str | dict) -> Edit:
    """A typed edit from ``{"op": ..., <fields>}`` (or its JSON text) or from the instruction text
    ``edit_instruction`` writes."""
    if isinstance(instruction, str) and instruction.strip().startswith("{"):
        instruction = json.loads(instruction)
    if isinstance(instruction, dict):
        fields = dict(instruction)
        op = fields.pop("op", None)
        if op not in EDITS:
            raise ValueError(f"unknown edit op {op!r} in {instruction} (ops: {sorted(EDITS)})")
        try:
            return EDITS[op](**fields)
        except TypeError as e:
            raise ValueError(f"edit {instruction}: {e}") from None
    text = " ".join(str(instruction).split())
    for pattern, build in _TEXT:
        if m := pattern.fullmatch(text):
            return build(m)
    examples = [
        "Remove vehicle <id> from the scene.",
        "Move vehicle <id> along the path (x, y) -> (x, y) at <v> m/s.",
        "Stop vehicle <id> and keep it where it is.",
        "Insert a copy of vehicle <id> at (x, y[, z]) with yaw <rad> rad.",
        f"Change the weather to <{'|'.join(WEATHERS)}>.",
    ]
    raise ValueError(f"unrecognised edit instruction {text!r}; expected one of: {' | '.join(examples)}")


# ----------------------------------------------------------------------------- applying an edit


@dataclass
class ReferenceFrame:
    """The frame whose pose a stopped vehicle keeps."""

    frame: int
    """Its index in the scene."""
    gaussians: dict[str, np.ndarray]
    """Its Gaussians, in its own ego frame."""
    boxes: list[dict]
    """Its ``boxes3d`` rows."""
    to_ego_44: np.ndarray
    """Its ego frame -> the edited frame's ego frame: ``inv(ego2world[edited]) @ ego2world[frame]``."""


def _box(boxes: list[dict], instance_id: str, where: str) -> dict:
    for b in boxes:
        if b["instance_id"] == instance_id:
            return b
    ids = sorted({b["instance_id"] for b in boxes})
    raise ValueError(f"{where}: no vehicle with instance id '{instance_id}' (ids present: {ids})")


def apply_edit(
    edit: Edit,
    gaussians: dict[str, np.ndarray],
    boxes: list[dict],
    *,
    scene: str,
    frame: int,
    t_s: float = 0.0,
    reference: ReferenceFrame | None = None,
    margin: float = 0.1,
) -> dict[str, np.ndarray]:
    """The frame's Gaussians with ``edit`` applied (``boxes`` are the frame's ``boxes3d`` rows).

    ``t_s``: seconds since the edit started (a move's distance is ``speed * t_s``). ``reference``: the frame whose
    pose a stopped vehicle keeps (needed by ``StopVehicle`` only). ``Weather`` returns ``gaussians`` itself.
    """
    where = f"{scene}/frame_{frame:03d}"
    match edit:
        case RemoveVehicle(instance_id=i):
            return remove_vehicle(gaussians, _box(boxes, i, where), margin)
        case MoveVehicle(instance_id=i, trajectory=t, speed_mps=v):
            return move_vehicle(gaussians, _box(boxes, i, where), np.asarray(t), v, t_s, margin)
        case StopVehicle(instance_id=i):
            if reference is None:
                raise ValueError(f"{where}: stop {i} needs the reference frame whose pose the vehicle keeps")
            ref_box = _box(reference.boxes, i, f"{scene}/frame_{reference.frame:03d}")
            box = next((b for b in boxes if b["instance_id"] == i), None)
            return stop_vehicle(gaussians, box, reference.gaussians, ref_box, reference.to_ego_44, margin)
        case InsertVehicle(donor_id=d, center=c, yaw=y):
            donor_box = _box(boxes, d, where)
            center = [*c, float(donor_box["center"][2])] if len(c) == 2 else list(c)
            donor = extract_vehicle(gaussians, donor_box, margin)
            return insert_vehicle(gaussians, donor, {**donor_box, "center": center, "yaw": y})
        case Weather():
            return gaussians
    raise TypeError(f"{where}: not an edit: {edit!r} (edits: {sorted(EDITS)})")
