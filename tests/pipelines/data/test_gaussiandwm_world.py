"""World (generation) records, CLIP text features and the split-overlap policy of the GaussianDWM release import:
values read back equal to what the fixture wrote, exact errors for bad input, and ``gdwm data info`` on the result."""

from __future__ import annotations

import json
import logging
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipelines.data.gaussiandwm import ReleaseConfig, build
from pipelines.data.layout import DataError
from pipelines.data.reader import GSQADataset
from pipelines.data.summary import summarize
from tests.pipelines.data.fixtures_release import (
    BACK0,
    CLIP_ROWS,
    CLIP_SHARD,
    FRONT0,
    PACK,
    PACK_SHAPE,
    S2F0,
    record,
    write_jsonl,
    write_npz,
    write_pack,
    write_png,
    write_release,
)
from tests.pipelines.data.test_gaussiandwm_import import assert_nothing_published


@pytest.fixture
def release(tmp_path: Path):
    return write_release(tmp_path / "release")


@pytest.fixture
def imported(release, tmp_path: Path) -> GSQADataset:
    return GSQADataset(build(ReleaseConfig(), tmp_path / "out", str(release.root)))


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _edit(path: Path, index: int, **changes) -> None:
    """Change one record of a JSONL file in place."""
    recs = _records(path)
    recs[index] |= changes
    write_jsonl(path, recs)


def _edit_w1(root: Path, **changes) -> None:
    """Change w1 in both world files (it stays one record, repeated in both splits)."""
    _edit(root / "world_train.jsonl", 0, **changes)
    _edit(root / "world_val.jsonl", 0, **changes)


# ----------------------------------------------------------------------------- world samples


def test_world_records_become_generation_samples(imported):
    rows = imported.world().to_pylist()
    assert [(r["sample_id"], r["split"], r["scene_token"], r["frame_idx"]) for r in rows] == [
        ("w1", "train", "scene_0000", 0),
        ("w2", "train", "scene_0002", 0),
        ("w1", "val", "scene_0000", 0),  # world_train.jsonl and world_val.jsonl both hold w1
    ]
    w1 = rows[0]
    assert w1["conversations"] == [{"from": "human", "value": "<gauss>Generate the next 3 frames."}]
    assert w1["gauss"] == ["scenes/scene_0000/gaussians/00000.arrow"]
    assert (w1["ref_image"], w1["image"]) == ("release/images/world_ref.png", ["release/images/world_ref.png"])
    assert w1["pseudo_rgb"] == [f"release/images/world_pseudo_{k:03d}.png" for k in range(3)]
    assert w1["pseudo_depth"] == [f"release/depth/world_pseudo_{k:03d}.npz" for k in range(3)]
    assert w1["gt_depth"] == [f"release/depth/world_gt_{k:03d}.npz" for k in range(3)]
    assert (w1["latent_pack"], w1["latent_indices"]) == ("release/latents/world_pack.dat", [1, 2, 3])
    assert (w1["fps"], w1["motion_bucket_id"], w1["pseudo_source_name"], w1["pseudo_source_kind"]) == (
        5,
        127,
        "dummy",
        "contract",
    )
    assert json.loads(w1["provenance"])["gauss_paths"] == [FRONT0, BACK0]
    w2 = rows[1]
    assert (w2["gt_rgb"], w2["gt_depth"], w2["fps"], w2["pseudo_source_name"]) == ([], [], 10, None)


