"""The NuScenes-GSQA on-disk layout and its atomic writer.

A dataset root looks like::

    dataset.json                 name, layout version, scene ids, cameras, counts, fingerprint, files, params (last)
    scenes.parquet               one row per scene
    frames.parquet               one row per (scene, frame)
    cameras.parquet              intrinsics + sensor->ego extrinsics per (scene, camera)
    ego_poses.parquet            ego->world pose per (scene, frame)
    boxes3d.parquet              3D boxes in the frame's ego frame
    boxes2d.parquet              2D boxes per camera (pixels of the stored image)
    qa.parquet                   QA records in the paper's JSON schema (+ sample_id, split, gt)
    routes.json                  optional: {scene: [[x, y], ...]} the ego's planned route, a world-frame polyline in
                                 driving order (navigation, never the recorded motion), for model.selector.path=route
    scenes/<scene>/images/<CAM>/<frame:05d>.png          RGB (clear weather)
    scenes/<scene>/images_<weather>/<CAM>/<frame:05d>.png weather variants of the same frames
    scenes/<scene>/depth/<CAM>/<frame:05d>.png           uint16 PNG, metres * DEPTH_SCALE, 0 = no depth
    scenes/<scene>/lidar/<frame:05d>.arrow               Arrow IPC: x, y, z, intensity (ego frame)
    scenes/<scene>/gaussians/<frame:05d>.arrow           Arrow IPC, GAUSSIAN_SCHEMA (ego frame)

Optional tables (``OPTIONAL_TABLES``), written only by the builders that have such data; a reader sees an empty
table where the file is absent, so datasets without them keep their bytes and fingerprint::

    world.parquet                generation samples (WORLD_SCHEMA): a reference image, T pseudo RGB-D condition
                                 frames, T ground-truth RGB/depth frames, fps, and T target latents of a pack
    clip_text.parquet            a QA sample's CLIP text feature: row ``row`` of the [N, D] ``.npy`` shard ``path``
    release/<path>               files copied verbatim from the GaussianDWM release at their source-relative paths
                                 (world images, ``.npz`` depths, latent packs with their ``meta.json``, CLIP shards)

A world sample's paths are relative to the dataset root. Its pseudo depth ``.npz`` holds ``depth_proj``
(``PSEUDO_DEPTH_KEY``), a ground-truth one the first of ``GT_DEPTH_KEYS`` it has; both [H, W] metres. Its latent
pack is a raw C-order memmap whose ``dtype``, ``shape`` [N, 2, C, H, W] and ``streams`` (rgb, depth) are in the
``meta.json`` beside it (``read_latent_meta``); the sample's latents are ``pack[latent_indices]``.

Conventions: ego frame x forward, y left, z up (nuScenes); camera frame x right, y down,
z forward (OpenCV); quaternions are stored (qw, qx, qy, qz) in tables and converted to the
paper's (qx, qy, qz, qw) order only in trajectory QA text. Poses are 4x4 row-major.

``dataset.json`` records what a reader needs to check the files against, not just trust them:

- ``fingerprint``: sha256 over ``relpath \\0 sha256 \\n`` of every file but dataset.json, in relpath order
  (compared component by component, as ``pathlib`` sorts); relpaths are POSIX, relative to the root. This formula
  is a data-format contract: ``gdwm`` recomputes it from ``files`` when it verifies a dataset (``fingerprint_of``).
- ``files``: ``{relpath: {"sha256": hex, "size": bytes, "mtime_ns": int}}`` of the same files, stat taken at
  publish time (renaming the finished directory into place keeps file mtimes). A file whose size and mtime still
  match can be trusted without reading it; any other is re-hashed.
- ``params``: the builder's parameters that determine the content (``DatasetWriter(params=...)``; the ``data.<key>``
  values it was built with, e.g. synthetic_mini's num_scenes, seed, width). ``gdwm run`` refuses a dataset whose
  recorded params differ from the requested ``data.<key>``. May be empty; absent in datasets of older versions.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import uuid
import zipfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipelines.data.config import DatasetConfig

LAYOUT_VERSION = 1
CAMERAS = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_FRONT_LEFT",
)
WEATHERS = ("clear", "rain", "fog", "night")
# Task families of the paper's QA: region description & perception, 2D/3D grounding, planning, trajectory.
TASKS = ("rdp", "vg2d", "vg3d", "plan", "traj")
SPLITS = ("train", "val")
DEPTH_SCALE = 256.0  # KITTI convention: uint16 value / 256 = metres, 0 = invalid (max 255.99 m)
GAUSS_TOKEN = "<gauss>"
ROUTES_FILE = "routes.json"


class DataError(ValueError):
    """Bad or missing data; the message names the file, scene, frame, camera or field."""


def contained(root: Path, rel: str | Path, what: str) -> Path:
    """``root / rel`` resolved (symlinks followed; it need not exist). Outside ``root`` (a ``..``, an absolute path or
    a symlink leading out) it is a DataError ``"<what> <rel> leads outside <root> ..."``. Every path that a source's
    records, options or globs name is read only through this."""
    base = Path(root).resolve()
    path = (base / rel).resolve()
    if not path.is_relative_to(base):
        raise DataError(f"{what} {rel} leads outside {base} (to {path}); refusing to read it")
    return path


def _fsl(n: int) -> pa.DataType:
    return pa.list_(pa.float32(), n)


POSE_TYPE = _fsl(16)

SCENES_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("name", pa.string()),
        ("num_frames", pa.int32()),
        ("frame_rate_hz", pa.float32()),
        ("description", pa.string()),
        ("weathers", pa.list_(pa.string())),
        ("source", pa.string()),
    ]
)
FRAMES_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("frame_idx", pa.int32()),
        ("timestamp_us", pa.int64()),
        ("token", pa.string()),
    ]
)
CAMERAS_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("camera", pa.string()),
        ("width", pa.int32()),
        ("height", pa.int32()),
        ("fx", pa.float32()),
        ("fy", pa.float32()),
        ("cx", pa.float32()),
        ("cy", pa.float32()),
        ("sensor2ego", POSE_TYPE),
    ]
)
EGO_POSES_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("frame_idx", pa.int32()),
        ("ego2world", POSE_TYPE),
    ]
)
BOXES3D_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("frame_idx", pa.int32()),
        ("instance_id", pa.string()),
        ("category", pa.string()),
        ("attribute", pa.string()),
        ("center", _fsl(3)),  # ego frame, metres
        ("size", _fsl(3)),  # length (x), width (y), height (z), metres
        ("yaw", pa.float32()),  # about ego z, radians
        ("velocity", _fsl(2)),  # ego frame, m/s
    ]
)
BOXES2D_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("frame_idx", pa.int32()),
        ("camera", pa.string()),
        ("instance_id", pa.string()),
        ("box", _fsl(4)),  # x1, y1, x2, y2 in pixels of the stored image
        ("visible_fraction", pa.float32()),
    ]
)
_TURN = pa.struct([("from", pa.string()), ("value", pa.string())])
QA_SCHEMA = pa.schema(
    [
        ("sample_id", pa.string()),
        ("scene_token", pa.string()),  # == scene_id
        ("frame_idx", pa.int32()),
        ("task", pa.string()),
        ("category", pa.string()),
        ("conversations", pa.list_(_TURN)),
        ("image", pa.list_(pa.string())),  # paths relative to the dataset root
        ("views", pa.list_(pa.string())),
        ("gauss", pa.list_(pa.string())),  # paths relative to the dataset root
        ("split", pa.string()),
        ("gt", pa.string()),  # JSON: the ground truth the answer was computed from
    ]
)
LIDAR_SCHEMA = pa.schema(
    [
        ("x", pa.float32()),
        ("y", pa.float32()),
        ("z", pa.float32()),
        ("intensity", pa.float32()),
    ]
)


def gaussian_schema(feature_dim: int, frame: str = "ego") -> pa.Schema:
    """Gaussians of one frame (in its ego frame unless ``frame`` says otherwise); activated values, not logits.

    ``feature_dim`` 0 (reconstruction before distillation) omits the ``feature`` column.
    """
    fields = [
        ("xyz", _fsl(3)),  # centre, metres, ego frame
        ("scale", _fsl(3)),  # standard deviations along the local axes, metres (> 0)
        ("rotation", _fsl(4)),  # unit quaternion (w, x, y, z), local -> ego
        ("opacity", pa.float32()),  # probability in [0, 1]
        ("color", _fsl(3)),  # linear RGB in [0, 1]
    ]
    if feature_dim:
        fields.append(("feature", _fsl(feature_dim)))  # compact feature code z_i
    return pa.schema(fields, metadata={b"gdwm.feature_dim": str(feature_dim).encode(), b"gdwm.frame": frame.encode()})


TABLES: dict[str, pa.Schema] = {
    "scenes": SCENES_SCHEMA,
    "frames": FRAMES_SCHEMA,
    "cameras": CAMERAS_SCHEMA,
    "ego_poses": EGO_POSES_SCHEMA,
    "boxes3d": BOXES3D_SCHEMA,
    "boxes2d": BOXES2D_SCHEMA,
    "qa": QA_SCHEMA,
}
WORLD_SCHEMA = pa.schema(
    [
        ("sample_id", pa.string()),
        ("scene_token", pa.string()),  # == scene_id
        ("frame_idx", pa.int32()),  # the frame the Gaussians come from
        ("split", pa.string()),
        ("conversations", pa.list_(_TURN)),  # the generation instruction, with the <gauss> placeholder
        ("views", pa.list_(pa.string())),
        ("gauss", pa.list_(pa.string())),  # paths relative to the dataset root
        ("image", pa.list_(pa.string())),  # the instruction's input images, relative to the dataset root
        ("ref_image", pa.string()),  # reference RGB image
        ("pseudo_rgb", pa.list_(pa.string())),  # T condition frames rendered from the Gaussians
        ("pseudo_depth", pa.list_(pa.string())),  # T .npz, PSEUDO_DEPTH_KEY
        ("gt_rgb", pa.list_(pa.string())),  # T ground-truth frames, or none
        ("gt_depth", pa.list_(pa.string())),  # T .npz, one of GT_DEPTH_KEYS, or none
        ("latent_pack", pa.string()),  # raw memmap, meta.json beside it
        ("latent_indices", pa.list_(pa.int32())),  # T rows of the pack, in frame order
        ("fps", pa.int32()),
        ("motion_bucket_id", pa.int32()),
        ("pseudo_source_name", pa.string()),
        ("pseudo_source_kind", pa.string()),
        ("provenance", pa.string()),  # JSON: where the record came from
    ]
)
CLIP_TEXT_SCHEMA = pa.schema(
    [
        ("sample_id", pa.string()),  # a qa.sample_id
        ("path", pa.string()),  # [N, D] .npy shard, relative to the dataset root
        ("row", pa.int32()),
    ]
)
OPTIONAL_TABLES: dict[str, pa.Schema] = {"world": WORLD_SCHEMA, "clip_text": CLIP_TEXT_SCHEMA}
RELEASE_DIR = "release"
LATENT_META = "meta.json"
LATENT_STREAMS = (["rgb", "depth"], ["rgb_latent", "depth_latent"])
PSEUDO_DEPTH_KEY = "depth_proj"
GT_DEPTH_KEYS = ("depth", "depth_gt", "depth_proj")


def image_relpath(scene_id: str, camera: str, frame_idx: int, weather: str = "clear") -> str:
    folder = "images" if weather == "clear" else f"images_{weather}"
    return f"scenes/{scene_id}/{folder}/{camera}/{frame_idx:05d}.png"


def depth_relpath(scene_id: str, camera: str, frame_idx: int) -> str:
    return f"scenes/{scene_id}/depth/{camera}/{frame_idx:05d}.png"


def lidar_relpath(scene_id: str, frame_idx: int) -> str:
    return f"scenes/{scene_id}/lidar/{frame_idx:05d}.arrow"


def gaussians_relpath(scene_id: str, frame_idx: int) -> str:
    return f"scenes/{scene_id}/gaussians/{frame_idx:05d}.arrow"


_FILE_KINDS = {"images": "images", "depth": "depth", "lidar": "lidar", "gaussians": "gaussians"}
"""Per-scene file folders (``scenes/<id>/<folder>/...``; ``images_<weather>`` counts as images) -> table name."""


def held_tables(root: Path, files: Iterable[str]) -> list[str]:
    """What a dataset holds, by name: every parquet table with a row, every kind of per-scene file (images, depth,
    lidar, gaussians) and ``routes`` (``routes.json``). Written to ``dataset.json`` as ``tables``: a run refuses,
    before launch, a stage that needs one it lacks (``gdwm.stage.stage(needs=...)``)."""
    held = {p.stem for p in root.glob("*.parquet") if pq.read_metadata(p).num_rows > 0}
    for rel in files:
        parts = rel.split("/")
        if len(parts) > 3 and parts[0] == "scenes":
            kind = _FILE_KINDS.get(parts[2].split("_")[0])
            if kind:
                held.add(kind)
    if (root / ROUTES_FILE).is_file():
        held.add("routes")
    return sorted(held)


def release_relpath(source_rel: str) -> str:
    """Where a file copied from the GaussianDWM release lives in the dataset (its source-relative POSIX path)."""
    return f"{RELEASE_DIR}/{source_rel}"


def read_latent_meta(pack: Path, where: str) -> tuple[np.dtype, tuple[int, ...]]:
    """(dtype, shape) of a latent pack from the ``meta.json`` beside it, checked against the pack's size.

    Errors name ``where`` and the ``meta.json`` field: dtype a float type, shape [N, 2, C, H, W], streams
    ``LATENT_STREAMS``, and the file exactly ``prod(shape) * itemsize`` bytes (a short pack would read past its end).
    """
    meta_path = pack.with_name(LATENT_META)
    if not pack.is_file():
        raise DataError(f"{where}: latent pack not found")
    if not meta_path.is_file():
        raise DataError(f"{where}: no {LATENT_META} beside the latent pack")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{where}: {LATENT_META} is not JSON ({e})") from e
    if not isinstance(meta, dict):
        raise DataError(f"{where}: {LATENT_META} is a {type(meta).__name__}, expected an object")
    if meta.get("streams") not in LATENT_STREAMS:
        raise DataError(f"{where}: {LATENT_META} streams is {meta.get('streams')!r}, expected one of {LATENT_STREAMS}")
    try:
        dtype = np.dtype(str(meta.get("dtype")))
    except TypeError as e:
        raise DataError(f"{where}: {LATENT_META} dtype {meta.get('dtype')!r} is not a numpy dtype") from e
    if dtype.kind != "f":
        raise DataError(f"{where}: {LATENT_META} dtype {meta.get('dtype')!r} is not a float type")
    shape = meta.get("shape")
    ok = isinstance(shape, list) and len(shape) == 5 and all(type(v) is int and v > 0 for v in shape)
    if not ok or shape[1] != 2:
        raise DataError(f"{where}: {LATENT_META} shape is {shape!r}, expected [N, 2, C, H, W]")
    need = int(np.prod(shape)) * dtype.itemsize
    size = pack.stat().st_size
    if size != need:
        raise DataError(f"{where}: latent pack is {size} bytes, {LATENT_META} shape {shape} of {dtype} needs {need}")
    return dtype, tuple(shape)


def numpy_load_error(e: Exception) -> str:
    """Why ``np.load(allow_pickle=False)`` failed, without numpy's advice to allow pickles (never, for a download)."""
    if isinstance(e, ValueError) and "pickle" in str(e):
        return "not an array file: it would need unpickling, which is never done"
    return f"{type(e).__name__}: {e}"


