"""nuScenes v1.0 metadata read straight from its JSON tables (no nuscenes-devkit: it pins numpy 1.x and
its opencv-python-headless clashes with opencv-contrib's ``cv2``), indexed by token."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from pipelines.data.layout import DataError, pose_matrix

TABLE_NAMES = (
    "scene",
    "sample",
    "sample_data",
    "calibrated_sensor",
    "sensor",
    "ego_pose",
    "sample_annotation",
    "instance",
    "category",
    "attribute",
    "log",
)


class NuScenesTables:
    """The tables of ``<source>/<version>/``; lookups by token fail naming the table and the token."""

    def __init__(self, source: Path, version: str):
        self.source = Path(source)
        self.version = version
        folder = self.source / version
        if not folder.is_dir():
            raise DataError(f"{folder}: no such folder (expected the nuScenes tables in <source>/{version}/)")
        paths = {name: folder / f"{name}.json" for name in TABLE_NAMES}
        for name, path in paths.items():  # all present before the slow loads start
            if not path.is_file():
                raise DataError(f"{path}: missing nuScenes table '{name}.json'")
        big = ("sample_data", "ego_pose")
        self._tables = {name: _by_token(paths[name]) for name in TABLE_NAMES if name not in big}
        # trainval's sample_data and ego_pose hold ~2.6M rows each, mostly sweeps: keep keyframes only.
        keyframes = [sd for sd in _by_token(paths["sample_data"]).values() if sd.get("is_key_frame")]
        self._tables["sample_data"] = {sd["token"]: sd for sd in keyframes}
        wanted = {sd["ego_pose_token"] for sd in keyframes}
        self._tables["ego_pose"] = {k: v for k, v in _by_token(paths["ego_pose"]).items() if k in wanted}
        self._keyframes = {(sd["sample_token"], self.channel(sd)): sd for sd in keyframes}
        self._annotations: dict[str, list[dict]] = defaultdict(list)
        for ann in self._tables["sample_annotation"].values():
            self._annotations[ann["sample_token"]].append(ann)

    def get(self, table: str, token: str, where: str = "") -> dict:
        try:
            return self._tables[table][token]
        except KeyError:
            by = f" (referenced by {where})" if where else ""
            raise DataError(f"{self.version}/{table}.json: no record with token '{token}'{by}") from None

    # -- scenes and samples
    def scenes(self) -> list[dict]:
        """Scenes in name order (scene.json order is not guaranteed)."""
        return sorted(self._tables["scene"].values(), key=lambda s: s["name"])

    def samples(self, scene: dict) -> list[dict]:
        """The scene's keyframe samples, first to last along the ``next`` chain."""
        out, token = [], scene["first_sample_token"]
        while token:
            if len(out) > len(self._tables["sample"]):
                raise DataError(f"{self.version}/sample.json: the next chain of scene {scene['name']} loops")
            sample = self.get("sample", token, f"scene {scene['name']}")
            out.append(sample)
            token = sample["next"]
        return out

    def keyframe(self, sample: dict, channel: str, where: str) -> dict:
        sd = self._keyframes.get((sample["token"], channel))
        if sd is None:
            raise DataError(
                f"{where} {channel}: sample {sample['token']} has no {channel} keyframe in sample_data.json"
            )
        return sd

    def annotations(self, sample: dict) -> list[dict]:
        return self._annotations.get(sample["token"], [])

    # -- sensors and poses
    def channel(self, sd: dict) -> str:
        calib = self.get("calibrated_sensor", sd["calibrated_sensor_token"], f"sample_data {sd['token']}")
        return self.get("sensor", calib["sensor_token"], f"calibrated_sensor {calib['token']}")["channel"]

    def calibration(self, sd: dict) -> dict:
        return self.get("calibrated_sensor", sd["calibrated_sensor_token"], f"sample_data {sd['token']}")

    def sensor2ego(self, sd: dict) -> np.ndarray:
        calib = self.calibration(sd)
        return pose_matrix(calib["rotation"], calib["translation"])

    def ego2world(self, sd: dict) -> np.ndarray:
        """The ego pose at this sample_data's own timestamp."""
        pose = self.get("ego_pose", sd["ego_pose_token"], f"sample_data {sd['token']}")
        return pose_matrix(pose["rotation"], pose["translation"])

    # -- annotation labels
    def category(self, ann: dict) -> str:
        instance = self.get("instance", ann["instance_token"], f"sample_annotation {ann['token']}")
        return self.get("category", instance["category_token"], f"instance {instance['token']}")["name"]

    def attribute(self, ann: dict) -> str:
        tokens = ann.get("attribute_tokens") or []
        return self.get("attribute", tokens[0], f"sample_annotation {ann['token']}")["name"] if tokens else ""

    def timestamp_us(self, ann: dict) -> int:
        return int(self.get("sample", ann["sample_token"], f"sample_annotation {ann['token']}")["timestamp"])


def _by_token(path: Path) -> dict[str, dict]:
    try:
        rows = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: malformed JSON ({e.msg} at line {e.lineno})") from e
    return {r["token"]: r for r in rows}
