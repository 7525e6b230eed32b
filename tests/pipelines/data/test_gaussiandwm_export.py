"""Export of a dataset into the GaussianDWM release's format, and the round trip import(export(dataset)): on
synthetic_mini (Gaussians from a stage-output folder) and on an imported release. Exact refusals; the real CLI.

Gaussians come back within the float32 round-off of the activations: xyz and feature bit-exact; scale, rotation,
opacity and color within rtol 1e-6, atol 1e-7 (log/exp, logit/sigmoid and the SH DC colour in float32).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pipelines.data.gaussiandwm import ReleaseConfig, build
from pipelines.data.gaussiandwm_export import (
    MANIFEST,
    TASK_GROUP,
    export,
    release_fields,
    release_scene_indices,
    strip_gauss_token,
)
from pipelines.data.gaussiandwm_pth import read_release_gaussians
from pipelines.data.layout import GAUSS_TOKEN, DataError, gaussians_relpath, gaussians_table, write_arrow
from pipelines.data.reader import GSQADataset, gaussians_from_table
from tests.pipelines.data.fixtures_release import write_release

RELEASE_FIELDS = ["_xyz", "_features_dc", "_scaling", "_rotation", "_opacity", "_language_feature"]


def random_gaussians(rng: np.random.Generator, n: int, feature_dim: int = 3) -> dict[str, np.ndarray]:
    """Gaussians as a stage writes them (float32 via the Arrow table), with opacity and colour at 0 and 1 exactly."""
    opacity, color = rng.random(n), rng.random((n, 3))
    opacity[:2], color[:2] = [0.0, 1.0], [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]
    arrays = {
        "xyz": rng.normal(size=(n, 3)) * 10,
        "scale": np.exp(rng.normal(size=(n, 3)) * 2 - 2),
        "rotation": rng.normal(size=(n, 4)),
        "opacity": opacity,
        "color": color,
        "feature": rng.random((n, feature_dim)),
    }
    return gaussians_from_table(gaussians_table(arrays))


def assert_gaussians_close(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    np.testing.assert_array_equal(got["xyz"], want["xyz"])
    np.testing.assert_array_equal(got["feature"], want["feature"])
    for key in ("scale", "rotation", "opacity", "color"):
        np.testing.assert_allclose(got[key], want[key], rtol=1e-6, atol=1e-7, err_msg=key)


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=600)


# ----------------------------------------------------------------------------- Gaussian fields


def test_release_fields_invert_the_importers_activation(tmp_path):
    want = random_gaussians(np.random.default_rng(3), 500)
    fields = release_fields(want, "frame 0")
    assert list(fields) == RELEASE_FIELDS
    assert {k: tuple(v.shape) for k, v in fields.items()} == {
        "_xyz": (500, 3),
        "_features_dc": (500, 1, 3),
        "_scaling": (500, 3),
        "_rotation": (500, 4),
        "_opacity": (500, 1),
        "_language_feature": (500, 3),
    }
    np.testing.assert_allclose(fields["_scaling"].numpy(), np.log(want["scale"]), rtol=1e-6)
    # opacity 0 and 1 have no finite logit: clamped to 1e-12 from either end.
    np.testing.assert_allclose(fields["_opacity"].numpy()[:2, 0], [-27.631021, 27.631021], rtol=1e-6)
    path = tmp_path / "00000.pth"
    torch.save(fields, path)
    loaded = torch.load(path, weights_only=True)  # a plain dict of tensors, as the release's files
    assert sorted(loaded) == sorted(RELEASE_FIELDS) and all(v.dtype == torch.float32 for v in loaded.values())
    back = read_release_gaussians(path, "00000.pth", feature_dim=3)
    assert back.has_color
    assert_gaussians_close(back.arrays, want)


def test_feature_width_other_than_the_releases_is_refused():
    with pytest.raises(DataError) as e:
        release_fields(random_gaussians(np.random.default_rng(0), 4, feature_dim=16), "scene-0000/frame 2")
    assert str(e.value) == (
        "scene-0000/frame 2: Gaussian 'feature' is 16-d; the release's _language_feature is [N, 3] "
        "(distill with stage.distill.d_z=3)"
    )
    reconstructed = {k: v for k, v in random_gaussians(np.random.default_rng(0), 4).items() if k != "feature"}
    with pytest.raises(DataError, match=r"^scene-0000/frame 2: Gaussians have no 'feature' \(reconstructed, not"):
        release_fields(reconstructed, "scene-0000/frame 2")


def test_gauss_token_is_removed_only_from_the_head_of_the_first_user_turn():
    turns = [
        {"from": "system", "value": "You drive."},
        {"from": "human", "value": f"{GAUSS_TOKEN}Where is the car?"},
        {"from": "gpt", "value": "Ahead."},
    ]
    assert strip_gauss_token(turns, "s") == [
        {"role": "system", "content": "You drive."},
        {"role": "user", "content": "Where is the car?"},
        {"role": "assistant", "content": "Ahead."},
    ]
    later = [*turns, {"from": "human", "value": f"And now {GAUSS_TOKEN}?"}]
    with pytest.raises(DataError) as e:
        strip_gauss_token(later, "qa.parquet sample 'x' (train)")
    assert str(e.value) == (
        "qa.parquet sample 'x' (train): conversations[3] holds '<gauss>' 1x; the release has one Gaussian item, "
        "in the first user turn"
    )
    twice = [{"from": "human", "value": f"{GAUSS_TOKEN} vs {GAUSS_TOKEN}"}]
    with pytest.raises(DataError, match=r"conversations\[0\] holds '<gauss>' 2x"):
        strip_gauss_token(twice, "s")


def test_scene_indices_from_import_names_ids_or_positions():
    rows = [{"scene_id": "scene-0003", "name": "a"}, {"scene_id": "scene_0007", "name": "b"}]
    assert release_scene_indices(rows, from_release=False) == {"scene-0003": 3, "scene_0007": 7}
    imported = [{"scene_id": "scene_0000", "name": "0"}, {"scene_id": "scene_0002", "name": "2"}]
    assert release_scene_indices(imported, from_release=True) == {"scene_0000": 0, "scene_0002": 2}
    clash = [
        {"scene_id": "scene-0001", "name": "a"},
        {"scene_id": "scene_1", "name": "b"},
        {"scene_id": "x", "name": "c"},
    ]
    assert release_scene_indices(clash, from_release=False) == {"scene-0001": 0, "scene_1": 1, "x": 2}


# ----------------------------------------------------------------------------- synthetic_mini round trip


@pytest.fixture(scope="module")
def synth_gaussians(synth_small, tmp_path_factory) -> tuple[Path, dict]:
    """A stage-output folder ``<scene_id>/gaussians/<frame:05d>.arrow`` for every frame, and what it holds."""
    gdir = tmp_path_factory.mktemp("stage_out")
    rng = np.random.default_rng(11)
    written = {}
    for scene in GSQADataset(synth_small).scenes():
        for f in range(scene.num_frames):
            written[scene.id, f] = random_gaussians(rng, 5 + f)
            write_arrow(gaussians_table(written[scene.id, f]), gdir / scene.id / "gaussians" / f"{f:05d}.arrow")
    return gdir, written


@pytest.fixture(scope="module")
def synth_export(synth_small, synth_gaussians, tmp_path_factory):
    base = tmp_path_factory.mktemp("synth_export")
    summary = export(synth_small, base / "out", synth_gaussians[0])
    back = GSQADataset(build(ReleaseConfig(), base / "back", str(base / "out")))
    return summary, base / "out", back


SCENES = {"scene-0000": "scene_0000", "scene-0001": "scene_0001"}  # scene ids come back as scene_<idx:04d>


def test_synthetic_export_writes_release_records(synth_small, synth_export):
    summary, out, _ = synth_export
    qa = GSQADataset(synth_small).qa().to_pylist()
    n_train = sum(r["split"] == "train" for r in qa)
    assert summary.records == {"qa_train.jsonl": n_train, "qa_val.jsonl": len(qa) - n_train}
    assert (summary.pth_files, summary.pth_scenes, summary.qa_without_clip) == (20, 2, len(qa))
    assert sorted(p.relative_to(out).as_posix() for p in out.glob("gauss/**/*.pth"))[:2] == [
        "gauss/scene_0000/00000.pth",
        "gauss/scene_0000/00001.pth",
    ]
    first = qa[0] if qa[0]["split"] == "train" else next(r for r in qa if r["split"] == "train")
    rec = read_jsonl(out / "qa_train.jsonl")[0]
    assert list(rec) == [
        "major_task",
        "sample_uid",
        "scene_idx",
        "frame_idx",
        "views",
        "image_paths",
        "gauss_paths",
        "conversations",
        "qa_group",
        "qa_subtask",
    ]
    assert rec["sample_uid"] == first["sample_id"] and rec["major_task"] == "qa"
    assert (rec["scene_idx"], rec["frame_idx"]) == (int(first["scene_token"][-4:]), first["frame_idx"])
    assert rec["gauss_paths"] == [f"gauss/scene_{rec['scene_idx']:04d}/{rec['frame_idx']:05d}.pth"]
    assert rec["conversations"][0] == {
        "role": "user",
        "content": first["conversations"][0]["value"].replace(GAUSS_TOKEN, ""),
    }
    assert (rec["qa_group"], rec["qa_subtask"]) == (TASK_GROUP[first["task"]], first["category"])
    # The QA images the dataset holds travel with the records.
    assert all((out / p).is_file() for r in read_jsonl(out / "qa_val.jsonl") for p in r["image_paths"])
    assert json.loads((out / MANIFEST).read_text())["scene_idx"] == {"scene-0000": 0, "scene-0001": 1}


def test_synthetic_round_trip_qa(synth_small, synth_export):
    *_, back = synth_export
    ours = {(r["sample_id"], r["split"]): r for r in GSQADataset(synth_small).qa().to_pylist()}
    theirs = {(r["sample_id"], r["split"]): r for r in back.qa().to_pylist()}
    assert sorted(theirs) == sorted(ours) and len(ours) == 211
    for key, a in ours.items():
        b = theirs[key]
        sid = SCENES[a["scene_token"]]
        assert (b["scene_token"], b["frame_idx"], b["task"]) == (sid, a["frame_idx"], a["task"])
        # The release keeps one Gaussian item at the head of the first user turn: <gauss> comes back there.
        human, *rest = a["conversations"]
        assert b["conversations"] == [
            {"from": "human", "value": GAUSS_TOKEN + human["value"].replace(GAUSS_TOKEN, "", 1)},
            *rest,
        ]
        assert b["category"] == f"{TASK_GROUP[a['task']]}/{a['category']}"
        assert (b["image"], b["views"]) == (a["image"], a["views"])
        assert b["gauss"] == [gaussians_relpath(sid, a["frame_idx"])]


def test_synthetic_round_trip_scenes_frames_and_gaussians(synth_small, synth_gaussians, synth_export):
    *_, back = synth_export
    ours = GSQADataset(synth_small)
    assert back.scene_ids == ["scene_0000", "scene_0001"]
    assert [s.num_frames for s in back.scenes()] == [s.num_frames for s in ours.scenes()] == [10, 10]
    frames = back.table("frames").to_pylist()
    assert [(f["scene_id"], f["frame_idx"], f["token"]) for f in frames] == [
        (SCENES[s], i, str(i)) for s in ("scene-0000", "scene-0001") for i in range(10)
    ]
    assert {f["timestamp_us"] for f in frames} == {None}  # the release has no timestamps
    for name in ("cameras", "ego_poses", "boxes3d", "boxes2d"):
        assert back.table(name).num_rows == 0
    for (sid, f), want in synth_gaussians[1].items():
        assert_gaussians_close(back.scene(SCENES[sid]).frame(f).gaussians(), want)


def test_dataset_without_gaussians_is_refused(synth_small, tmp_path):
    with pytest.raises(DataError) as e:
        export(synth_small, tmp_path / "out")
    assert str(e.value) == (
        f"dataset synthetic_mini at {synth_small} holds no per-frame Gaussians; pass args.gaussians=DIR, a folder of "
        "<scene_id>/gaussians/<frame:05d>.arrow (the reconstruct/distill stage outputs of its scenes)"
    )
    assert not (tmp_path / "out").exists()


def test_qa_frame_without_gaussians_is_refused(synth_small, synth_gaussians, tmp_path):
    gdir = tmp_path / "g"
    for path in synth_gaussians[0].glob("*/gaussians/*.arrow"):
        if path.name != "00004.arrow":  # every frame but frame 4
            dest = gdir / path.relative_to(synth_gaussians[0])
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(path.read_bytes())
    row = next(r for r in GSQADataset(synth_small).qa().to_pylist() if r["frame_idx"] == 4)
    with pytest.raises(DataError) as e:
        export(synth_small, tmp_path / "out", gdir)
    sid = row["scene_token"]
    assert str(e.value) == (
        f"qa.parquet sample '{row['sample_id']}' ({row['split']}): no Gaussians for {sid} frame 4: neither "
        f"scenes/{sid}/gaussians/00004.arrow in the dataset nor {gdir.resolve()}/{sid}/gaussians/00004.arrow exists"
    )
    assert [p.name for p in tmp_path.iterdir()] == ["g"]  # nothing written, no temp dir left


def test_out_dir_rules(synth_small, synth_gaussians, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(DataError) as e:
        export(synth_small, out, synth_gaussians[0])
    assert str(e.value) == f"args.out={out}: directory is not empty (overwrite=true replaces an earlier export)"
    with pytest.raises(DataError) as e:
        export(synth_small, out, synth_gaussians[0], overwrite=True)
    assert (
        str(e.value) == f"args.out={out}: not empty and not an earlier export (no {MANIFEST}); refusing to replace it"
    )
    assert (out / "notes.txt").read_text() == "mine"
    (out / "notes.txt").unlink()  # an empty folder is written into
    assert export(synth_small, out, synth_gaussians[0]).pth_files == 20
    (out / "stale.jsonl").write_text("{}\n")
    assert export(synth_small, out, synth_gaussians[0], overwrite=True).pth_files == 20
    assert not (out / "stale.jsonl").exists() and (out / MANIFEST).is_file()


# ----------------------------------------------------------------------------- release round trip


@pytest.fixture
def release_round_trip(tmp_path):
    release = write_release(tmp_path / "release")
    first = GSQADataset(build(ReleaseConfig(), tmp_path / "first", str(release.root)))
    summary = export(first.root, tmp_path / "out")
    second = GSQADataset(build(ReleaseConfig(), tmp_path / "second", str(tmp_path / "out")))
    return release, first, summary, tmp_path / "out", second


def _without_gauss_paths(rows: list[dict], column: str) -> tuple[list[dict], list[list[str]]]:
    """Rows with ``gauss_paths`` taken out of their provenance JSON, and those paths."""
    out, paths = [], []
    for r in rows:
        prov = json.loads(r[column])
        paths.append(prov.pop("gauss_paths"))
        out.append({**r, column: prov})
    return out, paths


def test_release_round_trip_tables(release_round_trip):
    _, first, summary, _, second = release_round_trip
    assert summary.records == {"qa_train.jsonl": 4, "qa_val.jsonl": 2, "world_train.jsonl": 2, "world_val.jsonl": 1}
    assert (summary.pth_files, summary.copied, summary.clip_shards, summary.qa_without_clip) == (4, 21, 1, 0)
    for name in ("scenes", "frames", "cameras", "ego_poses", "clip_text"):
        assert second.table(name).to_pylist() == first.table(name).to_pylist(), name
    qa_a, _ = _without_gauss_paths(first.qa().to_pylist(), "gt")
    qa_b, qa_paths = _without_gauss_paths(second.qa().to_pylist(), "gt")
    assert qa_b == qa_a
    # One .pth per frame: the provenance names the exported file (q1's frame was two view files).
    assert qa_paths == [
        ["gauss/scene_0000/00000.pth"],
        ["gauss/scene_0000/00001.pth"],
        ["gauss/scene_0000/00001.pth"],
        ["gauss/scene_0000/00001.pth"],
        ["gauss/scene_0002/00000.pth"],
        ["gauss/scene_0000/00001.pth"],
    ]
    world_a, _ = _without_gauss_paths(first.world().to_pylist(), "provenance")
    world_b, world_paths = _without_gauss_paths(second.world().to_pylist(), "provenance")
    assert world_b == world_a and len(world_a) == 3
    assert world_paths == [
        ["gauss/scene_0000/00000.pth"],
        ["gauss/scene_0002/00000.pth"],
        ["gauss/scene_0000/00000.pth"],
    ]


def test_release_round_trip_records_are_the_releases_own(release_round_trip):
    release, _, _, out, _ = release_round_trip
    pth = {0: "gauss/scene_0000/00000.pth", 1: "gauss/scene_0000/00001.pth"}
    originals = {r["sample_uid"]: r for r in [*release.records, *release.world]}
    exported = [*read_jsonl(out / "qa_train.jsonl"), *read_jsonl(out / "qa_val.jsonl")]
    exported += [*read_jsonl(out / "world_train.jsonl"), *read_jsonl(out / "world_val.jsonl")]
    assert [r["sample_uid"] for r in exported] == ["q1", "q2", "q3", "q5", "q4", "q5", "w1", "w2", "w1"]
    for rec in exported:
        own = originals[rec["sample_uid"]]
        new = pth[own["frame_idx"]] if own["scene_idx"] == 0 else "gauss/scene_0002/00000.pth"
        assert rec == {**own, "gauss_paths": [new]}, rec["sample_uid"]


def test_release_round_trip_gaussians_latents_and_files(release_round_trip):
    release, first, _, out, second = release_round_trip
    for scene in first.scenes():
        for f in scene.frames():
            assert_gaussians_close(second.scene(scene.id).frame(f.idx).gaussians(), f.gaussians())
    for a, b in zip(first.world_samples(), second.world_samples(), strict=True):
        np.testing.assert_array_equal(b.latents(), a.latents())
        np.testing.assert_array_equal(b.ref_image(), a.ref_image())
        np.testing.assert_array_equal(b.pseudo_depth(), a.pseudo_depth())
        np.testing.assert_array_equal(b.gt_rgb(), a.gt_rgb())
    np.testing.assert_array_equal(second.world_sample("w2").latents(), release.pack[[4, 0]])
    ids = ["q1", "q2", "q3", "q4", "q5"]
    np.testing.assert_array_equal(second.clip_text_features(ids), first.clip_text_features(ids))
    assert (out / "latents" / "meta.json").read_bytes() == (release.root / "latents" / "meta.json").read_bytes()


# ----------------------------------------------------------------------------- the CLI


def test_cli_exports_the_imported_release_and_refuses_a_used_out(tmp_path):
    release = write_release(tmp_path / "release")
    data = build(ReleaseConfig(), tmp_path / "data", str(release.root))
    out = (tmp_path / "out").resolve()
    args = ["data", "export-gaussiandwm", "data=gaussiandwm_release", f"data.root={data}", f"workdir={tmp_path}"]
    r = _gdwm(*args, f"args.out={out}")
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.splitlines() == [
        f"exported gaussiandwm_release to {out} (GaussianDWM release format):",
        "  qa_train.jsonl     4 record(s)",
        "  qa_val.jsonl       2 record(s)",
        "  world_train.jsonl  2 record(s)",
        "  world_val.jsonl    1 record(s)",
        "  gauss/             4 .pth file(s) of 2 scene(s)",
        "  copied             21 file(s) (images, depths, latent packs, 1 CLIP shard(s))",
    ]
    r = _gdwm(*args, f"args.out={out}")
    assert r.returncode == 1
    assert r.stderr.strip() == (
        f"gdwm data export-gaussiandwm: DataError: args.out={out}: directory is not empty "
        "(overwrite=true replaces an earlier export)"
    )
    r = _gdwm(*args, f"args.out={out}", "overwrite=true")
    assert r.returncode == 0, r.stderr[-3000:]
    assert len(read_jsonl(out / "world_train.jsonl")) == 2


def test_cli_refuses_synthetic_mini_without_gaussians_and_a_missing_out(synth_small, tmp_path):
    args = ["data", "export-gaussiandwm", f"data.root={synth_small}", f"workdir={tmp_path}"]
    r = _gdwm(*args, f"args.out={tmp_path / 'out'}")
    assert r.returncode == 1
    assert r.stderr.strip() == (
        f"gdwm data export-gaussiandwm: DataError: dataset synthetic_mini at {synth_small} holds no per-frame "
        "Gaussians; pass args.gaussians=DIR, a folder of <scene_id>/gaussians/<frame:05d>.arrow (the "
        "reconstruct/distill stage outputs of its scenes)"
    )
    r = _gdwm(*args)
    assert (r.returncode, r.stderr.strip()) == (
        2,
        "gdwm data export-gaussiandwm: args.out=DIR is required (the folder to write)",
    )
