"""Importer of the public GaussianDWM release into the NuScenes-GSQA layout (``gdwm data import-gaussiandwm``).

Expected release folder (``source=``), as in the release's ``examples/dummy_data``::

    <source>/
      qa_train.jsonl, qa_val.jsonl            QA records (``major_task: qa``, see gaussiandwm_qa)
      world_train.jsonl, world_val.jsonl      world records (``major_task: world``, see gaussiandwm_world)
      gauss/**/<frame>.pth                    per-frame Gaussian state dicts (see gaussiandwm_pth), e.g.
                                              gauss/output-full-6v/0_CAM_FRONT/langsplat_3/per_frame/00000.pth
      images/*.png, depth/*.npz               world reference, pseudo and ground-truth frames and depths
      latents/<pack>.dat + latents/meta.json  world target latents, a raw memmap [N, 2, C, H, W]
      clip_text/features_<k>.npy              CLIP text features [N, 512] of the QA records (see gaussiandwm_clip)
      poses/<scene_idx>.txt                   optional world->ego rows, one per frame (``pose_dir``)

Every ``records_glob`` match is read; each record's ``major_task`` says whether it is QA (-> ``qa``, and
``clip_text`` where it names a feature) or a generation sample (-> ``world``). A record's split comes from the record,
else its file name (``*_train``/``*_val``), else its scene. The release's own examples repeat one record in
``qa_train.jsonl`` and ``qa_val.jsonl``: an unchanged record in both splits is handled by ``split_overlap``; any other
repeated ``sample_uid`` is an error.

Scene and frame of a ``.pth``: from the records that list it in ``gauss_paths`` (their
``scene_idx``/``frame_idx``); a file no record lists takes them from its path: the deepest folder
named ``scene_<n>``/``scene-<n>`` or ``<n>_<anything>`` is the scene, the trailing number of the file
name the frame. Several files of one frame (e.g. one per view) are merged into its Gaussians.
Scene ids are ``scene_<idx:04d>`` (the release's numbering, not nuScenes scene names); frames are
renumbered 0..F-1 per scene in original order, the original index kept in ``frames.token``.

Every path the release or the options name (``gauss_paths``, world files, CLIP shards, the roots, glob matches, pose
files) must resolve, symlinks followed, inside ``source=``; one that leads out (``..``, absolute, a symlink) is
refused, naming it. World files and CLIP shards are checked before anything is written and copied verbatim under
``release/`` at their source-relative paths (``layout.release_relpath``).

The release has no camera rigs, LiDAR, boxes or timestamps: those tables stay empty (or null),
``dataset.json`` says so, and ``qa.image`` keeps the release's own image paths (QA images are not imported).
"""

from __future__ import annotations

import json
import logging
import re
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Annotated

import numpy as np
from annotated_types import Ge, Interval

from pipelines.data.config import DatasetConfig
from pipelines.data.gaussiandwm_clip import ClipChecker
from pipelines.data.gaussiandwm_poses import read_pose_file
from pipelines.data.gaussiandwm_qa import DEFAULT_TASK_MAP, ReleaseRecord, map_task, read_records_file
from pipelines.data.gaussiandwm_world import WorldChecker, source_rel
from pipelines.data.layout import (
    DataError,
    DatasetWriter,
    contained,
    content_params,
    flat_pose,
    gaussians_relpath,
    release_relpath,
    transform_gaussians,
)
from pipelines.data.scene_splits import split_scenes

log = logging.getLogger(__name__)

FORMAT = "gaussiandwm_release"
_SCENE_DIR = re.compile(r"scene[_-]?(\d+)|(\d+)_.+", re.IGNORECASE)
_FRAME_STEM = re.compile(r"(\d+)$")
SPLIT_OVERLAP = ("warn", "drop_from_train", "error")