def test_world_samples_read_back_what_the_release_holds(imported, release):
    w1 = imported.world_sample("w1", split="train")
    assert (w1.num_frames, w1.fps, w1.split) == (3, 5, "train")
    np.testing.assert_array_equal(w1.latents(), release.pack[[1, 2, 3]])
    assert w1.latents().shape == (3, 2, 4, 56, 96) and w1.latents().dtype == np.float32
    np.testing.assert_array_equal(w1.ref_image(), release.images["images/world_ref.png"])
    assert w1.ref_image().shape == (32, 48, 3)  # 48x32 reference, 32x24 frames: stored sizes, not resized
    pseudo = np.stack([release.images[f"images/world_pseudo_{k:03d}.png"] for k in range(3)])
    np.testing.assert_array_equal(w1.pseudo_rgb(), pseudo)
    assert w1.pseudo_rgb().shape == (3, 24, 32, 3)
    depth = np.stack([release.depths[f"depth/world_pseudo_{k:03d}.npz"] for k in range(3)])
    np.testing.assert_array_equal(w1.pseudo_depth(), depth)
    gt_rgb = np.stack([release.images[f"images/world_gt_{k:03d}.png"] for k in range(3)])
    np.testing.assert_array_equal(w1.gt_rgb(), gt_rgb)
    np.testing.assert_array_equal(
        w1.gt_depth(), np.stack([release.depths[f"depth/world_gt_{k:03d}.npz"] for k in range(3)])
    )
    w2 = imported.world_sample("w2")
    np.testing.assert_array_equal(w2.latents(), release.pack[[4, 0]])  # indices in record order, not sorted
    assert (w2.fps, w2.pseudo_rgb().shape, w2.pseudo_depth().shape) == (10, (2, 20, 40, 3), (2, 20, 40))
    assert w2.gt_rgb().shape == (0, 0, 0, 3) and w2.gt_depth().shape == (0, 0, 0)
    assert [(w.id, w.split) for w in imported.world_samples(split="val")] == [("w1", "val")]


def test_a_sample_in_both_splits_needs_its_split(imported):
    with pytest.raises(DataError) as e:
        imported.world_sample("w1")
    assert str(e.value) == f"{imported.root}: 2 (in splits ['train', 'val']; pass split=) world sample 'w1'"
    with pytest.raises(DataError) as e:
        imported.world_sample("w9")
    assert str(e.value) == f"{imported.root}: no world sample 'w9'"


def test_copies_are_the_release_bytes_and_in_the_fingerprint(imported, release):
    for rel in ("latents/meta.json", PACK, "depth/world_gt_002.npz", "images/w2_ref.png", CLIP_SHARD):
        assert (imported.root / "release" / rel).read_bytes() == (release.root / rel).read_bytes()
        assert f"release/{rel}" in imported.meta["files"]
    # QA images are not imported (as before); only what world records and CLIP features name is copied.
    assert not (imported.root / "release" / "images" / "q1.png").exists()
    assert (
        len([p for p in (imported.root / "release").rglob("*") if p.is_file()]) == 21
    )  # 10 images, 8 depths, pack + meta, shard


def test_datasets_without_world_data_read_empty_optional_tables(imported, tmp_path):
    for name in ("world.parquet", "clip_text.parquet"):
        (imported.root / name).unlink()
    ds = GSQADataset(imported.root)
    assert (ds.has_table("world"), ds.has_table("qa")) == (False, True)
    assert ds.world().num_rows == 0 and ds.world_samples() == [] and ds.table("clip_text").num_rows == 0
    assert ds.table("world").schema.names[:4] == ["sample_id", "scene_token", "frame_idx", "split"]


# ----------------------------------------------------------------------------- CLIP text features


def test_clip_text_features_follow_the_records_rows(imported, release):
    assert sorted(imported.table("clip_text").to_pylist(), key=lambda r: r["sample_id"]) == [
        {"sample_id": uid, "path": f"release/{CLIP_SHARD}", "row": row} for uid, row in sorted(CLIP_ROWS.items())
    ]  # q5, kept in both splits, has one feature
    for uid, row in CLIP_ROWS.items():
        np.testing.assert_array_equal(imported.clip_text_feature(uid), release.clip[row])
    features = imported.clip_text_features(["q4", "q1"])
    assert features.shape == (2, 512) and features.dtype == np.float32
    np.testing.assert_array_equal(features, release.clip[[5, 3]])


