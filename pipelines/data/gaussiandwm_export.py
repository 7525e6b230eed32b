"""Exporter of a NuScenes-GSQA dataset into the public GaussianDWM release's format (``gdwm data export-gaussiandwm``).

The inverse of ``pipelines.data.gaussiandwm`` (the importer; its modules document the format): the folder written
here is laid out as the release's ``examples/dummy_data``, so the release's own loaders (``data/records.py``,
``data/dataset.py``, ``data/gauss_normalizer.py``) read it with their annotation, image, Gaussian and CLIP roots all
set to ``args.out=``, and ``gdwm data import-gaussiandwm source=<out>`` reads it back::

    <out>/
      qa_train.jsonl, qa_val.jsonl            QA records (major_task qa), one file per split of the qa table
      world_train.jsonl, world_val.jsonl      world records (major_task world), where the dataset has a world table
      gauss/scene_<idx:04d>/<frame:05d>.pth   one Gaussian state dict per frame (``release_fields``), every frame
                                              that has Gaussians, whether or not a record names it
      <copied files>                          world images, .npz depths, latent packs with their meta.json, CLIP
                                              shards and the QA images the dataset holds, at their dataset paths
                                              (a ``release/`` prefix, where an import put them, dropped)
      gdwm_export.json                        what was exported from where: dataset, fingerprint, scene mapping

Records: ``scene_idx`` is the release's int (an import's own index; else the number of a ``scene-<n>`` id; else the
scene's position), ``frame_idx`` the release's frame (an import's ``frames.token``; else our index). The text keeps
no ``<gauss>``: the release's loader puts one Gaussian item at the head of the first user turn, so the placeholder
is removed there, and one anywhere else, or a second one, is an error naming the sample. ``qa_group``/``qa_subtask``
are the release's own for records it came from (the provenance in ``qa.gt``, else a ``<group>/<subtask>``
category), otherwise the first group ``DEFAULT_TASK_MAP`` maps onto the task family, and our category as subtask.

Gaussians come from the dataset (an imported release holds them per frame) or from ``args.gaussians=DIR``, a folder laid
out as the per-scene outputs of the reconstruct or distill stage: ``<scene_id>/gaussians/<frame:05d>.arrow`` (the
stage writes ``gaussians/<frame>.arrow`` into its cache entry of each scene, ``<workdir>/cache/distill/<k2>/<key>/``;
link or copy each entry to ``DIR/<scene_id>``). Where both have a frame, ``args.gaussians`` wins. They keep the frame
they are stored in (our ego frame): run the release without ``gauss.pose_dir``. The release's ``_language_feature``
is [N, 3], so a feature code of another width (``stage.distill.d_z``) or none (reconstruction only) is refused.

What the release format cannot carry, and so a re-import lacks: cameras, ego poses, LiDAR, 3D/2D boxes, timestamps
and frame rates, scene names, descriptions and weathers (scene ids come back as ``scene_<idx:04d>``), images and
depth maps of the scenes other than the QA images copied, routes, the QA answers' ground truth ``qa.gt`` (an import
fills it with provenance), frame tokens (they come back as the release's frame index), frames that neither a record
nor a Gaussian file names, the position of a ``<gauss>`` not at the head of the first user turn (it comes back
there), a category outside the release's groups (it comes back as ``<group>/<category>``), and the split of one
frame's Gaussians into per-view files (one file per frame; ``gauss_paths`` in the provenance name the new file).
The release's own loader also requires of every QA record a CLIP text feature, images and ``gauss_paths``, and a
``qa_subtask`` its taxonomy lists (``configs/qa/budgets.yaml``, ``RELEASE_TAXONOMY``); the summary counts the
records that lack them.

Legend: N Gaussians.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import uuid
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from pipelines.data.gaussiandwm import FORMAT
from pipelines.data.gaussiandwm_pth import GREY, SH_C0
from pipelines.data.gaussiandwm_qa import DEFAULT_TASK_MAP, ROLES
from pipelines.data.layout import GAUSS_TOKEN, LATENT_META, RELEASE_DIR, SPLITS, DataError, contained, gaussians_relpath
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow

MANIFEST = "gdwm_export.json"
FEATURE_DIM = 3  # the release's _language_feature width (data/gauss_normalizer.py packs [N, 14])
OPACITY_EPS = 1e-12  # opacity 0 or 1 has no finite logit; the importer's sigmoid maps these back within 1e-12
# Our task family -> the release QA group it comes back from (the first DEFAULT_TASK_MAP entry: RD&P, not Caption).
TASK_GROUP = {task: group for group, task in reversed(DEFAULT_TASK_MAP.items())}
# The groups and subtasks the release's loader accepts (its configs/qa/budgets.yaml, taxonomy.py).
RELEASE_TAXONOMY = {
    "NuInteract_2DVG": ("2D_perception_location",),
    "NuInteract_3DVG": ("perception",),
    "NuInteract_RD&P": ("2D_perception_infos", "prediction", "not_gt_perception", "interaction"),
    "NuInteract_Caption": ("caption",),
    "NuInteract_Planning": ("planning_go_straight", "planning_turn_left", "planning_turn_right"),
}
_ROLE_OF = {ours: theirs for theirs, ours in ROLES.items()}  # human -> user, gpt -> assistant
_SCENE_NUMBER = re.compile(r"scene[_-]?(\d+)", re.IGNORECASE)


@dataclass
class ExportSummary:
    """What an export wrote; ``lines()`` is what the command prints."""

    dataset: str
    out: Path
    records: dict[str, int] = field(default_factory=dict)  # jsonl file -> records
    pth_files: int = 0
    pth_scenes: int = 0
    scenes: dict[str, int] = field(default_factory=dict)  # our scene id -> the release's scene_idx
    copied: int = 0
    clip_shards: int = 0
    qa_without_clip: int = 0
    qa_without_gauss: int = 0
    off_taxonomy: Counter = field(default_factory=Counter)  # "<group>/<subtask>" -> QA records

    def lines(self) -> list[str]:
        out = [f"exported {self.dataset} to {self.out} (GaussianDWM release format):"]
        out += [f"  {name:<18} {n} record(s)" for name, n in self.records.items()]
        out.append(f"  {'gauss/':<18} {self.pth_files} .pth file(s) of {self.pth_scenes} scene(s)")
        out.append(
            f"  {'copied':<18} {self.copied} file(s) (images, depths, latent packs, {self.clip_shards} CLIP shard(s))"
        )
        if self.qa_without_clip:
            out.append(
                f"note: {self.qa_without_clip} QA record(s) without a CLIP text feature (the release's loader needs "
                "clip_text_embed_path/row on every QA record)"
            )
        if self.qa_without_gauss:
            out.append(
                f"note: {self.qa_without_gauss} QA record(s) without gauss_paths (the release's loader needs them)"
            )
        if self.off_taxonomy:
            pairs = ", ".join(f"{k} ({n})" for k, n in sorted(self.off_taxonomy.items()))
            out.append(f"note: qa_group/qa_subtask outside the release's taxonomy (configs/qa/budgets.yaml): {pairs}")
        return out


def export(
    root: str | Path, out: str | Path, gaussians: str | Path | None = None, overwrite: bool = False
) -> ExportSummary:
    """Write the dataset at ``root`` into ``out`` in the release's format; published atomically (a temp dir beside
    ``out``, renamed into place). A non-empty ``out`` is refused unless ``overwrite`` and it holds an earlier export."""
    out = Path(out).expanduser().resolve()
    _check_out(out, overwrite)
    ds = _open(Path(root))
    gdir = _gaussians_dir(gaussians)
    name = ds.meta.get("name", ds.root.name)
    from_release = ds.meta.get("format") == FORMAT
    scene_rows = ds.table("scenes").to_pylist()
    scene_idx = release_scene_indices(scene_rows, from_release)
    frame_idx = _frame_indices(ds, from_release)
    sources = _gaussian_sources(ds, gdir, name)
    pth = {key: f"gauss/scene_{scene_idx[key[0]]:04d}/{frame_idx[key]:05d}.pth" for key in sources}
    summary = ExportSummary(name, out, scenes=scene_idx)
    plan = _Plan(ds, scene_idx, frame_idx, pth, gdir)
    qa = plan.qa_records(summary)
    world = plan.world_records() if ds.has_table("world") else {}

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        for key, rel in pth.items():
            _write_pth(tmp / rel, sources[key], f"{key[0]}/frame {key[1]}")
        for kind, by_split in (("qa", qa), ("world", world)):
            for split, records in by_split.items():
                fname = f"{kind}_{split}.jsonl"
                (tmp / fname).write_text("".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records))
                summary.records[fname] = len(records)
        for rel, src in sorted(plan.copies.items()):
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, tmp / rel)
        summary.pth_files, summary.pth_scenes = len(pth), len({sid for sid, _ in pth})
        summary.copied = len(plan.copies)
        summary.clip_shards = len(plan.clip_shards)
        manifest = {
            "dataset": name,
            "root": str(ds.root.resolve()),
            "fingerprint": ds.meta.get("fingerprint"),
            "gaussians": str(gdir) if gdir else None,
            "scene_idx": scene_idx,
            "records": summary.records,
            "pth_files": len(pth),
            "copied_files": len(plan.copies),
        }
        # An earlier export is recognised by it: overwrite=true replaces only those.
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2))
        _publish(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return summary


def release_fields(arrays: Mapping[str, np.ndarray], where: str) -> dict[str, torch.Tensor]:
    """Our activated Gaussians -> the release's raw 3DGS/LangSplat fields, the inverse of ``read_release_gaussians``:
    ``_scaling`` = log(scale), ``_opacity`` = logit(opacity) [N, 1], ``_features_dc`` = (color - 0.5) / C0 [N, 1, 3],
    ``_rotation`` the unit (w, x, y, z) quaternion, ``_xyz`` and ``_language_feature`` as stored; float32."""
    feature = np.asarray(arrays.get("feature", np.zeros((len(arrays["xyz"]), 0))), dtype=np.float32)
    if feature.shape[1] == 0:
        raise DataError(
            f"{where}: Gaussians have no 'feature' (reconstructed, not distilled); the release needs "
            f"_language_feature [N, {FEATURE_DIM}]"
        )
    if feature.shape[1] != FEATURE_DIM:
        raise DataError(
            f"{where}: Gaussian 'feature' is {feature.shape[1]}-d; the release's _language_feature is "
            f"[N, {FEATURE_DIM}] (distill with stage.distill.d_z={FEATURE_DIM})"
        )
    n = len(arrays["xyz"])
    opacity = np.clip(np.asarray(arrays["opacity"], np.float64).reshape(n, 1), OPACITY_EPS, 1.0 - OPACITY_EPS)
    color = np.asarray(arrays["color"], np.float64)
    fields = {
        "_xyz": np.asarray(arrays["xyz"], np.float32),
        "_features_dc": ((color - GREY) / SH_C0).reshape(n, 1, 3),
        "_scaling": np.log(np.asarray(arrays["scale"], np.float64)),
        "_rotation": np.asarray(arrays["rotation"], np.float32),
        "_opacity": np.log(opacity) - np.log1p(-opacity),
        "_language_feature": feature,
    }
    # np.array copies: the Arrow columns are read-only memory maps, which torch will not wrap.
    return {k: torch.from_numpy(np.array(v, dtype=np.float32, order="C")) for k, v in fields.items()}


def release_scene_indices(scenes: list[dict], from_release: bool) -> dict[str, int]:
    """Our scene id -> the release's int ``scene_idx``: an import's own index (``scenes.name``), else the number of a
    ``scene-<n>``/``scene_<n>`` id; where any scene has neither or two share one, every scene's position."""

    def number(row: dict) -> int | None:
        if from_release and str(row["name"]).isdigit():
            return int(row["name"])
        m = _SCENE_NUMBER.fullmatch(row["scene_id"])
        return int(m.group(1)) if m else None

    nums = [number(r) for r in scenes]
    if None in nums or len(set(nums)) != len(nums):
        return {r["scene_id"]: i for i, r in enumerate(scenes)}
    return {r["scene_id"]: n for r, n in zip(scenes, nums, strict=True)}