@dataclass
class ReleaseConfig(DatasetConfig):
    """Import of the public GaussianDWM release: Gaussians, QA, world (generation) samples, CLIP text features."""

    name: str = "gaussiandwm_release"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    builder: str = "pipelines.data.gaussiandwm.build"
    """Dotted path of the importer."""
    build_command: str | None = "gdwm data import-gaussiandwm"
    """Imports it from ``source=DIR``."""
    gauss_glob: str = "gauss/**/*.pth"
    """Glob (relative to the source) of the per-frame Gaussian ``.pth`` files to import."""
    records_glob: str = "**/*.jsonl"
    """Glob (relative to the source) of the record JSONL files, QA and world alike (``major_task`` tells them apart)."""
    gauss_root: str = ""
    """Folder (relative to the source) that the records' ``gauss_paths`` are relative to."""
    image_root: str = ""
    """Folder (relative to the source) that world records' image and depth paths are relative to."""
    latent_root: str = ""
    """Folder (relative to the source) that world records' ``target_latent_pack_path`` is relative to."""
    clip_text_root: str = ""
    """Folder (relative to the source) that QA records' ``clip_text_embed_path`` is relative to."""
    feature_dim: Annotated[int, Ge(1)] = 3
    """Width of ``_language_feature`` (the compact feature code); other widths are an error."""
    pose_dir: str = ""
    """Optional folder (relative to the source) of world->ego pose files; empty keeps the release's frame."""
    pose_template: str = "{scene_idx}.txt"
    """File name of a scene's pose file inside ``pose_dir``."""
    clip_dim: Annotated[int, Ge(1)] = 512
    """Width of a CLIP text feature (the release's shards are [N, 512]); other widths are an error."""
    latent_chw: Annotated[list[int], Ge(1)] = field(default_factory=lambda: [4, 56, 96])
    """[C, H, W] of a target latent in the packs (the release's: SVD latents of 768x448 frames)."""
    insert_gauss_token: bool = True
    """Insert ``<gauss>`` at the head of the first user turn, as the release's loader inserts its Gaussian item
    (the release keeps none in its text); false: a record with ``gauss_paths`` whose text lacks it is an error."""
    split_overlap: str = "warn"
    """An unchanged record in both train and val (the release's examples do this): ``warn`` keeps both copies,
    ``drop_from_train`` keeps the val copy only, ``error`` refuses the import. Every policy names the records."""
    val_fraction: Annotated[float, Interval(ge=0, le=1)] = 0.1
    """Share of scenes (the last, by id) whose records go to ``val`` when neither record nor file name says."""
    task_map: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_TASK_MAP))
    """``qa_group`` or ``"<qa_group>/<qa_subtask>"`` -> task family (rdp, vg2d, vg3d, plan, traj)."""


@dataclass
class _Frame:
    orig: int  # the release's frame_idx
    files: set[Path] = field(default_factory=set)


def build(cfg: ReleaseConfig, root: Path, source: str | None, overwrite: bool = False) -> Path:
    """Import the release at ``source`` into a dataset at ``root``; returns the published root."""
    src = _require_source(source)
    if cfg.split_overlap not in SPLIT_OVERLAP:
        raise DataError(f"data.split_overlap is {cfg.split_overlap!r}, expected one of {list(SPLIT_OVERLAP)}")
    records, overlap = _read_records(src, cfg)
    records = _apply_split_overlap(records, overlap, cfg.split_overlap)
    frames = _collect_frames(src, cfg, records)
    scene_keys = sorted(frames, key=_scene_sort_key)
    clash = [k for k, n in Counter(map(scene_id, scene_keys)).items() if n > 1]
    if clash:
        raise DataError(f"source={src}: scene_idx values map to the same scene id {clash} (an int and a name)")
    dense = {s: {f: i for i, f in enumerate(sorted(frames[s]))} for s in scene_keys}
    splits = split_scenes(scene_keys, cfg.val_fraction)
    qa = [r for r in records if r.kind == "qa"]
    world = [r for r in records if r.kind == "world"]
    # Rows and file checks first: a bad record fails before any Gaussian is read.
    qa_rows = _qa_rows(qa, frames, dense, splits, cfg.task_map)
    copies: dict[str, Path] = {}
    clip_rows = _clip_rows(src, cfg, qa, copies)
    world_rows = _world_rows(src, cfg, world, frames, dense, splits, copies)
    colors: Counter = Counter()
    params = content_params(cfg, ReleaseConfig)  # the import options; the release itself is source=
    with DatasetWriter(root, cfg.name, source=str(src), overwrite=overwrite, params=params) as w:
        for key in scene_keys:
            _write_scene(w, src, cfg, key, {dense[key][f]: frames[key][f] for f in dense[key]}, colors)
        w.extend("qa", qa_rows)
        w.extend("world", world_rows)
        w.extend("clip_text", clip_rows)
        for rel, path in sorted(copies.items()):
            w.copy_file(release_relpath(rel), path)
        w.extra_meta = _meta(cfg, colors, records, qa_rows, world_rows, clip_rows, overlap)
    return w.root