def read_depth_npz(path: Path, keys: Sequence[str], where: str) -> np.ndarray:
    """The [H, W] float32 depth of a ``.npz``: its first array named in ``keys``; no pickles are loaded."""
    try:
        npz = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise DataError(f"{where}: not a readable .npz ({numpy_load_error(e)})") from e
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise DataError(f"{where}: a single .npy array, expected an .npz archive")
    with npz:
        key = next((k for k in keys if k in npz.files), None)
        if key is None:
            want = " or ".join(f"'{k}'" for k in keys)
            raise DataError(f"{where}: no array {want} in the .npz (arrays: {sorted(npz.files)})")
        try:
            depth = npz[key]
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise DataError(f"{where}: array '{key}' is unreadable ({numpy_load_error(e)})") from e
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
        raise DataError(f"{where}: array '{key}' is {depth.dtype} {list(depth.shape)}, expected a numeric [H, W]")
    return depth.astype(np.float32)


# ----------------------------------------------------------------------------- arrays <-> arrow


def fsl_array(values: np.ndarray, width: int) -> pa.FixedSizeListArray:
    """An [N, width] float array as a fixed-size-list column (zero-copy where contiguous)."""
    flat = np.ascontiguousarray(values, dtype=np.float32).reshape(-1)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat, type=pa.float32()), width)