def strip_gauss_token(conversations: list[dict], where: str) -> list[dict]:
    """Our turns -> the release's (role/content) without ``<gauss>``, which may only head the first user turn."""
    first_user = next((i for i, t in enumerate(conversations) if t["from"] == "human"), None)
    out = []
    for i, turn in enumerate(conversations):
        text = turn["value"]
        count = text.count(GAUSS_TOKEN)
        if count and (i != first_user or count > 1):
            raise DataError(
                f"{where}: conversations[{i}] holds '{GAUSS_TOKEN}' {count}x; the release has one Gaussian item, "
                "in the first user turn"
            )
        if turn["from"] not in _ROLE_OF:
            raise DataError(f"{where}: conversations[{i}] is from '{turn['from']}', expected one of {list(_ROLE_OF)}")
        out.append({"role": _ROLE_OF[turn["from"]], "content": text.replace(GAUSS_TOKEN, "", 1)})
    return out


def export_relpath(rel: str) -> str:
    """Where a dataset file lands in the export: its dataset path, less the ``release/`` an import put it under."""
    return rel.removeprefix(f"{RELEASE_DIR}/")


class _Plan:
    """The records of one export and the files they need copied (``copies``: export path -> dataset file)."""

    def __init__(self, ds: GSQADataset, scene_idx: dict, frame_idx: dict, pth: dict, gdir: Path | None):
        self.ds = ds
        self.scene_idx = scene_idx
        self.frame_idx = frame_idx
        self.pth = pth
        self.gdir = gdir
        self.copies: dict[str, Path] = {}
        self.clip_shards: set[str] = set()
        self.clip = {r["sample_id"]: (r["path"], r["row"]) for r in ds.table("clip_text").to_pylist()}

    def qa_records(self, summary: ExportSummary) -> dict[str, list[dict]]:
        out: dict[str, list[dict]] = {s: [] for s in SPLITS}
        for row in self.ds.qa().to_pylist():
            where = f"qa.parquet sample '{row['sample_id']}' ({row['split']})"
            rec = self._common(row, "qa", where)
            group, subtask = _qa_group(row, where)
            rec |= {"qa_group": group, "qa_subtask": subtask}
            if group not in RELEASE_TAXONOMY or subtask not in RELEASE_TAXONOMY[group]:
                summary.off_taxonomy[f"{group}/{subtask}"] += 1
            if row["sample_id"] in self.clip:
                rel, clip_row = self.clip[row["sample_id"]]
                shard = self._copy(rel, f"{where}: CLIP shard")
                self.clip_shards.add(shard)
                rec |= {"clip_text_embed_path": shard, "clip_text_embed_row": clip_row}
            else:
                summary.qa_without_clip += 1
            summary.qa_without_gauss += not rec["gauss_paths"]
            for rel in row["image"]:
                self._copy_image(rel)
            out[_split(row, where)].append(rec)
        return _checked_splits(out, "qa")

    def world_records(self) -> dict[str, list[dict]]:
        out: dict[str, list[dict]] = {s: [] for s in SPLITS}
        for row in self.ds.world().to_pylist():
            where = f"world.parquet sample '{row['sample_id']}' ({row['split']})"

            def copied(key: str, row=row, where=where) -> list[str]:
                return [self._copy(rel, f"{where}: {key}[{i}]") for i, rel in enumerate(row[key])]

            rec = self._common(row, "world", where)
            rec["image_paths"] = copied("image")
            pack = self._copy(row["latent_pack"], f"{where}: latent_pack")
            meta = (Path(row["latent_pack"]).parent / LATENT_META).as_posix()
            self._copy(meta, f"{where}: latent_pack's {LATENT_META}")
            rec |= {
                "ref_image_path": self._copy(row["ref_image"], f"{where}: ref_image"),
                "pseudo_video_paths": copied("pseudo_rgb"),
                "pseudo_depth_paths": copied("pseudo_depth"),
                "target_latent_pack_path": pack,
                "target_latent_indices": list(row["latent_indices"]),
            }
            if row["gt_rgb"] or row["gt_depth"]:
                rec |= {"gt_rgb_frame_paths": copied("gt_rgb"), "gt_depth_npz_paths": copied("gt_depth")}
            for key in ("pseudo_source_name", "pseudo_source_kind"):
                if row[key] is not None:
                    rec[key] = row[key]
            rec |= {"fps": row["fps"], "motion_bucket_id": row["motion_bucket_id"]}
            out[_split(row, where)].append(rec)
        return _checked_splits(out, "world")

    def _common(self, row: dict, kind: str, where: str) -> dict:
        """The fields QA and world records share, in the release's key order."""
        sid, idx = row["scene_token"], row["frame_idx"]
        if (sid, idx) not in self.frame_idx:
            raise DataError(f"{where}: scene '{sid}' frame {idx} is not a frame of the dataset")
        return {
            "major_task": kind,
            "sample_uid": row["sample_id"],
            "scene_idx": self.scene_idx[sid],
            "frame_idx": self.frame_idx[sid, idx],
            "views": list(row["views"]),
            "image_paths": list(row["image"]),
            "gauss_paths": self._gauss_paths(row, where),
            "conversations": strip_gauss_token(row["conversations"], where),
        }

    def _gauss_paths(self, row: dict, where: str) -> list[str]:
        sid, idx = row["scene_token"], row["frame_idx"]
        own = gaussians_relpath(sid, idx)
        if not row["gauss"]:
            return []
        if list(row["gauss"]) != [own]:
            raise DataError(
                f"{where}: gauss {list(row['gauss'])}, expected [{own}] (a release record gets its own frame's)"
            )
        if (sid, idx) not in self.pth:
            also = f" nor {self.gdir / sid / 'gaussians' / f'{idx:05d}.arrow'}" if self.gdir else ""
            raise DataError(f"{where}: no Gaussians for {sid} frame {idx}: neither {own} in the dataset{also} exists")
        return [self.pth[sid, idx]]

    def _copy_image(self, rel: str) -> None:
        """A QA image, where the dataset holds it (an import keeps only the release's path: then nothing is copied)."""
        for found in (rel, f"{RELEASE_DIR}/{rel}"):
            try:
                if contained(self.ds.root, found, "QA image").is_file():
                    self._copy(found, "QA image")
                    return
            except DataError:  # a path leading outside the dataset is the release's, not a file of ours
                return

    def _copy(self, rel: str, what: str) -> str:
        """Plan the copy of a dataset file; returns its export path."""
        dest = export_relpath(rel)
        path = contained(self.ds.root, rel, what)
        if not path.is_file():
            raise DataError(f"{what} {rel} not found in the dataset at {self.ds.root}")
        if dest == MANIFEST or dest.endswith(".jsonl") or dest.startswith("gauss/"):
            raise DataError(f"{what} {rel}: its export path {dest} would clash with the records or Gaussians")
        prev = self.copies.setdefault(dest, path)
        if prev != path:
            raise DataError(f"{what} {rel}: export path {dest} would hold both {prev} and {path}")
        return dest