def _write_scene(
    w: DatasetWriter, src: Path, cfg: ReleaseConfig, key: int | str, frames: dict[int, _Frame], colors: Counter
) -> None:
    """One scene's rows and Gaussian files; ``frames`` maps our frame index to the release frame."""
    from pipelines.data.gaussiandwm_pth import concat, read_release_gaussians  # torch: not at config composition

    sid = scene_id(key)
    poses = _scene_poses(src, cfg, key) if cfg.pose_dir else None
    # The release has no timestamps: frame rate and timestamps are null rather than invented.
    w.add(
        "scenes",
        scene_id=sid,
        name=str(key),
        num_frames=len(frames),
        frame_rate_hz=None,
        description="",
        weathers=[],
        source=FORMAT,
    )
    for idx, frame in frames.items():
        w.add("frames", scene_id=sid, frame_idx=idx, timestamp_us=None, token=str(frame.orig))
        world2ego = _frame_pose(poses, frame.orig, key) if poses is not None else None
        if world2ego is not None:
            w.add("ego_poses", scene_id=sid, frame_idx=idx, ego2world=flat_pose(np.linalg.inv(world2ego)))
        if not frame.files:
            continue
        parts = [read_release_gaussians(p, _rel(p, src), cfg.feature_dim) for p in sorted(frame.files)]
        colors.update("sh_dc" if p.has_color else "grey" for p in parts)
        arrays = concat(parts)
        if world2ego is not None:
            arrays = transform_gaussians(arrays, world2ego)
        w.write_gaussians(gaussians_relpath(sid, idx), arrays, frame="ego" if cfg.pose_dir else "release")
    log.info("%s: %d frames", sid, len(frames))


def _qa_rows(records: list[ReleaseRecord], frames: dict, dense: dict, splits: dict, task_map: dict) -> list[dict]:
    rows = []
    for r in records:
        sid, idx = scene_id(r.scene_idx), dense[r.scene_idx][r.frame_idx]
        has_gauss = bool(r.gauss_paths) and bool(frames[r.scene_idx][r.frame_idx].files)
        provenance = {
            "source": FORMAT,
            "scene_idx": r.scene_idx,
            "frame_idx": r.frame_idx,
            "qa_group": r.qa_group,
            "qa_subtask": r.qa_subtask,
            "gauss_paths": r.gauss_paths,
        }
        if r.clip is not None:
            provenance |= {"clip_text_embed_path": r.clip.path, "clip_text_embed_row": r.clip.row}
        rows.append(
            {
                "sample_id": r.sample_uid,
                "scene_token": sid,
                "frame_idx": idx,
                "task": map_task(r, dict(task_map)),
                "category": f"{r.qa_group}/{r.qa_subtask}" if r.qa_subtask else r.qa_group,
                "conversations": r.conversations,
                "image": r.image_paths,
                "views": r.views,
                "gauss": [gaussians_relpath(sid, idx)] if has_gauss else [],
                "split": r.split or splits[r.scene_idx],
                "gt": json.dumps(provenance),  # no answer-side ground truth in the release: where the record came from
            }
        )
    return rows


