"""World (generation) records of the GaussianDWM release: their fields, and the checks of the files they name.

A world record (``major_task: world``) has the common fields of a record (``gaussiandwm_qa``) and::

    "ref_image_path": "images/world_ref.png",
    "pseudo_video_paths": ["images/world_pseudo_000.png", ...],     T condition frames rendered from the Gaussians
    "pseudo_depth_paths": ["depth/world_pseudo_000.npz", ...],      T .npz with 'depth_proj' [H, W], metres
    "target_latent_pack_path": "latents/world_pack.dat",            raw memmap [N, 2, C, H, W], meta.json beside it
    "target_latent_indices": [0, 1, 2, 3, 4, 5],                    T rows of the pack
    "gt_rgb_frame_paths": [...], "gt_depth_npz_paths": [...],       optional: T ground-truth frames and depths
    "fps": 5, "motion_bucket_id": 127, "pseudo_source_name": "dummy", "pseudo_source_kind": "contract"

As the release's ``data/records.py`` resolves them: image and depth paths against its image root (``image_root``),
the pack against its annotation root (``latent_root``). Its ``data/dataset.py`` reads the pseudo depth's
``depth_proj`` and needs as many pseudo RGB and depth frames as latent indices; its ``eval/world_metrics.py`` reads a
ground-truth depth's ``depth``, ``depth_gt`` or ``depth_proj``. Per-frame ``.pt`` latents (``target_latent_paths``)
are not imported. Errors name ``file:line``, the sample, the field and the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2

from pipelines.data.layout import (
    GT_DEPTH_KEYS,
    LATENT_META,
    PSEUDO_DEPTH_KEY,
    DataError,
    contained,
    read_depth_npz,
    read_image_file,
    read_latent_meta,
)


@dataclass(frozen=True)
class WorldFields:
    """A world record's generation fields, paths as the release writes them."""

    ref_image: str
    pseudo_rgb: list[str]
    pseudo_depth: list[str]
    gt_rgb: list[str]
    gt_depth: list[str]
    latent_pack: str
    latent_indices: list[int]
    fps: int
    motion_bucket_id: int
    pseudo_source_name: str | None
    pseudo_source_kind: str | None


@dataclass(frozen=True)
class WorldFiles:
    """The files of one world record, resolved inside the source and checked."""

    ref_image: Path
    images: list[Path]  # the instruction's input images (image_paths)
    pseudo_rgb: list[Path]
    pseudo_depth: list[Path]
    gt_rgb: list[Path]
    gt_depth: list[Path]
    latent_pack: Path
    latent_meta: Path  # resolved; its copy goes beside the pack's

    def copies(self, src: Path) -> dict[str, Path]:
        """Source-relative destination -> file to copy; the pack's meta.json lands beside the pack."""
        files = [self.ref_image, *self.images, *self.pseudo_rgb, *self.pseudo_depth, *self.gt_rgb, *self.gt_depth]
        out = {source_rel(p, src): p for p in [*files, self.latent_pack]}
        out[(Path(source_rel(self.latent_pack, src)).parent / LATENT_META).as_posix()] = self.latent_meta
        return out


def source_rel(path: Path, src: Path) -> str:
    """POSIX path of a resolved file inside the source, relative to it."""
    return path.relative_to(src).as_posix()


def parse_world(raw: dict, at: str) -> WorldFields:
    """The generation fields of a world record; ``at`` is ``file:line sample 'uid'``."""
    if raw.get("target_latent_pack_path") is None:
        extra = " (per-frame target_latent_paths are not imported)" if raw.get("target_latent_paths") else ""
        raise DataError(f"{at}: world record lacks 'target_latent_pack_path'{extra}")
    indices = raw.get("target_latent_indices")
    if not isinstance(indices, list) or not indices or not all(_count(i) for i in indices):
        raise DataError(f"{at}: 'target_latent_indices' must be a non-empty list of non-negative ints")
    fields = WorldFields(
        ref_image=_path(raw, "ref_image_path", at),
        pseudo_rgb=_paths(raw, "pseudo_video_paths", at, required=True),
        pseudo_depth=_paths(raw, "pseudo_depth_paths", at, required=True),
        gt_rgb=_paths(raw, "gt_rgb_frame_paths", at, required=False),
        gt_depth=_paths(raw, "gt_depth_npz_paths", at, required=False),
        latent_pack=_path(raw, "target_latent_pack_path", at),
        latent_indices=list(indices),
        fps=_int(raw, "fps", at),
        motion_bucket_id=_int(raw, "motion_bucket_id", at),
        pseudo_source_name=_opt_str(raw, "pseudo_source_name", at),
        pseudo_source_kind=_opt_str(raw, "pseudo_source_kind", at),
    )
    frames = len(fields.pseudo_rgb)
    lengths = {
        "pseudo_depth_paths": len(fields.pseudo_depth),
        "target_latent_indices": len(fields.latent_indices),
        "gt_rgb_frame_paths": len(fields.gt_rgb) or frames,
        "gt_depth_npz_paths": len(fields.gt_depth) or frames,
    }
    for key, n in lengths.items():
        if n != frames:
            raise DataError(f"{at}: '{key}' has {n} entries but 'pseudo_video_paths' has {frames}")
    return fields