def _qa_group(row: dict, where: str) -> tuple[str, str]:
    """(qa_group, qa_subtask): the release's own where the record came from it, else from the task family."""
    try:
        prov = json.loads(row["gt"]) if row["gt"] else None
    except json.JSONDecodeError:
        prov = None
    if isinstance(prov, dict) and prov.get("source") == FORMAT and isinstance(prov.get("qa_group"), str):
        return prov["qa_group"], str(prov.get("qa_subtask") or "")
    category = row["category"] or ""
    head, _, tail = category.partition("/")
    if head in DEFAULT_TASK_MAP:
        return head, tail
    if row["task"] not in TASK_GROUP:
        raise DataError(f"{where}: task '{row['task']}' has no release QA group (known: {sorted(TASK_GROUP)})")
    return TASK_GROUP[row["task"]], category


def _split(row: dict, where: str) -> str:
    if row["split"] not in SPLITS:
        raise DataError(f"{where}: split '{row['split']}', expected one of {list(SPLITS)}")
    return row["split"]


def _checked_splits(by_split: dict[str, list[dict]], kind: str) -> dict[str, list[dict]]:
    """The release's files keep a sample once per split, and a sample in both splits unchanged (the importer's
    rule); the files of a kind the dataset has none of are left out."""
    seen: dict[str, tuple[str, str]] = {}
    for split, records in by_split.items():
        in_split: set[str] = set()
        for r in records:
            uid, text = r["sample_uid"], json.dumps(r, sort_keys=True)
            if uid in in_split:
                raise DataError(f"{kind}.parquet: sample '{uid}' appears twice in split {split}")
            in_split.add(uid)
            prev = seen.setdefault(uid, (split, text))
            if prev[1] != text:
                raise DataError(
                    f"{kind}.parquet: sample '{uid}' differs between splits {prev[0]} and {split} (the release keeps "
                    "a sample in both splits only unchanged)"
                )
    return by_split if any(by_split.values()) else {}


