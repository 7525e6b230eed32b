"""Typed, lazy reader of a NuScenes-GSQA dataset root (layout in ``pipelines.data.layout``).

ds = GSQADataset(root)
frame = ds.scene("scene-0000").frame(3)
rgb_HW3 = frame.image("CAM_FRONT")          # uint8 RGB
gs = frame.gaussians()                       # dict of [N, k] float32 arrays, memory-mapped
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from pipelines.data.layout import (
    TABLES,
    WEATHERS,
    DataError,
    decode_depth,
    depth_relpath,
    fsl_to_numpy,
    gaussians_relpath,
    image_relpath,
    lidar_relpath,
    read_image_file,
)


@dataclass(frozen=True)
class Camera:
    name: str
    width: int
    height: int
    K_33: np.ndarray  # intrinsics of the stored image
    sensor2ego_44: np.ndarray


def read_arrow(path: Path, where: str) -> pa.Table:
    """Memory-map an Arrow IPC file; errors name ``where``."""
    if not path.is_file():
        raise DataError(f"{where}: missing file {path}")
    try:
        return pa.ipc.open_file(pa.memory_map(str(path), "r")).read_all()
    except pa.ArrowInvalid as e:
        raise DataError(f"{where}: unreadable Arrow file {path} ({e})") from e


class GSQADataset:
    """A published dataset root. Only roots with a ``dataset.json`` are trusted."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        meta_path = self.root / "dataset.json"
        if not meta_path.is_file():
            raise DataError(f"{self.root}: not a gdwm dataset (dataset.json missing; was generation interrupted?)")
        self.meta: dict = json.loads(meta_path.read_text())

    def __repr__(self) -> str:
        return f"GSQADataset({str(self.root)!r}, scenes={self.meta.get('num_scenes')})"

    @property
    def fingerprint(self) -> str:
        return self.meta["fingerprint"]

    def table(self, name: str) -> pa.Table:
        if name not in TABLES:
            raise DataError(f"{self.root}: unknown table '{name}' (tables: {sorted(TABLES)})")
        return self._tables[name]

    @cached_property
    def _tables(self) -> dict[str, pa.Table]:
        out = {}
        for name in TABLES:
            path = self.root / f"{name}.parquet"
            if not path.is_file():
                raise DataError(f"{self.root}: missing table {path.name}")
            out[name] = pq.read_table(path, memory_map=True)
        return out

    @property
    def scene_ids(self) -> list[str]:
        return self.table("scenes").column("scene_id").to_pylist()

    @property
    def cameras(self) -> list[str]:
        return list(self.meta["cameras"])

    def scene(self, scene_id: str) -> Scene:
        if scene_id not in self.scene_ids:
            raise DataError(f"{self.root}: unknown scene '{scene_id}' (scenes: {self.scene_ids})")
        return Scene(self, scene_id)

    def scenes(self) -> list[Scene]:
        return [Scene(self, s) for s in self.scene_ids]

    def qa(self, split: str | None = None, task: str | None = None) -> pa.Table:
        t = self.table("qa")
        if split is not None:
            t = t.filter(pc.equal(t["split"], split))
        if task is not None:
            t = t.filter(pc.equal(t["task"], task))
        return t

    def _rows(self, table: str, scene_id: str, frame_idx: int | None = None) -> pa.Table:
        t = self.table(table)
        mask = pc.equal(t["scene_id"], scene_id)
        if frame_idx is not None:
            mask = pc.and_(mask, pc.equal(t["frame_idx"], frame_idx))
        return t.filter(mask)


class Scene:
    def __init__(self, ds: GSQADataset, scene_id: str):
        self.ds = ds
        self.id = scene_id

    def __repr__(self) -> str:
        return f"Scene({self.id!r}, frames={self.num_frames})"

    @cached_property
    def info(self) -> dict:
        return self.ds._rows("scenes", self.id).to_pylist()[0]

    @property
    def num_frames(self) -> int:
        return int(self.info["num_frames"])

    @property
    def weathers(self) -> list[str]:
        return list(self.info["weathers"])

    @cached_property
    def cameras(self) -> dict[str, Camera]:
        out = {}
        for r in self.ds._rows("cameras", self.id).to_pylist():
            K = np.array([[r["fx"], 0, r["cx"]], [0, r["fy"], r["cy"]], [0, 0, 1]], dtype=np.float64)
            out[r["camera"]] = Camera(
                r["camera"], r["width"], r["height"], K, np.asarray(r["sensor2ego"], dtype=np.float64).reshape(4, 4)
            )
        return out

    @cached_property
    def ego_poses(self) -> np.ndarray:
        """[F, 4, 4] ego->world, ordered by frame index."""
        t = self.ds._rows("ego_poses", self.id).sort_by("frame_idx")
        return fsl_to_numpy(t["ego2world"], 16).astype(np.float64).reshape(-1, 4, 4)

    def frame(self, frame_idx: int) -> Frame:
        if not 0 <= frame_idx < self.num_frames:
            raise DataError(f"{self.id}: frame {frame_idx} out of range (scene has {self.num_frames} frames)")
        return Frame(self, frame_idx)

    def frames(self) -> list[Frame]:
        return [Frame(self, i) for i in range(self.num_frames)]