def fsl_to_numpy(column: pa.ChunkedArray | pa.Array, width: int) -> np.ndarray:
    """A fixed-size-list column as an [N, width] float32 array (zero-copy for one chunk)."""
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks() if column.num_chunks != 1 else column.chunk(0)
    values = column.flatten().to_numpy(zero_copy_only=False)
    return values.reshape(-1, width)


def check_gaussians(arrays: Mapping[str, np.ndarray], where: str) -> None:
    """Reject wrong-shaped or non-finite Gaussians, naming ``where`` (file/scene/frame) and the field."""
    required = {"xyz": 3, "scale": 3, "rotation": 4, "opacity": 1, "color": 3, "feature": None}
    if "feature" not in arrays:
        required.pop("feature")  # not distilled yet
    missing = [k for k in required if k not in arrays]
    if missing:
        raise DataError(f"{where}: Gaussians lack field(s) {missing}")
    n = arrays["xyz"].shape[0]
    for key, width in required.items():
        a = np.asarray(arrays[key])
        shape_ok = a.ndim >= 1 and a.shape[0] == n
        if width == 1:
            shape_ok = shape_ok and (a.ndim == 1 or (a.ndim == 2 and a.shape[1] == 1))
        elif width is not None:
            shape_ok = shape_ok and a.ndim == 2 and a.shape[1] == width
        else:
            shape_ok = shape_ok and a.ndim == 2
        if not shape_ok:
            want = f"[{n}, {width}]" if width not in (None, 1) else (f"[{n}]" if width == 1 else f"[{n}, D]")
            raise DataError(f"{where}: Gaussian field '{key}' has shape {list(a.shape)}, expected {want}")
        bad = ~np.isfinite(a)
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            raise DataError(
                f"{where}: Gaussian field '{key}' has NaN/Inf ({int(bad.sum())} values, first at row {row})"
            )
    if (arrays["scale"] <= 0).any():
        raise DataError(f"{where}: Gaussian field 'scale' has non-positive values")
    norms = np.linalg.norm(arrays["rotation"], axis=1)
    if (norms < 1e-8).any():
        raise DataError(f"{where}: Gaussian field 'rotation' has a zero quaternion (not normalisable)")
    op = np.asarray(arrays["opacity"]).reshape(-1)
    if ((op < 0) | (op > 1)).any():
        raise DataError(f"{where}: Gaussian field 'opacity' is outside [0, 1] (expected probabilities, not logits)")


