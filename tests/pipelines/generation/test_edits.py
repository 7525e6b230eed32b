"""4D edits on Gaussians: box membership, remove/move/stop/insert, typed edits and their instruction texts."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from pipelines.data.reader import GSQADataset
from pipelines.generation.edits import (
    InsertVehicle,
    MoveVehicle,
    ReferenceFrame,
    RemoveVehicle,
    StopVehicle,
    Weather,
    apply_edit,
    edit_instruction,
    edit_to_dict,
    extract_vehicle,
    gaussians_in_box,
    insert_vehicle,
    move_vehicle,
    moved_box,
    parse_edit,
    remove_vehicle,
    stop_vehicle,
)
from pipelines.recon.init import _inside_boxes

BOX_A = {"instance_id": "car-a", "center": [10.0, 3.0, 0.8], "size": [4.5, 1.9, 1.6], "yaw": 0.3}
BOX_B = {"instance_id": "car-b", "center": [-8.0, -4.0, 0.8], "size": [4.0, 1.8, 1.5], "yaw": -1.2}
N_CAR = 50


def to_local(xyz, box):
    """Box-frame coordinates by hand: translate, then rotate by -yaw about z."""
    d = np.asarray(xyz, np.float64) - box["center"]
    c, s = math.cos(box["yaw"]), math.sin(box["yaw"])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)


def to_ego(local, box):
    c, s = math.cos(box["yaw"]), math.sin(box["yaw"])
    x, y = c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]
    return np.stack([x, y, local[:, 2]], 1) + box["center"]


def random_rows(rng, xyz) -> dict[str, np.ndarray]:
    n = len(xyz)
    q = rng.normal(size=(n, 4))
    return {
        "xyz": np.asarray(xyz, np.float32),
        "scale": rng.uniform(0.05, 0.3, (n, 3)).astype(np.float32),
        "rotation": (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        "opacity": rng.uniform(0.1, 1.0, n).astype(np.float32),
        "color": rng.uniform(0, 1, (n, 3)).astype(np.float32),
        "feature": rng.normal(size=(n, 4)).astype(np.float32),
    }


def concat(a, b):
    return {k: np.concatenate([a[k], b[k]]) for k in a}


@pytest.fixture
def scene():
    """200 background Gaussians well outside both boxes, then 50 inside car-a (rows 200..249)."""
    rng = np.random.default_rng(0)
    bg = rng.uniform([-30, -30, 0], [30, 30, 3], (2000, 3))
    far = np.all(np.abs(to_local(bg, BOX_A)) > np.array(BOX_A["size"]) / 2 + 0.5, axis=1)
    far &= np.all(np.abs(to_local(bg, BOX_B)) > np.array(BOX_B["size"]) / 2 + 0.5, axis=1)
    bg = bg[far][:200]
    car_local = rng.uniform(-1, 1, (N_CAR, 3)) * (np.array(BOX_A["size"]) / 2 - 0.05)
    return concat(random_rows(rng, bg), random_rows(rng, to_ego(car_local, BOX_A)))


def assert_same(a, b, rows_a=slice(None), rows_b=slice(None)):
    for k in a:
        np.testing.assert_array_equal(a[k][rows_a], b[k][rows_b], err_msg=k)


def test_gaussians_in_box_uses_the_oriented_box_and_margin():
    local = np.array([[2.25 + 0.05, 0, 0], [2.25 + 0.15, 0, 0], [0, 0.95 + 0.08, 0], [0, 0, -0.8 - 0.05], [0, 0, 0]])
    xyz = to_ego(local, BOX_A)
    np.testing.assert_array_equal(gaussians_in_box(xyz, BOX_A), [True, False, True, True, True])
    np.testing.assert_array_equal(gaussians_in_box(xyz, BOX_A, margin=0.0), [False, False, False, False, True])
    # the unrotated reading of the same points: the yaw matters
    assert not gaussians_in_box(np.array([[10 + 2.3, 3.0, 0.8]]), {**BOX_A, "yaw": math.pi / 2})[0]


def test_box_membership_agrees_with_the_reconstruction_on_dataset_boxes(synth_small):
    frame = GSQADataset(synth_small).scene("scene-0000").frame(2)
    pts = frame.lidar()[:, :3].astype(np.float64)
    counts = []
    for box in frame.boxes3d():
        ours = gaussians_in_box(pts, box, margin=0.2)
        np.testing.assert_array_equal(ours, _inside_boxes(pts, [box]))
        counts.append(int(ours.sum()))
    assert max(counts) > 100  # a real vehicle's LiDAR returns


def test_remove_vehicle_removes_exactly_the_box_and_keeps_the_rest(scene):
    out = remove_vehicle(scene, BOX_A)
    assert len(out["xyz"]) == 200 and out.keys() == scene.keys()
    assert_same(out, scene, slice(None), slice(0, 200))
    assert gaussians_in_box(out["xyz"], BOX_A).sum() == 0


def test_move_vehicle_straight_translates_by_speed_times_t(scene):
    heading = np.array([math.cos(BOX_A["yaw"]), math.sin(BOX_A["yaw"])])
    traj = np.array([BOX_A["center"][:2] + 30 * heading])
    out = move_vehicle(scene, BOX_A, traj, speed_mps=5.0, t_s=1.5)
    shift = np.array([*(7.5 * heading), 0.0])
    np.testing.assert_allclose(out["xyz"][200:].mean(0) - scene["xyz"][200:].mean(0), shift, atol=1e-4)
    np.testing.assert_allclose(out["xyz"][200:], scene["xyz"][200:] + shift, atol=1e-4)
    np.testing.assert_allclose(np.abs((out["rotation"][200:] * scene["rotation"][200:]).sum(1)), 1.0, atol=1e-5)
    assert_same(out, scene, slice(0, 200), slice(0, 200))  # the others untouched, in place
    for k in ("scale", "opacity", "color", "feature"):
        np.testing.assert_array_equal(out[k], scene[k])
    box = moved_box(BOX_A, traj, 5.0, 1.5)
    np.testing.assert_allclose(box["center"], np.array(BOX_A["center"]) + shift, atol=1e-9)
    assert box["yaw"] == pytest.approx(BOX_A["yaw"]) and box["instance_id"] == "car-a"


def test_move_vehicle_turns_to_the_path_heading_and_stops_at_its_end(scene):
    c = np.array(BOX_A["center"])
    heading = np.array([math.cos(0.3), math.sin(0.3)])
    left = np.array([-heading[1], heading[0]])
    corner = c[:2] + 2 * heading
    traj = np.array([corner, corner + 10 * left])
    box = moved_box(BOX_A, traj, speed_mps=2.5, t_s=2.0)  # 5 m: 2 m to the corner, 3 m after it
    np.testing.assert_allclose(box["center"], [*(corner + 3 * left), c[2]], atol=1e-9)
    assert box["yaw"] == pytest.approx(0.3 + math.pi / 2)
    out = move_vehicle(scene, BOX_A, traj, 2.5, 2.0)
    before, after = extract_vehicle(scene, BOX_A), extract_vehicle(out, box)
    np.testing.assert_allclose(after["xyz"], before["xyz"], atol=1e-4)  # rigid: the same shape in its box frame
    np.testing.assert_allclose(np.abs((after["rotation"] * before["rotation"]).sum(1)), 1.0, atol=1e-5)
    np.testing.assert_allclose(to_local(out["xyz"][200:], box), to_local(scene["xyz"][200:], BOX_A), atol=1e-4)
    end = moved_box(BOX_A, traj, 2.5, 100.0)
    np.testing.assert_allclose(end["center"][:2], corner + 10 * left, atol=1e-9)
    up = moved_box(BOX_A, np.array([[*corner, 2.0]]), 1.0, 1.0)  # [T, 3]: the path's heights are the centre's
    assert up["center"][2] == pytest.approx(0.8 + 1.2 / 2.0)


def test_stop_vehicle_keeps_the_reference_pose(scene):
    """Ego drove 5 m forward between frame f and the later frame; the car moved 6 m. Stopped, it stays put."""
    f_to_later = np.eye(4)
    f_to_later[0, 3] = -5.0
    later_bg = {**scene, "xyz": scene["xyz"] + np.array([-5.0, 0, 0], np.float32)}
    later_bg = {k: v[:200] for k, v in later_bg.items()}
    box_later = {**BOX_A, "center": [10.0 - 5.0 + 6.0, 3.0, 0.8]}
    rng = np.random.default_rng(1)
    car_later = random_rows(rng, to_ego(to_local(scene["xyz"][200:], BOX_A), box_later))
    later = concat(later_bg, car_later)
    out = stop_vehicle(later, box_later, scene, BOX_A, f_to_later)
    assert len(out["xyz"]) == 250 and gaussians_in_box(out["xyz"], box_later).sum() == 0
    assert_same(out, later, slice(0, 200), slice(0, 200))
    np.testing.assert_allclose(out["xyz"][200:], scene["xyz"][200:] + np.array([-5.0, 0, 0]), atol=1e-5)
    for k in ("scale", "opacity", "color", "feature"):
        np.testing.assert_array_equal(out[k][200:], scene[k][200:])
    absent = stop_vehicle(later_bg, None, scene, BOX_A, f_to_later)  # the vehicle has left: only the insert
    assert len(absent["xyz"]) == 250
    ref = ReferenceFrame(0, scene, [BOX_A, BOX_B], f_to_later)
    via = apply_edit(StopVehicle("car-a"), later, [box_later], scene="scene-0001", frame=3, reference=ref)
    assert_same(via, out)


def test_insert_vehicle_places_the_donor_at_the_new_box(scene):
    donor = extract_vehicle(scene, BOX_A)
    assert len(donor["xyz"]) == N_CAR
    np.testing.assert_allclose(donor["xyz"], to_local(scene["xyz"][200:], BOX_A), atol=1e-5)
    new_box = {**BOX_A, "center": [0.0, -15.0, 0.8], "yaw": 2.0}
    out = insert_vehicle(scene, donor, new_box)
    assert len(out["xyz"]) == 250 + N_CAR
    assert_same(out, scene, slice(0, 250), slice(None))
    np.testing.assert_allclose(out["xyz"][250:], to_ego(donor["xyz"], new_box), atol=1e-4)
    assert gaussians_in_box(out["xyz"], new_box).sum() == N_CAR
    via = apply_edit(InsertVehicle("car-a", (0.0, -15.0), 2.0), scene, [BOX_A], scene="s", frame=0)
    np.testing.assert_allclose(via["xyz"], out["xyz"], atol=1e-5)
    with pytest.raises(ValueError, match=r"field 'feature' has row shape \(4,\) and \(2,\)"):
        insert_vehicle(scene, {**donor, "feature": donor["feature"][:, :2]}, new_box)


def test_apply_edit_dispatches_and_weather_leaves_geometry(scene):
    boxes = [BOX_A, BOX_B]
    assert_same(apply_edit(RemoveVehicle("car-a"), scene, boxes, scene="s", frame=0), remove_vehicle(scene, BOX_A))
    move = MoveVehicle("car-a", ((20.0, 6.0),), 4.0)
    assert_same(
        apply_edit(move, scene, boxes, scene="s", frame=0, t_s=0.5),
        move_vehicle(scene, BOX_A, np.array([[20.0, 6.0]]), 4.0, 0.5),
    )
    assert apply_edit(Weather("fog"), scene, boxes, scene="s", frame=0) is scene


EDITS = [
    RemoveVehicle("scene-0000-car-05"),
    MoveVehicle("car-a", ((12.5, 3.0), (20.0, -1.25)), 4.0),
    MoveVehicle("car-a", [[12.5, 3.0, 0.9]], 0.5),
    StopVehicle("scene-0000-truck-01"),
    InsertVehicle("car-b", (1.5, -2.0), 0.7853981633974483),
    InsertVehicle("car-b", (1.5, -2.0, 0.75)),
    Weather("rain"),
]


@pytest.mark.parametrize("edit", EDITS, ids=lambda e: e.op)
def test_parse_edit_round_trips(edit):
    assert parse_edit(edit_instruction(edit)) == edit
    assert parse_edit(edit_to_dict(edit)) == edit
    assert parse_edit(json.dumps(edit_to_dict(edit))) == edit


def test_instruction_texts():
    texts = [edit_instruction(e) for e in EDITS]
    assert texts == [
        "Remove vehicle scene-0000-car-05 from the scene.",
        "Move vehicle car-a along the path (12.5, 3) -> (20, -1.25) at 4 m/s.",
        "Move vehicle car-a along the path (12.5, 3, 0.9) at 0.5 m/s.",
        "Stop vehicle scene-0000-truck-01 and keep it where it is.",
        "Insert a copy of vehicle car-b at (1.5, -2) with yaw 0.7853981633974483 rad.",
        "Insert a copy of vehicle car-b at (1.5, -2, 0.75) with yaw 0 rad.",
        "Change the weather to rain.",
    ]
    assert parse_edit("  change the weather to FOG ") == Weather("fog")
    assert edit_to_dict(EDITS[1]) == {
        "op": "move",
        "instance_id": "car-a",
        "trajectory": [[12.5, 3.0], [20.0, -1.25]],
        "speed_mps": 4.0,
    }


def test_errors_name_the_thing(scene):
    msg = "scene-0003/frame_007: no vehicle with instance id 'car-z' (ids present: ['car-a', 'car-b'])"
    for edit in (RemoveVehicle("car-z"), MoveVehicle("car-z", ((0.0, 0.0),), 1.0), InsertVehicle("car-z", (0, 0))):
        with pytest.raises(ValueError, match=re.escape(msg)):
            apply_edit(edit, scene, [BOX_B, BOX_A], scene="scene-0003", frame=7)
    ref = ReferenceFrame(2, scene, [BOX_B], np.eye(4))
    with pytest.raises(ValueError, match=re.escape("scene-0003/frame_002: no vehicle with instance id 'car-a'")):
        apply_edit(StopVehicle("car-a"), scene, [BOX_A], scene="scene-0003", frame=7, reference=ref)
    with pytest.raises(ValueError, match=re.escape("scene-0003/frame_007: stop car-a needs the reference frame")):
        apply_edit(StopVehicle("car-a"), scene, [BOX_A], scene="scene-0003", frame=7)
    weather = "unknown weather 'snow' (one of ['clear', 'rain', 'fog', 'night'])"
    for bad in (
        lambda: Weather("snow"),
        lambda: parse_edit("Change the weather to snow."),
        lambda: parse_edit({"op": "weather", "name": "snow"}),
    ):
        with pytest.raises(ValueError, match=re.escape(weather)):
            bad()
    with pytest.raises(ValueError, match=re.escape("unknown edit op 'paint' in {'op': 'paint'} (ops: ['insert',")):
        parse_edit({"op": "paint"})
    with pytest.raises(ValueError, match=re.escape("unrecognised edit instruction 'Paint car-a red.'; expected one")):
        parse_edit("Paint car-a red.")
    with pytest.raises(ValueError, match=re.escape("move car-a: speed_mps must be a finite number >= 0, got -1")):
        MoveVehicle("car-a", ((1.0, 2.0),), -1)
    with pytest.raises(ValueError, match=re.escape("move car-a: trajectory point must be 2 or 3 finite numbers")):
        MoveVehicle("car-a", ((1.0,),), 1.0)
    with pytest.raises(ValueError, match=re.escape("has no segment of positive length")):
        moved_box(BOX_A, np.array([BOX_A["center"][:2]]), 1.0, 1.0)
