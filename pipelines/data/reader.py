"""Typed, lazy reader of a NuScenes-GSQA dataset root (layout in ``pipelines.data.layout``).

ds = GSQADataset(root)
frame = ds.scene("scene-0000").frame(3)
rgb_HW3 = frame.image("CAM_FRONT")          # uint8 RGB
gs = frame.gaussians()                       # dict of [N, k] float32 arrays, memory-mapped
w = ds.world_samples(split="train")[0]       # a generation sample (GaussianDWM release imports)
latents_T2CHW = w.latents()                  # its target latents, rgb and depth streams
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
    GT_DEPTH_KEYS,
    OPTIONAL_TABLES,
    PSEUDO_DEPTH_KEY,
    TABLES,
    WEATHERS,
    DataError,
    decode_depth,
    depth_relpath,
    fsl_to_numpy,
    gaussians_relpath,
    image_relpath,
    lidar_relpath,
    read_depth_npz,
    read_image_file,
    read_latent_meta,
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
        if name in OPTIONAL_TABLES:
            return self._optional_table(name)
        if name not in TABLES:
            raise DataError(f"{self.root}: unknown table '{name}' (tables: {sorted(TABLES | OPTIONAL_TABLES)})")
        return self._tables[name]

    def has_table(self, name: str) -> bool:
        """Whether the dataset has the table (an optional one may be absent: read as empty)."""
        return name in TABLES or (self.root / f"{name}.parquet").is_file()

    @cached_property
    def _optional_tables(self) -> dict[str, pa.Table]:
        return {}

    def _optional_table(self, name: str) -> pa.Table:
        if name not in self._optional_tables:
            path = self.root / f"{name}.parquet"
            found = path.is_file()
            self._optional_tables[name] = (
                pq.read_table(path, memory_map=True) if found else OPTIONAL_TABLES[name].empty_table()
            )
        return self._optional_tables[name]

    def world(self, split: str | None = None) -> pa.Table:
        """The generation samples (``world`` table), of one split or all."""
        t = self.table("world")
        return t if split is None else t.filter(pc.equal(t["split"], split))

    def world_samples(self, split: str | None = None) -> list[WorldSample]:
        return [WorldSample(self, row) for row in self.world(split).to_pylist()]

    def world_sample(self, sample_id: str, split: str | None = None) -> WorldSample:
        """One generation sample; ``split`` picks the copy of a sample kept in both splits."""
        rows = [r for r in self.world(split).to_pylist() if r["sample_id"] == sample_id]
        if len(rows) != 1:
            how = "no" if not rows else f"{len(rows)} (in splits {[r['split'] for r in rows]}; pass split=)"
            raise DataError(f"{self.root}: {how} world sample '{sample_id}'" + (f" in {split}" if split else ""))
        return WorldSample(self, rows[0])

    @cached_property
    def _clip_index(self) -> dict[str, tuple[str, int]]:
        return {r["sample_id"]: (r["path"], r["row"]) for r in self.table("clip_text").to_pylist()}

    def clip_text_feature(self, sample_id: str) -> np.ndarray:
        """[D] float32 CLIP text feature of a QA sample (``clip_text`` table)."""
        if sample_id not in self._clip_index:
            raise DataError(f"{self.root}: QA sample '{sample_id}' has no CLIP text feature")
        rel, row = self._clip_index[sample_id]
        if rel not in self._clip_shards:
            path = self.root / rel
            if not path.is_file():
                raise DataError(f"{self.root}: QA sample '{sample_id}': missing CLIP shard {rel}")
            self._clip_shards[rel] = np.load(path, mmap_mode="r", allow_pickle=False)
        return np.array(self._clip_shards[rel][row], dtype=np.float32)

    def clip_text_features(self, sample_ids: list[str]) -> np.ndarray:
        """[N, D] float32 CLIP text features of QA samples, in the given order."""
        return np.stack([self.clip_text_feature(s) for s in sample_ids])

    @cached_property
    def _clip_shards(self) -> dict[str, np.ndarray]:
        return {}  # memory-mapped once per dataset object

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


class WorldSample:
    """A generation sample of the ``world`` table: a reference image, T pseudo RGB-D condition frames, T target
    latents (rgb, depth streams), and optionally T ground-truth frames and depths. Images are [H, W, 3] uint8 RGB,
    depths [H, W] float32 metres, all at their stored size."""

    def __init__(self, ds: GSQADataset, row: dict):
        self.ds = ds
        self.row = row

    def __repr__(self) -> str:
        return f"WorldSample({self.id!r}, {self.split}, frames={self.num_frames})"

    @property
    def id(self) -> str:
        return self.row["sample_id"]

    @property
    def split(self) -> str:
        return self.row["split"]

    @property
    def num_frames(self) -> int:
        return len(self.row["pseudo_rgb"])

    @property
    def fps(self) -> int:
        return int(self.row["fps"])

    @property
    def where(self) -> str:
        return f"world sample '{self.id}' ({self.split})"

    def _image(self, rel: str, what: str) -> np.ndarray:
        img = read_image_file(self.ds.root / rel, f"{self.where} {what}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def ref_image(self) -> np.ndarray:
        return self._image(self.row["ref_image"], "ref_image")

    def pseudo_rgb(self) -> np.ndarray:
        """[T, H, W, 3] uint8."""
        return np.stack([self._image(r, f"pseudo_rgb[{i}]") for i, r in enumerate(self.row["pseudo_rgb"])])

    def pseudo_depth(self) -> np.ndarray:
        """[T, H, W] float32 metres (the release's ``depth_proj``)."""
        rels = self.row["pseudo_depth"]
        return np.stack([self._depth(r, (PSEUDO_DEPTH_KEY,), f"pseudo_depth[{i}]") for i, r in enumerate(rels)])

    def gt_rgb(self) -> np.ndarray:
        """[T, H, W, 3] uint8; T = 0 when the sample has no ground truth."""
        rels = self.row["gt_rgb"]
        if not rels:
            return np.zeros((0, 0, 0, 3), np.uint8)
        return np.stack([self._image(r, f"gt_rgb[{i}]") for i, r in enumerate(rels)])

    def gt_depth(self) -> np.ndarray:
        """[T, H, W] float32 metres; T = 0 when the sample has no ground truth."""
        rels = self.row["gt_depth"]
        if not rels:
            return np.zeros((0, 0, 0), np.float32)
        return np.stack([self._depth(r, GT_DEPTH_KEYS, f"gt_depth[{i}]") for i, r in enumerate(rels)])

    def _depth(self, rel: str, keys: tuple[str, ...], what: str) -> np.ndarray:
        path = self.ds.root / rel
        if not path.is_file():
            raise DataError(f"{self.where} {what}: missing file {path}")
        return read_depth_npz(path, keys, f"{self.where} {what} {rel}")

    def latents(self) -> np.ndarray:
        """[T, 2, C, H, W] float32: rows ``latent_indices`` of the pack, stream 0 rgb, stream 1 depth."""
        pack = self.ds.root / self.row["latent_pack"]
        dtype, shape = read_latent_meta(pack, f"{self.where} latent_pack {self.row['latent_pack']}")
        memmap = np.memmap(pack, mode="r", dtype=dtype, shape=shape)
        return np.asarray(memmap[list(self.row["latent_indices"])], dtype=np.float32)