def test_a_record_without_a_clip_feature_imports_without_one(release, tmp_path):
    recs = _records(release.root / "qa_val.jsonl")
    write_jsonl(release.root / "qa_val.jsonl", [{k: v for k, v in recs[0].items() if "clip" not in k}, recs[1]])
    ds = GSQADataset(build(ReleaseConfig(), tmp_path / "out", str(release.root)))
    assert sorted(r["sample_id"] for r in ds.table("clip_text").to_pylist()) == ["q1", "q2", "q3", "q5"]
    with pytest.raises(DataError) as e:
        ds.clip_text_feature("q4")
    assert str(e.value) == f"{ds.root}: QA sample 'q4' has no CLIP text feature"


# ----------------------------------------------------------------------------- split overlap


WARN = (
    "gaussiandwm_release: 2 record(s) in both train and val: 'q5' (qa_train.jsonl:4, qa_val.jsonl:2), "
    "'w1' (world_train.jsonl:1, world_val.jsonl:1); "
)


def test_split_overlap_warn_keeps_both_copies_with_one_warning(release, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="pipelines.data.gaussiandwm"):
        ds = GSQADataset(build(ReleaseConfig(), tmp_path / "out", str(release.root)))
    assert [r.getMessage() for r in caplog.records] == [
        WARN + "kept in both splits (data.split_overlap=warn; drop_from_train keeps them in val only, "
        "error refuses the import)"
    ]
    assert [r["split"] for r in ds.qa().to_pylist() if r["sample_id"] == "q5"] == ["train", "val"]
    assert [w.split for w in ds.world_samples() if w.id == "w1"] == ["train", "val"]
    assert ds.meta["split_overlap"] == {"policy": "warn", "sample_ids": ["q5", "w1"]}


def test_split_overlap_drop_from_train_keeps_the_val_copy(release, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="pipelines.data.gaussiandwm"):
        ds = GSQADataset(build(ReleaseConfig(split_overlap="drop_from_train"), tmp_path / "out", str(release.root)))
    assert [r.getMessage() for r in caplog.records] == [
        WARN + "dropped from train, kept in val (data.split_overlap=drop_from_train)"
    ]
    assert [(r["sample_id"], r["split"]) for r in ds.qa().to_pylist()] == [
        ("q1", "train"),
        ("q2", "train"),
        ("q3", "train"),
        ("q4", "val"),
        ("q5", "val"),
    ]
    assert [(w.id, w.split) for w in ds.world_samples()] == [("w2", "train"), ("w1", "val")]
    assert ds.meta["qa"]["by_task"] == {"rdp": 2, "vg2d": 1, "vg3d": 1, "plan": 1}
    np.testing.assert_array_equal(ds.clip_text_feature("q5"), release.clip[CLIP_ROWS["q5"]])


def test_split_overlap_error_refuses_naming_every_record(release, tmp_path):
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(split_overlap="error"), root, str(release.root))
    assert str(e.value) == (
        "2 record(s) in both train and val: 'q5' (qa_train.jsonl:4, qa_val.jsonl:2), "
        "'w1' (world_train.jsonl:1, world_val.jsonl:1) "
        "(data.split_overlap=error; warn keeps both copies, drop_from_train keeps val only)"
    )
    assert_nothing_published(root)


def test_split_overlap_must_be_a_known_policy(release, tmp_path):
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(split_overlap="ignore"), tmp_path / "out", str(release.root))
    assert str(e.value) == "data.split_overlap is 'ignore', expected one of ['warn', 'drop_from_train', 'error']"


# ----------------------------------------------------------------------------- record kinds


@pytest.mark.parametrize("kind", ["caption", None])
def test_major_task_decides_the_kind_and_an_unknown_one_is_an_error(release, tmp_path, kind):
    _edit(release.root / "world_val.jsonl", 0, major_task=kind)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == f"world_val.jsonl:1 sample 'w1': 'major_task' is {kind!r}, expected one of ['qa', 'world']"
    assert_nothing_published(root)


def test_a_world_record_is_not_read_as_qa(release, tmp_path):
    """The default glob matches world_*.jsonl: their records lack qa_group, which only QA records need."""
    assert "qa_group" not in _records(release.root / "world_train.jsonl")[0]
    write_jsonl(release.root / "qa_val.jsonl", [record("q9", 2, 0, [S2F0], "NuInteract_RD&P", "prediction", "?")])
    recs = _records(release.root / "qa_val.jsonl")
    del recs[0]["qa_group"]
    write_jsonl(release.root / "qa_val.jsonl", recs)
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), tmp_path / "out", str(release.root))
    assert str(e.value) == "qa_val.jsonl:1 sample 'q9': missing or empty 'qa_group'"