class WorldChecker:
    """Resolves and checks the files of world records; files shared by records are read once."""

    def __init__(self, src: Path, image_root: str, latent_root: str, latent_chw: tuple[int, int, int]):
        self.src = src
        self.image_root = image_root
        self.latent_root = latent_root
        self.latent_chw = tuple(latent_chw)
        self._sizes: dict[tuple[Path, str], tuple[int, int]] = {}  # (file, depth key or "") -> (H, W)
        self._packs: dict[Path, tuple[int, ...]] = {}

    def check(self, at: str, world: WorldFields, image_paths: list[str]) -> WorldFiles:
        """Every file of one record: inside the source, readable, frames of one size, indices inside the pack."""
        ref = self._file(at, "ref_image_path", world.ref_image, self.image_root)
        self._image_hw(at, "ref_image_path", ref, world.ref_image)
        images = [self._file(at, f"image_paths[{i}]", p, self.image_root) for i, p in enumerate(image_paths)]
        pseudo_rgb = self._frames(at, "pseudo_video_paths", world.pseudo_rgb, None)
        pseudo_depth = self._frames(at, "pseudo_depth_paths", world.pseudo_depth, (PSEUDO_DEPTH_KEY,))
        gt_rgb = self._frames(at, "gt_rgb_frame_paths", world.gt_rgb, None)
        gt_depth = self._frames(at, "gt_depth_npz_paths", world.gt_depth, GT_DEPTH_KEYS)
        pack = self._file(at, "target_latent_pack_path", world.latent_pack, self.latent_root)
        # meta.json is read beside the resolved pack; it too must stay inside the source.
        meta = contained(self.src, pack.with_name(LATENT_META).relative_to(self.src), f"{at}: {LATENT_META}")
        shape = self._pack_shape(at, world.latent_pack, pack)
        top = max(world.latent_indices)
        if top >= shape[0]:
            raise DataError(
                f"{at}: 'target_latent_indices' reach {top} but target_latent_pack_path {world.latent_pack} "
                f"holds {shape[0]} latents (meta.json shape {list(shape)})"
            )
        return WorldFiles(ref, images, pseudo_rgb, pseudo_depth, gt_rgb, gt_depth, pack, meta)

    def _frames(self, at: str, key: str, rels: list[str], depth_keys: tuple[str, ...] | None) -> list[Path]:
        """Files of one stream, all of one size (H, W)."""
        out, first = [], None
        for i, rel in enumerate(rels):
            field = f"{key}[{i}]"
            path = self._file(at, field, rel, self.image_root)
            if depth_keys is None:
                hw = self._image_hw(at, field, path, rel)
            else:
                hw = self._depth_hw(at, field, path, rel, depth_keys)
            if first is None:
                first = (hw, f"{key}[0] {rel}")
            elif hw != first[0]:
                raise DataError(
                    f"{at}: {field} {rel} is {_wxh(hw)} but {first[1]} is {_wxh(first[0])} "
                    "(the frames of one stream must share one size)"
                )
            out.append(path)
        return out

    def _file(self, at: str, field: str, rel: str, root: str) -> Path:
        path = contained(self.src, Path(root, rel), f"{at}: {field}")
        if not path.is_file():
            raise DataError(f"{at}: {field} {rel} not found under {self.src / root}")
        return path

    def _image_hw(self, at: str, field: str, path: Path, rel: str) -> tuple[int, int]:
        if (path, "") not in self._sizes:
            img = read_image_file(path, f"{at}: {field} {rel}", cv2.IMREAD_UNCHANGED)
            self._sizes[path, ""] = (int(img.shape[0]), int(img.shape[1]))
        return self._sizes[path, ""]

    def _depth_hw(self, at: str, field: str, path: Path, rel: str, keys: tuple[str, ...]) -> tuple[int, int]:
        if (path, keys[0]) not in self._sizes:
            depth = read_depth_npz(path, keys, f"{at}: {field} {rel}")
            self._sizes[path, keys[0]] = (int(depth.shape[0]), int(depth.shape[1]))
        return self._sizes[path, keys[0]]

    def _pack_shape(self, at: str, rel: str, pack: Path) -> tuple[int, ...]:
        if pack not in self._packs:
            where = f"{at}: target_latent_pack_path {rel}"
            _, shape = read_latent_meta(pack, where)
            if tuple(shape[2:]) != self.latent_chw:
                raise DataError(
                    f"{where}: meta.json shape {list(shape)} has latents {list(shape[2:])}, "
                    f"expected [C, H, W] = {list(self.latent_chw)} (data.latent_chw)"
                )
            self._packs[pack] = shape
        return self._packs[pack]


def _wxh(hw: tuple[int, int]) -> str:
    return f"{hw[1]}x{hw[0]}"


def _count(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _path(raw: dict, key: str, at: str) -> str:
    value = raw.get(key)
    if not isinstance(value, str) or not value:
        raise DataError(f"{at}: world record lacks '{key}' (a non-empty path)")
    return value


def _paths(raw: dict, key: str, at: str, required: bool) -> list[str]:
    value = raw.get(key)
    if value is None and not required:
        return []
    if not isinstance(value, list) or (required and not value) or not all(isinstance(v, str) and v for v in value):
        need = "a non-empty list" if required else "a list"
        raise DataError(f"{at}: '{key}' must be {need} of non-empty paths")
    return list(value)


def _int(raw: dict, key: str, at: str) -> int:
    value = raw.get(key)
    if not _count(value):
        raise DataError(f"{at}: '{key}' must be a non-negative int, got {value!r}")
    return value


def _opt_str(raw: dict, key: str, at: str) -> str | None:
    value = raw.get(key)
    if value is not None and (not isinstance(value, str) or not value):
        raise DataError(f"{at}: '{key}' must be a non-empty string when given")
    return value