def _clip_rows(src: Path, cfg: ReleaseConfig, records: list[ReleaseRecord], copies: dict[str, Path]) -> list[dict]:
    """One row per QA sample that names a CLIP feature; its shard is checked and added to ``copies``."""
    checker = ClipChecker(src, cfg.clip_text_root, cfg.clip_dim)
    rows: dict[str, dict] = {}  # a record kept in both splits is one sample: one feature
    for r in records:
        if r.clip is None:
            continue
        shard = checker.check(f"{r.where} sample '{r.sample_uid}'", r.clip.path, r.clip.row)
        rel = _add_copy(copies, source_rel(shard, src), shard)
        rows.setdefault(r.sample_uid, {"sample_id": r.sample_uid, "path": release_relpath(rel), "row": r.clip.row})
    return list(rows.values())


def _world_rows(
    src: Path,
    cfg: ReleaseConfig,
    records: list[ReleaseRecord],
    frames: dict,
    dense: dict,
    splits: dict,
    copies: dict[str, Path],
) -> list[dict]:
    """One row per world record; every file it names is checked and added to ``copies``."""
    checker = WorldChecker(src, cfg.image_root, cfg.latent_root, tuple(cfg.latent_chw))
    rows = []
    for r in records:
        assert r.world is not None
        wf = r.world
        files = checker.check(f"{r.where} sample '{r.sample_uid}'", wf, r.image_paths)
        for rel, path in files.copies(src).items():
            _add_copy(copies, rel, path)
        ours = partial(_copied, src=src)
        sid, idx = scene_id(r.scene_idx), dense[r.scene_idx][r.frame_idx]
        has_gauss = bool(r.gauss_paths) and bool(frames[r.scene_idx][r.frame_idx].files)
        provenance = {
            "source": FORMAT,
            "scene_idx": r.scene_idx,
            "frame_idx": r.frame_idx,
            "gauss_paths": r.gauss_paths,
            "image_paths": r.image_paths,
            "target_latent_pack_path": wf.latent_pack,
        }
        rows.append(
            {
                "sample_id": r.sample_uid,
                "scene_token": sid,
                "frame_idx": idx,
                "split": r.split or splits[r.scene_idx],
                "conversations": r.conversations,
                "views": r.views,
                "gauss": [gaussians_relpath(sid, idx)] if has_gauss else [],
                "image": ours(files.images),
                "ref_image": ours([files.ref_image])[0],
                "pseudo_rgb": ours(files.pseudo_rgb),
                "pseudo_depth": ours(files.pseudo_depth),
                "gt_rgb": ours(files.gt_rgb),
                "gt_depth": ours(files.gt_depth),
                "latent_pack": ours([files.latent_pack])[0],
                "latent_indices": wf.latent_indices,
                "fps": wf.fps,
                "motion_bucket_id": wf.motion_bucket_id,
                "pseudo_source_name": wf.pseudo_source_name,
                "pseudo_source_kind": wf.pseudo_source_kind,
                "provenance": json.dumps(provenance),
            }
        )
    return rows


def _copied(paths: list[Path], src: Path) -> list[str]:
    """Dataset paths of source files copied by ``_add_copy``."""
    return [release_relpath(source_rel(p, src)) for p in paths]


def _add_copy(copies: dict[str, Path], rel: str, path: Path) -> str:
    prev = copies.setdefault(rel, path)
    if prev != path:
        raise DataError(f"release/{rel}: would hold both {prev} and {path} (a meta.json beside its pack is a link?)")
    return rel