class Frame:
    def __init__(self, scene: Scene, idx: int):
        self.scene = scene
        self.idx = idx

    def __repr__(self) -> str:
        return f"Frame({self.scene.id!r}, {self.idx})"

    @property
    def where(self) -> str:
        return f"{self.scene.id}/frame_{self.idx:03d}"

    @property
    def ego2world(self) -> np.ndarray:
        return self.scene.ego_poses[self.idx]

    def _camera(self, camera: str) -> Camera:
        if camera not in self.scene.cameras:
            raise DataError(f"{self.where}: unknown camera '{camera}' (cameras: {list(self.scene.cameras)})")
        return self.scene.cameras[camera]

    def image(self, camera: str, weather: str = "clear") -> np.ndarray:
        """[H, W, 3] uint8 RGB."""
        self._camera(camera)
        if weather not in WEATHERS:
            raise DataError(f"{self.where} {camera}: unknown weather '{weather}' (one of {list(WEATHERS)})")
        if weather not in self.scene.weathers:
            raise DataError(f"{self.where} {camera}: scene has no '{weather}' variant (has {self.scene.weathers})")
        path = self.scene.ds.root / image_relpath(self.scene.id, camera, self.idx, weather)
        img = read_image_file(path, f"{self.where} {camera}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def depth(self, camera: str) -> np.ndarray:
        """[H, W] float32 metres, 0 where there is no depth."""
        self._camera(camera)
        path = self.scene.ds.root / depth_relpath(self.scene.id, camera, self.idx)
        raw = read_image_file(path, f"{self.where} {camera} depth", cv2.IMREAD_UNCHANGED)
        if raw.dtype != np.uint16:
            raise DataError(f"{self.where} {camera}: depth image {path} is {raw.dtype}, expected uint16")
        return decode_depth(raw)

    def lidar(self) -> np.ndarray:
        """[N, 4] float32 (x, y, z, intensity) in the ego frame."""
        rel = lidar_relpath(self.scene.id, self.idx)
        t = read_arrow(self.scene.ds.root / rel, f"{self.where} lidar")
        return np.stack([t[c].to_numpy() for c in ("x", "y", "z", "intensity")], axis=1)

    def has_gaussians(self) -> bool:
        return (self.scene.ds.root / gaussians_relpath(self.scene.id, self.idx)).is_file()

    def gaussians(self) -> dict[str, np.ndarray]:
        """Gaussians in the ego frame: xyz/scale [N,3], rotation [N,4], opacity [N], color [N,3], feature [N,D]."""
        rel = gaussians_relpath(self.scene.id, self.idx)
        return gaussians_from_table(read_arrow(self.scene.ds.root / rel, f"{self.where} gaussians"))

    def boxes3d(self) -> list[dict]:
        return self.scene.ds._rows("boxes3d", self.scene.id, self.idx).to_pylist()

    def boxes2d(self, camera: str | None = None) -> list[dict]:
        rows = self.scene.ds._rows("boxes2d", self.scene.id, self.idx).to_pylist()
        if camera is not None:
            self._camera(camera)
            rows = [r for r in rows if r["camera"] == camera]
        return rows


def gaussians_from_table(t: pa.Table) -> dict[str, np.ndarray]:
    widths = {"xyz": 3, "scale": 3, "rotation": 4, "color": 3}
    out = {k: fsl_to_numpy(t[k], w) for k, w in widths.items()}
    out["opacity"] = t["opacity"].to_numpy()
    if "feature" in t.column_names:
        out["feature"] = fsl_to_numpy(t["feature"], t.schema.field("feature").type.list_size)
    else:  # reconstructed, not yet distilled
        out["feature"] = np.zeros((t.num_rows, 0), dtype=np.float32)
    return out
