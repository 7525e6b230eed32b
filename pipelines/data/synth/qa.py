"""QA of every task family, with answers computed from the ground truth written to the tables.

QA are built from the rows exactly as stored (float32 values), so anyone can re-derive each
answer from ``boxes3d``/``boxes2d``/``ego_poses``. Every record's ``gt`` column is the JSON of
the facts its answer came from. Every human turn starts with "Based on <gauss>, ...": trajectory QA
is the paper's example with the placeholder put in front, as the public release's loader inserts it,
so Gaussian and image-only models train on the same task families. Answer formats (evaluation
parses them):

- ``rdp`` distance (category ``2D_perception_infos``):
  "The object is approximately {d:.1f} meters away from the ego vehicle.", d = Euclidean
  distance in the ego xy plane from the ego origin (rear axle) to the 3D box centre.
- ``rdp`` description (``region_description``): "It is a(n) {colour} {car|truck|bus}, {state}." or
  "It is a pedestrian in {colour}, {standing|walking ...}."; state from the box attribute and
  the direction of its velocity relative to the ego heading.
- ``vg2d`` (``2D_visual_grounding``): "<CAM> <box>(x1,y1),(x2,y2)</box>", integer pixels of the
  stored image, pixel-edge coordinates (pixel j spans [j, j+1), so x2/y2 are exclusive): the
  instance's ``boxes2d`` row.
- ``vg3d`` (``3D_visual_grounding``): "center: (x, y, z), size: (l, w, h)", metres in the ego
  frame, 2 decimals: the instance's ``boxes3d`` row.
- ``plan`` (``planning_speed`` / ``planning_direction``): "{Decision}. Reason: {why}." with the
  decision label in ``gt["decision"]`` (rules in ``pipelines.data.synth.planning``).
- ``traj`` (``trajectory_prediction``): "[PT, [x, y, z, qx, qy, qz, qw], ...]".

Grounding questions name "the {colour} {noun} {on the left | in the middle | on the right}" (box
centre by image thirds) and ask only about referents that phrase makes unambiguous: the colour
and noun alone, or failing that together with the position, are unique among the camera's 2D
boxes; at least 30 % of the object is visible; and its 2D box is at least ``min_referent_pixels`` wide and high
(``data.min_referent_pixels``, 8: one patch of the tiny vision tower; a smaller object cannot be told apart in the
image tokens, so asking to locate it tests luck, not grounding).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipelines.data.layout import CAMERAS, GAUSS_TOKEN, gaussians_relpath, image_relpath
from pipelines.data.synth import planning
from pipelines.data.synth.scene import MOVING_SPEED

MIN_REFERENT_VISIBILITY = 0.3


@dataclass
class FrameTruth:
    frame_idx: int
    boxes3d: list[dict]
    boxes2d: list[dict]


@dataclass
class SceneTruth:
    scene_id: str
    split: str
    width: int
    height: int
    rate_hz: float
    ego2world_F44: np.ndarray
    """Ego poses as stored (float32 values)."""
    frames: list[FrameTruth]
    looks: dict[str, tuple[str, str]]
    """instance_id -> (kind, colour name)."""
    direction_truth: Callable[[int, int], str | None]
    """(frame, horizon frames) -> what the scene itself says the ego does laterally, None if unclear."""


def noun_phrase(kind: str, colour: str) -> str:
    return f"pedestrian in {colour}" if kind == "pedestrian" else f"{colour} {kind}"


def with_article(phrase: str) -> str:
    return f"{'an' if phrase[0] in 'aeiou' else 'a'} {phrase}"


def _box_text(cam: str, box: list[float]) -> str:
    x1, y1, x2, y2 = (int(v) for v in box)
    return f"<{cam}> <box>({x1},{y1}),({x2},{y2})</box>"


def _relation(box: list[float], width: int) -> str:
    cx = (box[0] + box[2]) / 2
    return "on the left" if cx < width / 3 else ("on the right" if cx > 2 * width / 3 else "in the middle")


def _state(row: dict, kind: str) -> str:
    vx, vy = row["velocity"]
    speed = float(np.hypot(vx, vy))
    if kind == "pedestrian":
        if speed <= MOVING_SPEED:
            return "standing"
        return "walking across the road" if abs(vy) > abs(vx) else "walking along the road"
    if row["attribute"] == "vehicle.parked":
        return "parked"
    if speed <= MOVING_SPEED:
        return "stopped"
    return "moving in the same direction as the ego vehicle" if vx > 0 else "moving in the opposite direction"


class _Records:
    """Accumulates QA rows with deterministic sample ids."""

    def __init__(self, truth: SceneTruth):
        self.truth = truth
        self.rows: list[dict] = []
        self._count: Counter = Counter()

    def add(self, frame: int, task: str, category: str, human: str, gpt: str, views: list[str], gt: dict) -> None:
        k = self._count[(frame, task)]
        self._count[(frame, task)] += 1
        t = self.truth
        self.rows.append(
            {
                "sample_id": f"{t.scene_id}/{frame:05d}/{task}/{k:02d}",
                "scene_token": t.scene_id,
                "frame_idx": frame,
                "task": task,
                "category": category,
                "conversations": [{"from": "human", "value": human}, {"from": "gpt", "value": gpt}],
                "image": [image_relpath(t.scene_id, cam, frame) for cam in views],
                "views": list(views),
                "gauss": [gaussians_relpath(t.scene_id, frame)],
                "split": t.split,
                "gt": json.dumps(gt, sort_keys=True),
            }
        )


def _pick(rng: np.random.Generator, items: list, n: int) -> list:
    if len(items) <= n:
        return items
    return [items[i] for i in sorted(rng.choice(len(items), size=n, replace=False))]


def _referents(truth: SceneTruth, ft: FrameTruth, min_px: int) -> list[tuple[dict, str]]:
    """(boxes2d row, unambiguous referring phrase) per well-visible object whose box is >= ``min_px`` both ways
    (the phrase is unambiguous among all the camera's boxes, small ones included)."""
    out = []
    for cam in CAMERAS:
        rows = [r for r in ft.boxes2d if r["camera"] == cam]
        phrases = [noun_phrase(*truth.looks[r["instance_id"]]) for r in rows]
        rels = [_relation(r["box"], truth.width) for r in rows]
        by_phrase = Counter(phrases)
        by_both = Counter(zip(phrases, rels, strict=True))
        for r, p, rel in zip(rows, phrases, rels, strict=True):
            x1, y1, x2, y2 = r["box"]
            if r["visible_fraction"] < MIN_REFERENT_VISIBILITY or min(x2 - x1, y2 - y1) < min_px:
                continue
            if by_phrase[p] == 1 or by_both[(p, rel)] == 1:
                out.append((r, f"{p} {rel}"))
    return out


def _perception(rec: _Records, ft: FrameTruth, rng: np.random.Generator, per_task: int) -> None:
    truth = rec.truth
    f = ft.frame_idx
    boxes3d = {r["instance_id"]: r for r in ft.boxes3d}
    visible = [r for r in ft.boxes2d if r["visible_fraction"] >= MIN_REFERENT_VISIBILITY]
    picked = _pick(rng, visible, per_task)
    for n, r in enumerate(picked):
        b3 = boxes3d[r["instance_id"]]
        cam, box = r["camera"], r["box"]
        base = {"instance_id": r["instance_id"], "camera": cam, "box": box, "center": b3["center"]}
        if n % 2 == 0:
            d = float(np.hypot(b3["center"][0], b3["center"][1]))
            rec.add(
                f,
                "rdp",
                "2D_perception_infos",
                f"Based on {GAUSS_TOKEN}, can you estimate the distance between the {_box_text(cam, box)} "
                "and the ego vehicle?",
                f"The object is approximately {d:.1f} meters away from the ego vehicle.",
                [cam],
                {**base, "distance_m": d, "distance": "ego-xy Euclidean distance, ego origin to 3D box centre"},
            )
        else:
            kind, colour = truth.looks[r["instance_id"]]
            state = _state(b3, kind)
            rec.add(
                f,
                "rdp",
                "region_description",
                f"Based on {GAUSS_TOKEN}, what is the object at {_box_text(cam, box)} and what is it doing?",
                f"It is {with_article(noun_phrase(kind, colour))}, {state}.",
                [cam],
                {**base, "category": b3["category"], "attribute": b3["attribute"], "colour": colour, "state": state},
            )


def _grounding(rec: _Records, ft: FrameTruth, rng: np.random.Generator, per_task: int, min_px: int) -> None:
    f = ft.frame_idx
    boxes3d = {r["instance_id"]: r for r in ft.boxes3d}
    refs = _referents(rec.truth, ft, min_px)
    for r, phrase in _pick(rng, refs, per_task):
        cam = r["camera"]
        rec.add(
            f,
            "vg2d",
            "2D_visual_grounding",
            f"Based on {GAUSS_TOKEN}, please locate the {phrase} in <{cam}>.",
            _box_text(cam, r["box"]),
            [cam],
            {"instance_id": r["instance_id"], "camera": cam, "box": r["box"], "referent": phrase},
        )
    for r, phrase in _pick(rng, refs, per_task):
        cam = r["camera"]
        b3 = boxes3d[r["instance_id"]]
        c, s = b3["center"], b3["size"]
        answer = f"center: ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}), size: ({s[0]:.2f}, {s[1]:.2f}, {s[2]:.2f})"
        rec.add(
            f,
            "vg3d",
            "3D_visual_grounding",
            f"Based on {GAUSS_TOKEN}, please locate the {phrase} in <{cam}> in 3D: give its center and size "
            "in the ego frame.",
            answer,
            [cam],
            {
                "instance_id": r["instance_id"],
                "camera": cam,
                "center": c,
                "size": s,
                "yaw": b3["yaw"],
                "referent": phrase,
            },
        )


def _obstacle_text(row: dict | None, looks: dict) -> str:
    if row is None:
        return f"the ego lane is clear for the next {planning.OBSTACLE_RANGE_M:.0f} meters"
    kind, colour = looks[row["instance_id"]]
    d = float(np.hypot(row["center"][0], row["center"][1]))
    speed = float(np.hypot(*row["velocity"]))
    motion = "stopped" if speed <= MOVING_SPEED else f"moving at {speed:.1f} m/s"
    return f"{with_article(noun_phrase(kind, colour))} is {d:.1f} meters ahead in the ego lane, {motion}"


def _plan(rec: _Records, ft: FrameTruth, horizon: int) -> None:
    truth = rec.truth
    f = ft.frame_idx
    poses = truth.ego2world_F44
    if f + horizon >= len(poses):
        return
    secs = horizon / truth.rate_hz
    obstacle = planning.lane_obstacle(ft.boxes3d)
    obstacle_gt = (
        None
        if obstacle is None
        else {
            "instance_id": obstacle["instance_id"],
            "center": obstacle["center"],
            "distance_m": float(np.hypot(obstacle["center"][0], obstacle["center"][1])),
        }
    )
    views = list(CAMERAS)
    label, facts = planning.speed_decision(poses, f, horizon, truth.rate_hz)
    if label is not None:
        rec.add(
            f,
            "plan",
            "planning_speed",
            f"Based on {GAUSS_TOKEN}, how should the ego vehicle adjust its speed over the next {secs:g} seconds?",
            f"{label.capitalize()}. Reason: {_obstacle_text(obstacle, truth.looks)}; the ego vehicle drives "
            f"{facts['v_now']:.1f} m/s now.",
            views,
            {"decision": label, "horizon_s": secs, "obstacle": obstacle_gt, **facts},
        )
    label, facts = planning.direction_decision(poses, f, horizon)
    if label is not None and label == truth.direction_truth(f, horizon):
        dpsi = facts["yaw_change_deg"]
        if label.startswith("turn"):
            why = f"the road bends to the {label.split()[1]}; the heading changes by {abs(dpsi):.0f} degrees"
        elif label.startswith("change lane"):
            side = label.split()[-1]
            why = f"{_obstacle_text(obstacle, truth.looks)}, and the {side} lane is free"
        else:
            why = "the road ahead is straight and the ego vehicle keeps its lane"
        rec.add(
            f,
            "plan",
            "planning_direction",
            f"Based on {GAUSS_TOKEN}, which way should the ego vehicle go over the next {secs:g} seconds?",
            f"{label.capitalize()}. Reason: {why}.",
            views,
            {"decision": label, "horizon_s": secs, "obstacle": obstacle_gt, **facts},
        )


def _trajectory(rec: _Records, start: int) -> None:
    truth = rec.truth
    history, future = planning.trajectory_window(truth.ego2world_F44, start)
    f = start + planning.HISTORY
    rec.add(
        f,
        "traj",
        "trajectory_prediction",
        f"Based on {GAUSS_TOKEN}, there are last {planning.HISTORY} frames of ego trajectory: "
        f"{planning.format_poses(history)}. "
        f"Predict the future {planning.FUTURE}-frame ego trajectory.",
        planning.format_poses(future),
        list(CAMERAS),
        {
            "window": [start, start + planning.WINDOW - 1],
            "reference_frame": f,
            "order": "x, y, z, qx, qy, qz, qw in the reference frame's ego frame",
            "history": history,
            "future": future,
        },
    )


def scene_qa(
    truth: SceneTruth, seed: int, scene_index: int, per_task: int, horizon: int, min_referent_pixels: int
) -> list[dict]:
    """All QA records of one scene (deterministic in seed and scene index)."""
    rec = _Records(truth)
    for ft in truth.frames:
        rng = np.random.default_rng([seed, scene_index, ft.frame_idx, 99])
        _perception(rec, ft, rng, per_task)
        _grounding(rec, ft, rng, per_task, min_referent_pixels)
        _plan(rec, ft, horizon)
    for start in range(len(truth.frames) - planning.WINDOW + 1):
        _trajectory(rec, start)
    return rec.rows