# ----------------------------------------------------------------------------- bad input


def _short_pack(root: Path) -> None:
    _edit(root / "world_train.jsonl", 1, target_latent_indices=[4, 5])


def _truncated_pack(root: Path) -> None:
    data = (root / PACK).read_bytes()
    (root / PACK).write_bytes(data[: len(data) // 2])


def _pseudo_size(root: Path) -> None:
    write_png(root / "images/world_pseudo_001.png", np.zeros((24, 30, 3), np.uint8))


def _pseudo_depth_size(root: Path) -> None:
    write_npz(root / "depth/world_pseudo_002.npz", depth_proj=np.ones((24, 31), np.float32))


def _pseudo_depth_key(root: Path) -> None:
    write_npz(root / "depth/world_pseudo_002.npz", depth=np.ones((24, 32), np.float32))


def _gt_depth_key(root: Path) -> None:
    write_npz(root / "depth/world_gt_001.npz", disparity=np.ones((24, 32), np.float32))


def _depth_not_npz(root: Path) -> None:
    (root / "depth/world_pseudo_000.npz").write_bytes(b"not a zip")


def _clip_row(root: Path) -> None:
    _edit(root / "qa_train.jsonl", 2, clip_text_embed_row=6)


def _clip_width(root: Path) -> None:
    np.save(root / CLIP_SHARD, np.zeros((6, 256), np.float32))


def _frame_count(root: Path) -> None:
    _edit_w1(root, target_latent_indices=[1, 2])


def _ref_outside(root: Path) -> None:
    write_png(root.parent / "outside.png", np.zeros((4, 4, 3), np.uint8))
    _edit_w1(root, ref_image_path="../outside.png")


def _latent_shape(root: Path) -> None:
    write_pack(root, PACK, np.zeros((5, 2, 4, 28, 48), np.float32))


def _per_frame_latents(root: Path) -> None:
    recs = _records(root / "world_train.jsonl")
    del recs[1]["target_latent_pack_path"]
    recs[1]["target_latent_paths"] = ["latents/w2_000.pt", "latents/w2_001.pt"]
    write_jsonl(root / "world_train.jsonl", recs)


W1, W2 = "world_train.jsonl:1 sample 'w1'", "world_train.jsonl:2 sample 'w2'"
NEED = int(np.prod(PACK_SHAPE)) * 4


@pytest.mark.parametrize(
    ("corrupt", "message"),
    [
        (
            _short_pack,
            f"{W2}: 'target_latent_indices' reach 5 but target_latent_pack_path {PACK} holds 5 latents "
            "(meta.json shape [5, 2, 4, 56, 96])",
        ),
        (
            _truncated_pack,
            f"{W1}: target_latent_pack_path {PACK}: latent pack is {NEED // 2} bytes, meta.json shape "
            f"[5, 2, 4, 56, 96] of float32 needs {NEED}",
        ),
        (
            _pseudo_size,
            f"{W1}: pseudo_video_paths[1] images/world_pseudo_001.png is 30x24 but pseudo_video_paths[0] "
            "images/world_pseudo_000.png is 32x24 (the frames of one stream must share one size)",
        ),
        (
            _pseudo_depth_size,
            f"{W1}: pseudo_depth_paths[2] depth/world_pseudo_002.npz is 31x24 but pseudo_depth_paths[0] "
            "depth/world_pseudo_000.npz is 32x24 (the frames of one stream must share one size)",
        ),
        (
            _pseudo_depth_key,
            f"{W1}: pseudo_depth_paths[2] depth/world_pseudo_002.npz: no array 'depth_proj' in the .npz "
            "(arrays: ['depth'])",
        ),
        (
            _gt_depth_key,
            f"{W1}: gt_depth_npz_paths[1] depth/world_gt_001.npz: no array 'depth' or 'depth_gt' or 'depth_proj' "
            "in the .npz (arrays: ['disparity'])",
        ),
        (
            _depth_not_npz,
            f"{W1}: pseudo_depth_paths[0] depth/world_pseudo_000.npz: not a readable .npz (not an array file: it would "
            "need unpickling, which is never done)",
        ),
        (
            _clip_row,
            "qa_train.jsonl:3 sample 'q3': clip_text_embed_row 6 is out of range for "
            "clip_text/features_000000.npy (6 rows)",
        ),
        (
            _clip_width,
            "qa_train.jsonl:1 sample 'q1': clip_text_embed_path clip_text/features_000000.npy: shard has shape "
            "[6, 256], expected [N, 512] (data.clip_dim)",
        ),
        (_frame_count, f"{W1}: 'target_latent_indices' has 2 entries but 'pseudo_video_paths' has 3"),
        (
            _latent_shape,
            f"{W1}: target_latent_pack_path {PACK}: meta.json shape [5, 2, 4, 28, 48] has latents [4, 28, 48], "
            "expected [C, H, W] = [4, 56, 96] (data.latent_chw)",
        ),
        (
            _per_frame_latents,
            f"{W2}: world record lacks 'target_latent_pack_path' (per-frame target_latent_paths are not imported)",
        ),
    ],
)
def test_bad_world_and_clip_input_is_refused_naming_file_and_field(release, tmp_path, corrupt, message):
    corrupt(release.root)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    text = str(e.value)
    assert "\n" not in text
    assert text == message
    assert_nothing_published(root)


def test_a_world_file_leading_out_of_the_source_is_refused(release, tmp_path):
    _ref_outside(release.root)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == (
        f"{W1}: ref_image_path ../outside.png leads outside {release.root.resolve()} "
        f"(to {(tmp_path / 'outside.png').resolve()}); refusing to read it"
    )
    assert_nothing_published(root)


def test_latent_chw_option_accepts_other_latent_sizes(release, tmp_path):
    pack = np.arange(np.prod((5, 2, 4, 28, 48)), dtype=np.float32).reshape(5, 2, 4, 28, 48)
    write_pack(release.root, PACK, pack)
    ds = GSQADataset(build(ReleaseConfig(latent_chw=[4, 28, 48]), tmp_path / "out", str(release.root)))
    np.testing.assert_array_equal(ds.world_sample("w2").latents(), pack[[4, 0]])


# ----------------------------------------------------------------------------- gdwm data info


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=600)


def test_import_and_data_info_on_the_cli(release, tmp_path):
    work = tmp_path / "w"
    r = _gdwm("data", "import-gaussiandwm", f"source={release.root}", f"workdir={work}")
    assert r.returncode == 0, r.stderr[-3000:]
    stderr = " ".join(r.stderr.split())
    assert "gaussiandwm_release: 2 record(s) in both train and val: 'q5' (qa_train.jsonl:4, qa_val.jsonl:2)" in stderr
    r = _gdwm("data", "info", "data=gaussiandwm_release", f"workdir={work}")
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    header = next(i for i, x in enumerate(lines) if "scenes" in x and "QA" in x)
    cells = [c.strip() for c in re.split("[│┃]", lines[header + 2])[1:-1]]
    assert cells[:7] == ["2", "4", "0", "-", "0", "0", "6"]  # scenes, frames, cameras, weathers, boxes, QA
    assert "QA splits: train 4, val 2" in r.stdout
    assert "world samples: 3 (train 2, val 1)" in r.stdout and "CLIP text features: 5 QA samples" in r.stdout
    assert "verified: 34 files match dataset.json" in r.stdout
    s = summarize(work / "data" / "gaussiandwm_release")  # what `gdwm data info` prints from
    assert (s["world_samples"], s["world_per_split"], s["clip_text_features"]) == (3, {"train": 2, "val": 1}, 5)
    assert (s["qa_total"], s["qa_per_split"], s["files"]) == (6, {"train": 4, "val": 2}, 34)