def _meta(
    cfg: ReleaseConfig,
    colors: Counter,
    records: list[ReleaseRecord],
    qa_rows: list[dict],
    world_rows: list[dict],
    clip_rows: list[dict],
    overlap: list[tuple[ReleaseRecord, ReleaseRecord]],
) -> dict:
    modalities = {
        "gaussians": True,
        "qa": True,
        "ego_poses": bool(cfg.pose_dir),
        "world": bool(world_rows),
        "clip_text": bool(clip_rows),
    }
    modalities |= dict.fromkeys(("images", "cameras", "lidar", "boxes", "timestamps"), False)
    return {
        "format": FORMAT,
        "modalities": modalities,
        "gaussians": {
            "frame": "ego (world->ego from pose_dir)" if cfg.pose_dir else "as released (no pose_dir given)",
            "feature_dim": cfg.feature_dim,
            "files_by_color_source": dict(colors),  # sh_dc: 0.5 + C0 * _features_dc; grey: no colour in the file
            "activation": "scale=exp(_scaling), opacity=sigmoid(_opacity), rotation=_rotation/|_rotation|",
        },
        "qa": {
            "records": len(qa_rows),
            "by_task": dict(Counter(r["task"] for r in qa_rows)),
            "task_map": dict(cfg.task_map),
            "gauss_token_inserted": sum(r.gauss_token_inserted for r in records if r.kind == "qa"),
            "image_paths": "relative to the release source; images are not imported",
            "clip_text_features": len(clip_rows),
        },
        "world": {
            "samples": len(world_rows),
            "by_split": dict(Counter(r["split"] for r in world_rows)),
            "latent_chw": list(cfg.latent_chw),
            "files": "copied verbatim under release/ at their source-relative paths",
        },
        "split_overlap": {
            "policy": cfg.split_overlap,
            "sample_ids": sorted({train.sample_uid for train, _ in overlap}),
        },
        "frame_index": "frames are renumbered 0..F-1 per scene; frames.token holds the release's frame_idx",
    }


def scene_id(scene_key: int | str) -> str:
    """Our scene id of a release scene index (``scene_0002``) or name (kept)."""
    return f"scene_{scene_key:04d}" if isinstance(scene_key, int) else scene_key


def ids_from_path(rel: Path) -> tuple[int, int] | None:
    """(scene, frame) from a release path, or None when the path does not say."""
    frame = _FRAME_STEM.search(rel.name.split(".")[0])
    for part in reversed(rel.parts[:-1]):
        m = _SCENE_DIR.fullmatch(part)
        if m and frame:
            return int(m.group(1) or m.group(2)), int(frame.group(1))
    return None


def _require_source(source: str | None) -> Path:
    if source is None:
        raise DataError("source= is required: the folder of the GaussianDWM release (QA .jsonl + gauss/*.pth)")
    src = Path(source).expanduser().resolve()
    if not src.is_dir():
        raise DataError(f"source={source}: no such directory")
    return src


def _read_records(
    src: Path, cfg: ReleaseConfig
) -> tuple[list[ReleaseRecord], list[tuple[ReleaseRecord, ReleaseRecord]]]:
    """Every record, and the (train, val) pairs of an unchanged record found in both splits."""
    files = sorted(src.glob(cfg.records_glob))
    if not files:
        raise DataError(f"source={src}: no record files match records_glob={cfg.records_glob!r}")
    records: list[ReleaseRecord] = []
    first: dict[str, ReleaseRecord] = {}
    in_split: dict[tuple[str, str | None], ReleaseRecord] = {}
    overlap = []
    for found in files:
        rel = found.relative_to(src).as_posix()
        path = contained(src, rel, "record file")
        for r in read_records_file(path, rel, cfg.insert_gauss_token):
            prev = first.setdefault(r.sample_uid, r)
            if prev is not r:
                # Only an explicit other split makes a repeat an overlap; an unknown one may well be the same.
                same = in_split.get((r.sample_uid, r.split)) or (None if r.split and prev.split else prev)
                if same is not None:
                    raise DataError(f"{r.where}: sample_uid '{r.sample_uid}' already used at {same.where}")
                if r.content != prev.content:
                    raise DataError(
                        f"{r.where}: sample_uid '{r.sample_uid}' already used at {prev.where} for a different record "
                        "(only an unchanged record may repeat, in the other split)"
                    )
                overlap.append((prev, r) if prev.split == "train" else (r, prev))
            in_split[r.sample_uid, r.split] = r
            records.append(r)
    return records, overlap