def _frame_indices(ds: GSQADataset, from_release: bool) -> dict[tuple[str, int], int]:
    """(our scene id, our frame) -> the release's frame_idx: an import's ``frames.token`` (where a scene's tokens are
    distinct numbers), else our index."""
    by_scene: dict[str, dict[int, str]] = {}
    for r in ds.table("frames").to_pylist():
        by_scene.setdefault(r["scene_id"], {})[r["frame_idx"]] = str(r["token"] or "")
    out = {}
    for sid, tokens in by_scene.items():
        numbered = from_release and all(t.isdigit() for t in tokens.values())
        numbered = numbered and len({int(t) for t in tokens.values()}) == len(tokens)
        out |= {(sid, idx): int(t) if numbered else idx for idx, t in tokens.items()}
    return out


def _gaussian_sources(ds: GSQADataset, gdir: Path | None, name: str) -> dict[tuple[str, int], Path]:
    """(scene id, frame) -> the Arrow file of its Gaussians: ``args.gaussians`` first, then the dataset."""
    out: dict[tuple[str, int], Path] = {}
    from_dir = 0
    for scene in ds.scenes():
        for f in range(scene.num_frames):
            rel = f"{scene.id}/gaussians/{f:05d}.arrow"
            if gdir is not None and (gdir / rel).is_file():
                out[scene.id, f] = contained(gdir, rel, "Gaussian file")
                from_dir += 1
            elif (ds.root / gaussians_relpath(scene.id, f)).is_file():
                out[scene.id, f] = contained(ds.root, gaussians_relpath(scene.id, f), "Gaussian file")
    if gdir is not None and not from_dir:
        raise DataError(
            f"args.gaussians={gdir}: no <scene_id>/gaussians/<frame:05d>.arrow for the scenes of dataset {name} "
            f"({', '.join(ds.scene_ids[:3])}{', ...' if len(ds.scene_ids) > 3 else ''})"
        )
    if not out:
        raise DataError(
            f"dataset {name} at {ds.root} holds no per-frame Gaussians; pass args.gaussians=DIR, a folder of "
            "<scene_id>/gaussians/<frame:05d>.arrow (the reconstruct/distill stage outputs of its scenes)"
        )
    return out


