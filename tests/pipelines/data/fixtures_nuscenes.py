"""A tiny nuScenes v1.0 root (tables + JPEGs + LIDAR_TOP sweeps) with hand-known poses and boxes.

Everything is yaw-only so tests can invert transforms by hand: ``rz(yaw)`` rotations, quaternions
``(cos(yaw/2), 0, 0, sin(yaw/2))``. Each sample has six camera keyframes, a LIDAR_TOP keyframe and one
non-keyframe LIDAR_TOP sweep (which the converter must ignore). Cameras fire ``CAM_DT_US`` after the
lidar, with their own ego pose shifted by ``CAM_SHIFT_M`` along world x.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

VERSION = "v1.0-mini"
CAMS = {  # channel -> (yaw of the optical axis in the ego frame, position on the ego)
    "CAM_FRONT": (0.0, (1.7, 0.0, 1.5)),
    "CAM_FRONT_RIGHT": (-0.96, (1.5, -0.5, 1.5)),
    "CAM_BACK_RIGHT": (-1.92, (1.0, -0.5, 1.5)),
    "CAM_BACK": (math.pi, (0.0, 0.0, 1.5)),
    "CAM_BACK_LEFT": (1.92, (1.0, 0.5, 1.5)),
    "CAM_FRONT_LEFT": (0.96, (1.5, 0.5, 1.5)),
}
RAW_W, RAW_H = 64, 36
FX = FY = 40.0
CX, CY = 32.0, 18.0
LIDAR_YAW, LIDAR_T = math.pi / 2, (0.9, 0.0, 1.8)
CAM_DT_US = 20_000
CAM_SHIFT_M = 0.3
T0_US = 1_532_402_927_647_951
# Box sizes in nuScenes order (w, l, h).
CAR_WLH = (1.8, 4.5, 1.6)
PED_WLH = (0.6, 0.7, 1.8)


def rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_z(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


# Optical (OpenCV) axes in a forward-looking camera's body: z forward = ego x, x right = -y, y down = -z.
CAM_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def quat_of(r: np.ndarray) -> list[float]:
    """(w, x, y, z) of a rotation matrix (trace > -1 holds for every rig rotation used here)."""
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    if w > 1e-6:
        return [w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)]
    x = math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2
    return [(r[2, 1] - r[1, 2]) / (4 * x), x, (r[0, 1] + r[1, 0]) / (4 * x), (r[0, 2] + r[2, 0]) / (4 * x)]


@dataclass
class Frame:
    token: str
    timestamp_us: int
    ego_yaw: float
    ego_t: np.ndarray  # lidar-time ego position (world)
    cam_ego_t: np.ndarray  # camera-time ego position (world), same yaw
    lidar_points: np.ndarray  # [N, 5] lidar frame
    boxes: dict[str, dict] = field(default_factory=dict)  # instance -> {"center", "yaw", "wlh"} world


@dataclass
class NuScenesFixture:
    root: Path
    scenes: dict[str, list[Frame]]

    def image_path(self, scene: str, frame: int, cam: str) -> Path:
        return self.root / "samples" / cam / f"{scene}_{frame}_{cam}.jpg"

    def table_path(self, name: str) -> Path:
        return self.root / VERSION / f"{name}.json"


def cam_rotation(cam: str) -> np.ndarray:
    """camera -> ego rotation."""
    return rz(CAMS[cam][0]) @ CAM_BASE


def _token(*parts) -> str:
    return "-".join(str(p) for p in parts)


TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "sensor", "ego_pose", "sample_annotation",
          "instance", "category", "attribute", "log")  # fmt: skip


def write_nuscenes(
    root: Path, scenes: tuple[str, ...] = ("scene-0001", "scene-0002"), frames: int = 3
) -> NuScenesFixture:
    rng = np.random.default_rng(0)
    t: dict[str, list[dict]] = {name: [] for name in TABLES}
    _static_rows(t)
    out = {scene: _scene_rows(root, t, s, scene, frames, rng) for s, scene in enumerate(scenes)}
    (root / VERSION).mkdir(parents=True, exist_ok=True)
    for name, rows in t.items():
        (root / VERSION / f"{name}.json").write_text(json.dumps(rows))
    return NuScenesFixture(root, out)


def _static_rows(t: dict) -> None:
    """Log, categories, attribute, sensors and their (scene-independent) calibrations."""
    t["log"].append(dict(token="log0", logfile="n008", vehicle="n008", date_captured="2018-08-01", location="sg"))
    t["category"] += [
        dict(token="cat-car", name="vehicle.car", description=""),
        dict(token="cat-ped", name="human.pedestrian.adult", description=""),
    ]
    t["attribute"].append(dict(token="attr-moving", name="vehicle.moving", description=""))
    intrinsic = [[FX, 0, CX], [0, FY, CY], [0, 0, 1]]
    for cam, (_, pos) in CAMS.items():
        t["sensor"].append(dict(token=f"sensor-{cam}", channel=cam, modality="camera"))
        rotation = quat_of(cam_rotation(cam))
        t["calibrated_sensor"].append(
            dict(token=f"calib-{cam}", sensor_token=f"sensor-{cam}", translation=list(pos), rotation=rotation,
                 camera_intrinsic=intrinsic)
        )  # fmt: skip
    t["sensor"].append(dict(token="sensor-LIDAR_TOP", channel="LIDAR_TOP", modality="lidar"))
    t["calibrated_sensor"].append(
        dict(token="calib-LIDAR_TOP", sensor_token="sensor-LIDAR_TOP", translation=list(LIDAR_T),
             rotation=quat_z(LIDAR_YAW), camera_intrinsic=[])
    )  # fmt: skip


def _scene_rows(root: Path, t: dict, s: int, scene: str, frames: int, rng: np.random.Generator) -> list[Frame]:
    tokens = [_token(scene, "sample", k) for k in range(frames)]
    t["scene"].append(
        dict(token=_token(scene), log_token="log0", nbr_samples=frames, name=scene, description=f"{scene}, rain",
             first_sample_token=tokens[0], last_sample_token=tokens[-1])
    )  # fmt: skip
    car, ped = _token(scene, "car"), _token(scene, "ped")
    out = []
    for k, tok in enumerate(tokens):
        ts = T0_US + s * 100_000_000 + k * 500_000
        yaw = 0.5 + 0.1 * k + s
        ego_t = np.array([100.0 + 5 * k, 50.0 + 2 * k + 10 * s, 0.3])
        points = rng.normal(size=(20, 5)).astype("f4") * 5
        frame = Frame(tok, ts, yaw, ego_t, ego_t + np.array([CAM_SHIFT_M, 0.0, 0.0]), points)
        # The car sits 10 m ahead, 1 m left of the ego, turned 0.2 rad; the pedestrian behind (first 2 frames).
        frame.boxes[car] = {"center": rz(yaw) @ [10.0, 1.0, 0.8] + ego_t, "yaw": yaw + 0.2, "wlh": CAR_WLH}
        if k < 2:
            frame.boxes[ped] = {"center": rz(yaw) @ [-8.0, -2.0, 0.9] + ego_t, "yaw": yaw, "wlh": PED_WLH}
        out.append(frame)
        prev, nxt = tokens[k - 1] if k else "", tokens[k + 1] if k + 1 < frames else ""
        t["sample"].append(dict(token=tok, timestamp=ts, scene_token=_token(scene), prev=prev, next=nxt))
        _sensor_rows(root, t, scene, k, frame)
    _annotation_rows(t, car, "cat-car", out)
    _annotation_rows(t, ped, "cat-ped", out)
    return out


def _annotation_rows(t: dict, inst: str, category: str, frames: list[Frame]) -> None:
    anns = [(f.token, f.boxes[inst]) for f in frames if inst in f.boxes]
    toks = [_token(inst, i) for i in range(len(anns))]
    t["instance"].append(
        dict(token=inst, category_token=category, nbr_annotations=len(anns), first_annotation_token=toks[0],
             last_annotation_token=toks[-1])
    )  # fmt: skip
    for i, (sample, b) in enumerate(anns):
        t["sample_annotation"].append(
            dict(token=toks[i], sample_token=sample, instance_token=inst, visibility_token="4",
                 attribute_tokens=["attr-moving"] if category == "cat-car" else [],
                 translation=[float(v) for v in b["center"]], size=list(b["wlh"]), rotation=quat_z(b["yaw"]),
                 prev=toks[i - 1] if i else "", next=toks[i + 1] if i + 1 < len(anns) else "", num_lidar_pts=5,
                 num_radar_pts=0)
        )  # fmt: skip


def _sensor_rows(root: Path, t: dict, scene: str, k: int, frame: Frame) -> None:
    def add(channel: str, ts: int, ego_t: np.ndarray, filename: str, key: bool, w: int = 0, h: int = 0) -> None:
        tok = _token(scene, k, channel, "key" if key else "sweep")
        translation = [float(v) for v in ego_t]
        t["ego_pose"].append(
            dict(token=f"ego-{tok}", timestamp=ts, rotation=quat_z(frame.ego_yaw), translation=translation)
        )
        t["sample_data"].append(
            dict(token=tok, sample_token=frame.token, ego_pose_token=f"ego-{tok}",
                 calibrated_sensor_token=f"calib-{channel}", timestamp=ts, fileformat=filename.rsplit(".", 1)[-1],
                 is_key_frame=key, height=h, width=w, filename=filename, prev="", next="")
        )  # fmt: skip

    lidar_rel = f"samples/LIDAR_TOP/{scene}_{k}.pcd.bin"
    (root / lidar_rel).parent.mkdir(parents=True, exist_ok=True)
    frame.lidar_points.tofile(root / lidar_rel)
    add("LIDAR_TOP", frame.timestamp_us, frame.ego_t, lidar_rel, True)
    add("LIDAR_TOP", frame.timestamp_us + 50_000, frame.ego_t + 1.0, f"sweeps/LIDAR_TOP/{scene}_{k}.pcd.bin", False)
    for c, cam in enumerate(CAMS):
        rel = f"samples/{cam}/{scene}_{k}_{cam}.jpg"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        bgr = np.zeros((RAW_H, RAW_W, 3), np.uint8)
        bgr[:] = (40 * c, 100 + 20 * k, 200)
        cv2.imwrite(str(root / rel), bgr)
        add(cam, frame.timestamp_us + CAM_DT_US, frame.cam_ego_t, rel, True, RAW_W, RAW_H)