def _apply_split_overlap(
    records: list[ReleaseRecord], overlap: list[tuple[ReleaseRecord, ReleaseRecord]], policy: str
) -> list[ReleaseRecord]:
    """``data.split_overlap`` on the records found in both splits: one warning (or error) names them all."""
    if not overlap:
        return records
    shown = ", ".join(f"'{t.sample_uid}' ({t.where}, {v.where})" for t, v in overlap[:5])
    more = f" and {len(overlap) - 5} more" if len(overlap) > 5 else ""
    what = f"{len(overlap)} record(s) in both train and val: {shown}{more}"
    if policy == "error":
        raise DataError(f"{what} (data.split_overlap=error; warn keeps both copies, drop_from_train keeps val only)")
    if policy == "drop_from_train":
        log.warning("%s: %s; dropped from train, kept in val (data.split_overlap=drop_from_train)", FORMAT, what)
        dropped = {id(t) for t, _ in overlap}
        return [r for r in records if id(r) not in dropped]
    log.warning(
        "%s: %s; kept in both splits (data.split_overlap=warn; drop_from_train keeps them in val only, error refuses "
        "the import)",
        FORMAT,
        what,
    )
    return records


def _collect_frames(src: Path, cfg: ReleaseConfig, records: list[ReleaseRecord]) -> dict:
    """scene key -> original frame index -> files, from records first, then unreferenced files' paths."""
    frames: dict[int | str, dict[int, _Frame]] = defaultdict(dict)
    owner: dict[Path, tuple[int | str, int, str]] = {}
    for r in records:
        key = r.scene_idx
        # A record's frame exists even when it has no Gaussians.
        frame = frames[key].setdefault(r.frame_idx, _Frame(r.frame_idx))
        for p in r.gauss_paths:
            where = f"{r.where} sample '{r.sample_uid}'"
            path = contained(src, Path(cfg.gauss_root, p), f"{where}: gauss path")
            if not path.is_file():
                raise DataError(f"{where}: gauss path {p} not found under {src / cfg.gauss_root}")
            prev = owner.setdefault(path, (key, r.frame_idx, r.where))
            if prev[:2] != (key, r.frame_idx):
                raise DataError(
                    f"{_rel(path, src)}: listed as scene {prev[0]} frame {prev[1]} at {prev[2]} "
                    f"but as scene {key} frame {r.frame_idx} at {r.where} (sample '{r.sample_uid}')"
                )
            frame.files.add(path)
    for found in sorted(src.glob(cfg.gauss_glob)):
        rel = found.relative_to(src)
        path = contained(src, rel, "Gaussian file")
        if path in owner:
            continue
        ids = ids_from_path(rel)
        if ids is None:
            raise DataError(
                f"{rel.as_posix()}: no QA record lists it and its path names no scene/frame "
                "(expected .../scene_<n>/<frame>.pth or .../<n>_<view>/.../<frame>.pth)"
            )
        frames[ids[0]].setdefault(ids[1], _Frame(ids[1])).files.add(path)
    if not any(f.files for scene in frames.values() for f in scene.values()):
        raise DataError(f"source={src}: no Gaussian files (gauss_glob={cfg.gauss_glob!r}, no record lists one)")
    return frames


def _scene_poses(src: Path, cfg: ReleaseConfig, scene_key: int | str) -> list[np.ndarray]:
    rel = Path(cfg.pose_dir, cfg.pose_template.format(scene_idx=scene_key, scene_id=scene_key))
    path = contained(src, rel, f"{scene_id(scene_key)}: pose file")
    return read_pose_file(path, scene_id(scene_key))


def _frame_pose(poses: list[np.ndarray], frame: int, scene_key: int | str) -> np.ndarray:
    if frame >= len(poses):
        raise DataError(f"{scene_id(scene_key)}/frame {frame}: its pose file has only {len(poses)} rows")
    return poses[frame]


def _scene_sort_key(key: int | str) -> tuple[int, int, str]:
    return (0, key, "") if isinstance(key, int) else (1, 0, key)


def _rel(path: Path, src: Path) -> str:
    try:
        return path.relative_to(src).as_posix()
    except ValueError:
        return str(path)