def gaussians_table(arrays: Mapping[str, np.ndarray], where: str = "gaussians", frame: str = "ego") -> pa.Table:
    check_gaussians(arrays, where)
    rot = np.asarray(arrays["rotation"], dtype=np.float32)
    rot = rot / np.linalg.norm(rot, axis=1, keepdims=True)
    feat = np.asarray(arrays["feature"], dtype=np.float32) if "feature" in arrays else None
    if feat is not None and feat.shape[1] == 0:
        feat = None
    schema = gaussian_schema(0 if feat is None else feat.shape[1], frame)
    cols = [
        fsl_array(arrays["xyz"], 3),
        fsl_array(arrays["scale"], 3),
        fsl_array(rot, 4),
        pa.array(np.asarray(arrays["opacity"], dtype=np.float32).reshape(-1)),
        fsl_array(arrays["color"], 3),
    ]
    if feat is not None:
        cols.append(fsl_array(feat, feat.shape[1]))
    return pa.Table.from_arrays(cols, schema=schema)


def write_arrow(table: pa.Table, path: Path) -> None:
    """Uncompressed Arrow IPC file, so readers can memory-map it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with pa.OSFile(str(path), "wb") as sink, pa.ipc.new_file(sink, table.schema) as writer:
        writer.write_table(table)


def read_image_file(path: Path, where: str, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    """Decode a PNG/JPEG (BGR, or as stored with IMREAD_UNCHANGED); missing/truncated/undecodable -> DataError."""
    if not path.is_file():
        raise DataError(f"{where}: missing image {path}")
    data = path.read_bytes()
    # OpenCV decodes a truncated JPEG/PNG with only a warning (grey bottom rows); the end marker tells.
    tail = data.rstrip(b"\0")
    if data[:2] == b"\xff\xd8" and not tail.endswith(b"\xff\xd9"):
        raise DataError(f"{where}: image unreadable {path} (truncated JPEG)")
    if data[:8] == b"\x89PNG\r\n\x1a\n" and not tail.endswith(b"IEND\xaeB`\x82"):
        raise DataError(f"{where}: image unreadable {path} (truncated PNG)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None:
        raise DataError(f"{where}: image unreadable {path} (not a decodable image)")
    return img


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.round(d * DEPTH_SCALE), 0, 65535).astype(np.uint16)


def decode_depth(raw: np.ndarray) -> np.ndarray:
    return raw.astype(np.float32) / DEPTH_SCALE


# ----------------------------------------------------------------------------- fingerprint


def file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _files_under(root: Path) -> list[str]:
    """POSIX relpaths of every file under ``root`` but its dataset.json (symlinked folders are not followed)."""
    out: list[str] = []
    stack = [(root, "")]
    while stack:
        folder, prefix = stack.pop()
        with os.scandir(folder) as it:
            for e in it:
                rel = prefix + e.name
                if e.is_dir(follow_symlinks=False):
                    stack.append((Path(e.path), rel + "/"))
                elif e.is_file() and rel != "dataset.json":
                    out.append(rel)
    return out


def relpath_order(rel: str) -> list[str]:
    """Sort key of the fingerprint: path components, as ``pathlib`` orders paths ("a/b" before "a.c")."""
    return rel.split("/")


def fingerprint_of(hashes: Mapping[str, str]) -> str:
    """The dataset fingerprint from ``{relpath: sha256}``: sha256 over ``relpath \\0 sha256 \\n`` in relpath order."""
    h = hashlib.sha256()
    for rel in sorted(hashes, key=relpath_order):
        h.update(rel.encode())
        h.update(b"\0")
        h.update(hashes[rel].encode())
        h.update(b"\n")
    return h.hexdigest()


def tree_files(root: Path) -> dict[str, dict]:
    """``{relpath: {"sha256", "size", "mtime_ns"}}`` of every file under ``root`` but dataset.json, in relpath order."""
    files = {}
    for rel in sorted(_files_under(root), key=relpath_order):
        path = root / rel
        st = path.stat()
        files[rel] = {"sha256": file_sha256(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    return files


def fingerprint_tree(root: Path) -> tuple[str, int, int]:
    """(sha256 over sorted (relpath, sha256) of every file but dataset.json, file count, bytes)."""
    files = tree_files(root)
    fingerprint = fingerprint_of({rel: f["sha256"] for rel, f in files.items()})
    return fingerprint, len(files), sum(f["size"] for f in files.values())


def plain(value):
    """A JSON-able copy of a config value: mappings -> dict, sequences (but strings) -> list (OmegaConf too)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain(v) for v in value]
    return value