def _write_pth(path: Path, arrow: Path, where: str) -> None:
    arrays = gaussians_from_table(read_arrow(arrow, where))
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(release_fields(arrays, f"{where} ({arrow})"), path)  # a plain dict of tensors: weights_only loads it


def _open(root: Path) -> GSQADataset:
    if not (root / "dataset.json").is_file():
        raise DataError(f"{root}: no dataset to export (build it first: gdwm data synth / import-gaussiandwm)")
    return GSQADataset(root)


def _gaussians_dir(gaussians: str | Path | None) -> Path | None:
    if gaussians is None or str(gaussians) == "":
        return None
    path = Path(gaussians).expanduser().resolve()
    if not path.is_dir():
        raise DataError(f"args.gaussians={gaussians}: no such directory")
    return path


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise DataError(f"args.out={out}: exists and is not a directory")
    if not out.exists() or not any(out.iterdir()):
        return
    if not overwrite:
        raise DataError(f"args.out={out}: directory is not empty (overwrite=true replaces an earlier export)")
    if not (out / MANIFEST).is_file():
        raise DataError(f"args.out={out}: not empty and not an earlier export (no {MANIFEST}); refusing to replace it")


def _publish(tmp: Path, out: Path) -> None:
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex[:8]}")
        os.rename(out, old)
    os.rename(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