def content_params(cfg, cls: type, skip: Iterable[str] = ()) -> dict:
    """The ``params`` of a dataset: ``cfg``'s values of ``cls``'s dataclass fields, but those that do not change the
    content (the ``DatasetConfig`` base fields: name, root, builder, needs_source, summarizer) and ``skip``."""
    omit = {f.name for f in fields(DatasetConfig)} | set(skip)
    return {f.name: plain(getattr(cfg, f.name)) for f in fields(cls) if f.name not in omit}


# ----------------------------------------------------------------------------- writer


@dataclass
class _Rows:
    schema: pa.Schema
    rows: list
    table: pa.Table | None = None
    """A whole table given at once (``put_table``), written instead of ``rows``."""

    def written(self) -> pa.Table:
        return self.table if self.table is not None else pa.Table.from_pylist(self.rows, schema=self.schema)


class DatasetWriter:
    """Builds a dataset in a temp dir beside ``root`` and publishes it atomically.

    Use as a context manager; on an exception the temp dir is removed and an existing
    dataset at ``root`` is untouched. ``overwrite=False`` refuses to replace one; ``overwrite=True`` replaces only a
    dataset gdwm wrote (its ``dataset.json`` is the marker), never a user's folder; an empty folder is filled. The
    published folder gets the umask's mode (the temp dir's 0700 would shut out other users of a shared root).
    """

    def __init__(
        self, root: str | os.PathLike, name: str, source: str, overwrite: bool = False, params: Mapping | None = None
    ):
        self.root = Path(root).resolve()
        self.name = name
        self.source = source
        self.overwrite = overwrite
        self.params: dict = plain(params or {})
        """What the content was built from (``dataset.json`` ``params``): the builder's ``data.<key>`` values."""
        self.tmp: Path | None = None
        self._tables = {k: _Rows(s, []) for k, s in TABLES.items()}
        self.extra_meta: dict = {}

    @classmethod
    def files_into(cls, tmp: Path) -> DatasetWriter:
        """A writer whose ``write_*`` methods target an existing temp dir (worker processes); it never publishes."""
        w = cls(tmp, name="", source="")
        w.tmp = Path(tmp)
        return w

    # -- lifecycle
    def __enter__(self) -> DatasetWriter:
        if self.root.exists() and not (self.root.is_dir() and not any(self.root.iterdir())):  # an empty one is filled
            if not self.overwrite:
                raise DataError(f"{self.root}: a dataset already exists (pass overwrite to replace it)")
            _check_ours(self.root)
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.root.name}.tmp-", dir=self.root.parent))
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self._publish()
        finally:
            if self.tmp is not None and self.tmp.exists():
                shutil.rmtree(self.tmp, ignore_errors=True)

    def path(self, rel: str) -> Path:
        assert self.tmp is not None, "DatasetWriter used outside its context"
        p = self.tmp / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    # -- rows
    def add(self, table: str, **row) -> None:
        self._rows(table).rows.append(row)

    def extend(self, table: str, rows: Iterable[Mapping]) -> None:
        self._rows(table).rows.extend(rows)
        if self._rows(table).table is not None:
            raise DataError(f"{table}: rows added to a table given whole (put_table)")

    def put_table(self, name: str, table: pa.Table) -> None:
        """Write ``table`` (e.g. another dataset's, unchanged) as table ``name``, cast to its schema; rows added to
        ``name`` before or after are an error."""
        rows = self._rows(name)
        if rows.rows:
            raise DataError(f"{name}: rows were added before put_table")
        rows.table = table.select(rows.schema.names).cast(rows.schema)

    def _rows(self, table: str) -> _Rows:
        # An optional table is written once a builder adds to it (even nothing), so other datasets stay unchanged.
        if table not in self._tables and table in OPTIONAL_TABLES:
            self._tables[table] = _Rows(OPTIONAL_TABLES[table], [])
        return self._tables[table]

    # -- files
    def write_image(self, rel: str, rgb_HW3: np.ndarray) -> None:
        img = np.asarray(rgb_HW3)
        if img.dtype != np.uint8:
            img = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
        if not cv2.imwrite(str(self.path(rel)), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            raise DataError(f"{rel}: OpenCV could not write the image")

    def copy_file(self, rel: str, src: Path) -> None:
        shutil.copyfile(src, self.path(rel))

    def link_file(self, rel: str, src: Path) -> None:
        """``src`` at ``rel`` as a hard link (no bytes copied: a dataset built on another shares its images), or a
        copy where the filesystem cannot link (another device, no hard links)."""
        dst = self.path(rel)
        try:
            os.link(src, dst)
        except OSError:
            shutil.copyfile(src, dst)

    def write_depth(self, rel: str, depth_HW: np.ndarray) -> None:
        if not cv2.imwrite(str(self.path(rel)), encode_depth(depth_HW)):
            raise DataError(f"{rel}: OpenCV could not write the depth image")

    def write_lidar(self, rel: str, points_N4: np.ndarray) -> None:
        pts = np.asarray(points_N4, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 4:
            raise DataError(f"{rel}: LiDAR points have shape {list(pts.shape)}, expected [N, 4]")
        cols = [pa.array(pts[:, i]) for i in range(4)]
        write_arrow(pa.Table.from_arrays(cols, schema=LIDAR_SCHEMA), self.path(rel))

    def write_gaussians(self, rel: str, arrays: Mapping[str, np.ndarray], frame: str = "ego") -> None:
        write_arrow(gaussians_table(arrays, where=rel, frame=frame), self.path(rel))

    # -- publish
    def _publish(self) -> None:
        assert self.tmp is not None
        written = {name: t.written() for name, t in self._tables.items()}
        for name, table in written.items():
            pq.write_table(table, self.tmp / f"{name}.parquet")
        scenes = pq.read_table(self.tmp / "scenes.parquet").num_rows
        frames = pq.read_table(self.tmp / "frames.parquet").num_rows
        files = tree_files(self.tmp)
        fingerprint = fingerprint_of({rel: f["sha256"] for rel, f in files.items()})
        nfiles, nbytes = len(files), sum(f["size"] for f in files.values())
        meta = {
            "name": self.name,
            "layout_version": LAYOUT_VERSION,
            "source": self.source,
            "cameras": sorted(set(written["cameras"].column("camera").to_pylist()), key=_camera_order),
            "num_scenes": scenes,
            "scenes": written["scenes"].column("scene_id").to_pylist(),
            "num_frames": frames,
            "num_files": nfiles,
            "bytes": nbytes,
            "tables": held_tables(self.tmp, files),
            **self.extra_meta,
            "fingerprint": fingerprint,
            "params": self.params,
            "files": files,  # stat taken now: renaming the folder into place below keeps file mtimes
        }
        # dataset.json is written last: a reader trusts only a root that has it.
        (self.tmp / "dataset.json").write_text(json.dumps(meta, indent=2, sort_keys=True))
        self.tmp.chmod(0o777 & ~_umask())  # mkdtemp's 0700 would lock out other users of a shared data.root
        old = None
        if self.root.exists():
            old = self.root.with_name(f".{self.root.name}.old-{uuid.uuid4().hex[:8]}")
            os.rename(self.root, old)
        os.rename(self.tmp, self.root)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    """The process's umask (reading it means setting it: put straight back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _check_ours(root: Path) -> None:
    """A ``DataError`` unless ``root`` holds a dataset gdwm wrote (its ``dataset.json``, with the layout version and
    fingerprint gdwm records, is the marker): ``overwrite`` must never replace a user's own folder."""
    try:
        meta = json.loads((root / "dataset.json").read_text())
        ours = isinstance(meta, dict) and {"layout_version", "fingerprint", "scenes"} <= set(meta)
    except (OSError, ValueError):
        ours = False
    if not ours:
        first = sorted(p.name for p in root.iterdir())[0] if root.is_dir() else root.name
        raise DataError(
            f"{root}: not a gdwm dataset (no dataset.json of gdwm's; {first} is not gdwm's): overwrite=true replaces "
            "only a dataset gdwm built; choose another data.root"
        )


def _camera_order(cam: str) -> tuple[int, str]:
    return (CAMERAS.index(cam) if cam in CAMERAS else len(CAMERAS), cam)


def pose_matrix(rotation_wxyz: Iterable[float], translation: Iterable[float]) -> np.ndarray:
    """4x4 from a (w, x, y, z) quaternion and a translation."""
    w, x, y, z = np.asarray(list(rotation_wxyz), dtype=np.float64) / np.linalg.norm(list(rotation_wxyz))
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = list(translation)
    return m


def matrix_to_quat_wxyz(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 from a 3x3 rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)[:3, :3]
    tr = np.trace(r)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def flat_pose(m: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(m, dtype=np.float64).reshape(16)]


def transform_gaussians(arrays: dict[str, np.ndarray], a_to_b_44: np.ndarray) -> dict[str, np.ndarray]:
    """Gaussians moved by a rigid transform: centres mapped, orientations pre-multiplied, the rest unchanged."""
    m = np.asarray(a_to_b_44, dtype=np.float64)
    xyz = arrays["xyz"].astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    q = _quat_mul(matrix_to_quat_wxyz(m[:3, :3]), arrays["rotation"].astype(np.float64))
    return {**arrays, "xyz": xyz.astype(np.float32), "rotation": q.astype(np.float32)}


def _quat_mul(a_4: np.ndarray, b_N4: np.ndarray) -> np.ndarray:
    """Hamilton product a * b for (w, x, y, z) quaternions (a broadcast over the rows of b)."""
    aw, ax, ay, az = a_4
    bw, bx, by, bz = b_N4.T
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=1,
    )
