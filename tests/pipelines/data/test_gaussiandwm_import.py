"""Import of the GaussianDWM public release (QA records and Gaussians): round trip through GSQADataset and exact
errors. World samples, CLIP features and the split-overlap policy: test_gaussiandwm_world.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from pipelines.data.gaussiandwm import ReleaseConfig, build, ids_from_path
from pipelines.data.gaussiandwm_pth import SH_C0, refusal
from pipelines.data.layout import DataError, pose_matrix
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_release import (
    BACK0,
    CLIP_SHARD,
    FRONT0,
    FRONT1,
    S2F0,
    S2F3,
    NotATensor,
    RunsACommand,
    gaussian_fields,
    record,
    write_jsonl,
    write_pth,
    write_release,
)


def expected(fields: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """The activation the importer must apply, computed independently in float64."""
    rot = fields["_rotation"].double().numpy()
    dc = fields.get("_features_dc")
    return {
        "xyz": fields["_xyz"].numpy(),
        "scale": np.exp(fields["_scaling"].double().numpy()),
        "rotation": rot / np.linalg.norm(rot, axis=1, keepdims=True),
        "opacity": 1.0 / (1.0 + np.exp(-fields["_opacity"].double().numpy()[:, 0])),
        "color": np.full((len(rot), 3), 0.5)
        if dc is None
        else np.clip(0.5 + SH_C0 * dc.double().numpy()[:, 0, :], 0, 1),
        "feature": fields["_language_feature"].numpy(),
    }


def stacked(*parts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def assert_gaussians(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    np.testing.assert_array_equal(got["xyz"], want["xyz"])
    np.testing.assert_array_equal(got["feature"], want["feature"])
    for key in ("scale", "rotation", "opacity", "color"):
        np.testing.assert_allclose(got[key], want[key], rtol=1e-6, atol=1e-7, err_msg=key)


def assert_nothing_published(root: Path) -> None:
    assert not root.exists()
    assert [p.name for p in root.parent.iterdir() if p.name.startswith(f".{root.name}")] == []


@pytest.fixture
def release(tmp_path: Path):
    return write_release(tmp_path / "release")


@pytest.fixture
def imported(release, tmp_path: Path) -> GSQADataset:
    return GSQADataset(build(ReleaseConfig(), tmp_path / "out", str(release.root)))


def test_scenes_and_frames_follow_records_then_paths(imported):
    assert imported.scene_ids == ["scene_0000", "scene_0002"]
    scenes = imported.table("scenes").to_pylist()
    assert [(s["name"], s["num_frames"], s["frame_rate_hz"], s["weathers"]) for s in scenes] == [
        ("0", 2, None, []),
        ("2", 2, None, []),
    ]
    frames = imported.table("frames").to_pylist()
    # scene 2 has release frames 0 and 3 (3 only from its path): renumbered 0, 1, original kept in token.
    assert [(f["scene_id"], f["frame_idx"], f["token"], f["timestamp_us"]) for f in frames] == [
        ("scene_0000", 0, "0", None),
        ("scene_0000", 1, "1", None),
        ("scene_0002", 0, "0", None),
        ("scene_0002", 1, "3", None),
    ]
    for name in ("cameras", "ego_poses", "boxes3d", "boxes2d"):
        assert imported.table(name).num_rows == 0


def test_gaussians_round_trip(imported, release):
    t = release.tensors
    # Two view files of one frame are merged, in path order (0_CAM_BACK before 0_CAM_FRONT).
    assert_gaussians(
        imported.scene("scene_0000").frame(0).gaussians(), stacked(expected(t[BACK0]), expected(t[FRONT0]))
    )
    assert_gaussians(imported.scene("scene_0000").frame(1).gaussians(), expected(t[FRONT1]))
    assert_gaussians(imported.scene("scene_0002").frame(0).gaussians(), expected(t[S2F0]))
    g = imported.scene("scene_0002").frame(1).gaussians()
    assert_gaussians(g, expected(t[S2F3]))
    assert g["xyz"].shape == (3, 3) and g["feature"].shape == (3, 3) and g["opacity"].shape == (3,)


def test_qa_records_are_mapped(imported):
    qa = imported.qa().to_pylist()
    # q5 is in qa_train.jsonl and qa_val.jsonl, as the release's examples repeat a record (split_overlap=warn).
    assert [(r["sample_id"], r["split"]) for r in qa] == [
        ("q1", "train"),
        ("q2", "train"),
        ("q3", "train"),
        ("q5", "train"),
        ("q4", "val"),
        ("q5", "val"),
    ]
    rows = {r["sample_id"]: r for r in qa}
    assert {k: r["task"] for k, r in rows.items()} == {
        "q1": "rdp",
        "q2": "vg2d",
        "q3": "vg3d",
        "q4": "plan",
        "q5": "rdp",
    }
    q2 = rows["q2"]
    # The release's text has no <gauss>: its loader puts the Gaussian item right before the first user text.
    assert q2["conversations"] == [
        {"from": "human", "value": "<gauss>Where is the car?"},
        {"from": "gpt", "value": "answer of q2"},
    ]
    assert q2["category"] == "NuInteract_2DVG/2D_perception_location"
    assert (q2["scene_token"], q2["frame_idx"], q2["split"]) == ("scene_0000", 1, "train")
    assert q2["gauss"] == ["scenes/scene_0000/gaussians/00001.arrow"]
    assert (q2["image"], q2["views"]) == (["images/q2.png"], ["CAM_FRONT"])
    gt = json.loads(q2["gt"])
    assert (gt["gauss_paths"], gt["clip_text_embed_path"], gt["clip_text_embed_row"]) == ([FRONT1], CLIP_SHARD, 0)
    assert (rows["q4"]["scene_token"], rows["q4"]["split"]) == ("scene_0002", "val")
    assert [r["sample_id"] for r in imported.qa(split="train", task="vg3d").to_pylist()] == ["q3"]


def test_meta_records_what_the_release_lacks(imported):
    meta = imported.meta
    assert meta["format"] == "gaussiandwm_release"
    assert meta["modalities"]["images"] is False and meta["modalities"]["gaussians"] is True
    assert meta["modalities"]["world"] is True and meta["modalities"]["clip_text"] is True
    assert meta["gaussians"]["files_by_color_source"] == {"sh_dc": 2, "grey": 3}
    assert meta["gaussians"]["frame"] == "as released (no pose_dir given)"
    assert meta["qa"]["by_task"] == {"rdp": 3, "vg2d": 1, "vg3d": 1, "plan": 1}
    assert (meta["qa"]["records"], meta["qa"]["gauss_token_inserted"], meta["qa"]["clip_text_features"]) == (6, 6, 5)
    assert meta["world"]["samples"] == 3 and meta["world"]["by_split"] == {"train": 2, "val": 1}
    assert (meta["num_scenes"], meta["num_frames"], meta["cameras"]) == (2, 4, [])


def test_pose_dir_moves_gaussians_into_ego(release, tmp_path):
    poses = release.root / "poses"
    poses.mkdir()
    w2e = [pose_matrix([np.cos(a / 2), 0, 0, np.sin(a / 2)], [1.0 + a, -2.0, 0.5]) for a in (0.3, -0.7)]
    (poses / "0.txt").write_text("".join(" ".join(map(str, m.reshape(-1))) + "\n" for m in w2e))
    (poses / "2.txt").write_text("\n".join(" ".join(map(str, np.eye(4).reshape(-1))) for _ in range(4)))
    ds = GSQADataset(build(ReleaseConfig(pose_dir="poses"), tmp_path / "posed", str(release.root)))
    scene = ds.scene("scene_0000")
    np.testing.assert_allclose(scene.ego_poses[1], np.linalg.inv(w2e[1]), atol=1e-6)
    got, raw = scene.frame(1).gaussians(), expected(release.tensors[FRONT1])
    np.testing.assert_allclose(got["xyz"], raw["xyz"] @ w2e[1][:3, :3].T + w2e[1][:3, 3], atol=1e-4)
    # Orientation: rotation matrix of the stored quaternion == R_world2ego @ R_release.
    for q_got, q_raw in zip(got["rotation"], raw["rotation"], strict=True):
        want = w2e[1][:3, :3] @ pose_matrix(q_raw, [0, 0, 0])[:3, :3]
        np.testing.assert_allclose(pose_matrix(q_got, [0, 0, 0])[:3, :3], want, atol=1e-5)
    np.testing.assert_allclose(got["scale"], raw["scale"], rtol=1e-6)
    assert ds.meta["gaussians"]["frame"] == "ego (world->ego from pose_dir)"


def test_ids_from_release_paths():
    assert ids_from_path(Path(FRONT1)) == (0, 1)
    assert ids_from_path(Path(S2F3)) == (2, 3)
    assert ids_from_path(Path("gauss/scene-0011/00042.pth")) == (11, 42)
    assert ids_from_path(Path("gauss/misc/model.pth")) is None


def test_gauss_token_is_inserted_by_default_and_required_when_insertion_is_off(release, tmp_path):
    records = [
        record("ok", 0, 0, [FRONT0], "NuInteract_RD&P", "prediction", "Based on <gauss>, fine?"),
        record("nogauss", 0, 1, [FRONT1], "NuInteract_RD&P", "prediction", "What is likely to happen next?"),
    ]
    write_jsonl(release.root / "qa_train.jsonl", records)
    root = tmp_path / "out"
    ds = GSQADataset(build(ReleaseConfig(), root, str(release.root)))
    turns = {r["sample_id"]: r["conversations"][0]["value"] for r in ds.qa().to_pylist()}
    assert turns["nogauss"] == "<gauss>What is likely to happen next?"
    assert turns["ok"] == "Based on <gauss>, fine?"  # one placeholder already: none added
    assert ds.meta["qa"]["gauss_token_inserted"] == 3  # nogauss, q4, q5 (qa_val.jsonl)
    off = tmp_path / "off"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(insert_gauss_token=False), off, str(release.root))
    assert str(e.value) == (
        "qa_train.jsonl:2 sample 'nogauss': first user turn lacks '<gauss>' although the record has gauss_paths "
        "(set insert_gauss_token=true to insert it as the release's loader does)"
    )
    assert_nothing_published(off)


def test_records_that_carry_the_placeholder_import_unchanged_with_insertion_off(release, tmp_path):
    for name in ("qa_train.jsonl", "qa_val.jsonl", "world_train.jsonl", "world_val.jsonl"):
        lines = (release.root / name).read_text().splitlines()
        recs = [json.loads(x) for x in lines]
        for r in recs:
            r["conversations"][0]["content"] = "<gauss>\n" + r["conversations"][0]["content"]
        write_jsonl(release.root / name, recs)
    ds = GSQADataset(build(ReleaseConfig(insert_gauss_token=False), tmp_path / "out", str(release.root)))
    assert ds.qa().to_pylist()[1]["conversations"][0]["value"] == "<gauss>\nWhere is the car?"
    assert ds.world().to_pylist()[0]["conversations"][0]["value"] == "<gauss>\nGenerate the next 3 frames."
    assert ds.meta["qa"]["gauss_token_inserted"] == 0


def test_malformed_jsonl_line_names_file_and_line(release, tmp_path):
    with open(release.root / "qa_val.jsonl", "a") as f:
        f.write('{"sample_uid": \n')
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == "qa_val.jsonl:3: malformed JSON (Expecting value at column 16)"
    assert_nothing_published(root)


def test_unmapped_qa_group_is_an_error(release, tmp_path):
    write_jsonl(release.root / "qa_val.jsonl", [record("x", 2, 0, [S2F0], "Mystery", "m", "<gauss> ?")])
    with pytest.raises(DataError, match=r"^qa_val.jsonl:1 sample 'x': qa_group 'Mystery' has no task mapping"):
        build(ReleaseConfig(), tmp_path / "out", str(release.root))


def _nan_xyz(f):
    f["_xyz"][2, 1] = float("nan")


def _rotation_3(f):
    f["_rotation"] = f["_rotation"][:, :3]


def _zero_rotation(f):
    f["_rotation"][4] = 0.0


def _huge_scaling(f):
    f["_scaling"][1, 0] = 200.0


@pytest.mark.parametrize(
    ("corrupt", "message"),
    [
        (_nan_xyz, "field '_xyz' has NaN/Inf (1 values, first at row 2)"),
        (_rotation_3, "field '_rotation' has shape [6, 3], expected [6, 4]"),
        (_zero_rotation, "field '_rotation' has a zero quaternion at row 4"),
        (_huge_scaling, "field '_scaling' gives exp(_scaling) outside float32 range (1 values, first at row 1)"),
    ],
)
def test_bad_gaussians_name_file_and_field(release, tmp_path, corrupt, message):
    fields = gaussian_fields(6, seed=9)
    corrupt(fields)
    write_pth(release.root / FRONT1, fields, nested=True)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == f"{FRONT1}: {message}"
    assert_nothing_published(root)


def test_feature_width_must_match_config(release, tmp_path):
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(feature_dim=4), tmp_path / "out", str(release.root))
    # The first file read is scene 0 frame 0's 0_CAM_BACK view (5 Gaussians).
    assert str(e.value) == f"{BACK0}: field '_language_feature' has shape [5, 3], expected [5, 4]"


def test_pickled_object_is_refused_by_weights_only_loading(release, tmp_path):
    fields = gaussian_fields(3, seed=1)
    fields["_xyz"] = NotATensor()
    write_pth(release.root / S2F3, fields)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == (
        f"{S2F3}: refused by torch.load(weights_only=True): unsupported GLOBAL "
        "tests.pipelines.data.fixtures_release.NotATensor "
        "(only tensors, containers and numeric arrays are accepted; it is never loaded unsafely)"
    )
    assert_nothing_published(root)


def test_a_pickled_call_of_os_system_is_refused_by_name_and_never_run(release, tmp_path):
    marker = tmp_path / "it_ran"
    fields = gaussian_fields(3, seed=1)
    fields["_xyz"] = RunsACommand(f"touch {marker}")  # pickled as GLOBAL posix.system + its argument
    write_pth(release.root / S2F3, fields, nested=True)
    assert b"posix" in (release.root / S2F3).read_bytes()  # the global is in the file (torch.save zips it unpacked)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    # torch's own message leads with advice to turn weights_only off: never shown, never followed.
    assert str(e.value) == (
        f"{S2F3}: refused by torch.load(weights_only=True): unsupported GLOBAL posix.system "
        "(only tensors, containers and numeric arrays are accepted; it is never loaded unsafely)"
    )
    assert not marker.exists()
    assert_nothing_published(root)


def test_refusal_reports_what_torch_refused_not_its_advice():
    advice = "Weights only load failed. Re-running `torch.load` with `weights_only` set to `False` will likely succeed"
    docs = "Check the documentation of torch.load to learn more about types accepted by default with weights_only"
    blocked = f"{advice}\n\n\nTrying to load unsupported GLOBAL posix.system whose module posix is blocked.\n\n{docs}"
    assert refusal(blocked) == "unsupported GLOBAL posix.system"
    listed = f"{advice}\n\t(2) Alternatively...\n\tWeightsUnpickler error: Unsupported global: GLOBAL a.B was not..."
    assert refusal(listed) == "unsupported GLOBAL a.B"
    assert (
        refusal(f"{advice}\n\tWeightsUnpickler error: Unsupported operand 149\n\n{docs}") == "Unsupported operand 149"
    )


def test_numpy_array_fields_load(release, tmp_path):
    fields = {k: v.numpy() for k, v in gaussian_fields(4, seed=7).items()}
    write_pth(release.root / S2F3, fields, nested=True)
    ds = GSQADataset(build(ReleaseConfig(), tmp_path / "out", str(release.root)))
    np.testing.assert_array_equal(ds.scene("scene_0002").frame(1).gaussians()["xyz"], fields["_xyz"])


def test_source_is_required(tmp_path):
    with pytest.raises(DataError, match=r"^source= is required"):
        build(ReleaseConfig(), tmp_path / "out", None)
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), tmp_path / "out", str(tmp_path / "nope"))
    assert str(e.value) == f"source={tmp_path / 'nope'}: no such directory"


def test_split_by_scene_when_file_names_say_nothing(release, tmp_path):
    write_jsonl(release.root / "nuinteract_part1.jsonl", release.records[:3])
    write_jsonl(release.root / "nuinteract_part2.jsonl", release.records[4:])  # q4; q5 left out
    (release.root / "qa_train.jsonl").unlink()
    (release.root / "qa_val.jsonl").unlink()
    ds = GSQADataset(build(ReleaseConfig(val_fraction=0.5), tmp_path / "out", str(release.root)))
    assert {r["sample_id"]: r["split"] for r in ds.qa().to_pylist()} == {
        "q1": "train",
        "q2": "train",
        "q3": "train",
        "q4": "val",
    }


def test_duplicate_sample_uid_names_both_lines(release, tmp_path):
    with open(release.root / "qa_val.jsonl", "a") as f:
        f.write(json.dumps(record("q2", 2, 0, [S2F0], "NuInteract_RD&P", "prediction", "again")) + "\n")
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), tmp_path / "out", str(release.root))
    # In the other split, but not the same record: never taken for the release's repeated examples.
    assert str(e.value) == (
        "qa_val.jsonl:3: sample_uid 'q2' already used at qa_train.jsonl:2 for a different record "
        "(only an unchanged record may repeat, in the other split)"
    )


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("qa_train.jsonl", "qa_train.jsonl:5: sample_uid 'q1' already used at qa_train.jsonl:1"),
        ("qa_train_more.jsonl", "qa_train_more.jsonl:1: sample_uid 'q1' already used at qa_train.jsonl:1"),
        ("nuinteract_extra.jsonl", "qa_train.jsonl:1: sample_uid 'q1' already used at nuinteract_extra.jsonl:1"),
    ],
)
def test_an_unchanged_record_repeated_in_one_split_is_an_error(release, tmp_path, name, message):
    """The same file, another file of the same split, or a file whose split is unknown: never a split overlap."""
    with open(release.root / name, "a") as f:
        f.write(json.dumps(release.records[0], separators=(",", ":")) + "\n")
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(split_overlap="drop_from_train"), root, str(release.root))
    assert str(e.value) == message
    assert_nothing_published(root)


def test_missing_and_conflicting_gauss_paths(release, tmp_path):
    bad = [record("gone", 0, 0, ["gauss/nowhere/00000.pth"], "NuInteract_RD&P", "prediction", "<gauss> ?")]
    write_jsonl(release.root / "qa_val.jsonl", bad)
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), tmp_path / "out", str(release.root))
    assert (
        str(e.value)
        == f"qa_val.jsonl:1 sample 'gone': gauss path gauss/nowhere/00000.pth not found under {release.root}"
    )
    clash = [record("clash", 2, 0, [FRONT1], "NuInteract_RD&P", "prediction", "<gauss> ?")]
    write_jsonl(release.root / "qa_val.jsonl", clash)
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), tmp_path / "out", str(release.root))
    assert str(e.value) == (
        f"{FRONT1}: listed as scene 0 frame 1 at qa_train.jsonl:2 but as scene 2 frame 0 at qa_val.jsonl:1 "
        "(sample 'clash')"
    )


def test_unlisted_file_without_ids_in_its_path(release, tmp_path):
    write_pth(release.root / "gauss" / "misc" / "model.pth", gaussian_fields(2, seed=3))
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), tmp_path / "out", str(release.root))
    assert str(e.value) == (
        "gauss/misc/model.pth: no QA record lists it and its path names no scene/frame "
        "(expected .../scene_<n>/<frame>.pth or .../<n>_<view>/.../<frame>.pth)"
    )


def _outside_pth(tmp_path: Path) -> Path:
    """A valid .pth next to (not inside) the release: what a path trick would smuggle in."""
    secret = tmp_path / "outside" / "secret.pth"
    write_pth(secret, gaussian_fields(2, seed=11))
    return secret.resolve()


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_gauss_paths_leading_out_of_the_source_are_refused(release, tmp_path, how):
    secret = _outside_pth(tmp_path)
    listed = {"dotdot": "../outside/secret.pth", "absolute": str(secret), "symlink": "gauss/scene_0002/link.pth"}[how]
    if how == "symlink":
        (release.root / listed).symlink_to(secret)
    evil = record("evil", 2, 1, [listed], "NuInteract_RD&P", "prediction", "<gauss> ?")
    write_jsonl(release.root / "qa_val.jsonl", [release.records[-1], evil])
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == (
        f"qa_val.jsonl:2 sample 'evil': gauss path {listed} leads outside {release.root.resolve()} (to {secret}); "
        "refusing to read it"
    )
    assert_nothing_published(root)


def test_globbed_files_and_pose_files_leading_out_are_refused(release, tmp_path):
    secret = _outside_pth(tmp_path)
    link = release.root / "gauss" / "scene_0002" / "frame_00009.pth"  # no record lists it: found by gauss_glob
    link.symlink_to(secret)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == (
        f"Gaussian file gauss/scene_0002/frame_00009.pth leads outside {release.root.resolve()} (to {secret}); "
        "refusing to read it"
    )
    assert_nothing_published(root)
    link.unlink()
    for scene in (0, 2):
        (tmp_path / "outside" / f"{scene}.txt").write_text("\n".join([" ".join(map(str, np.eye(4).ravel()))] * 4))
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(pose_dir="../outside"), root, str(release.root))
    assert str(e.value) == (
        f"scene_0000: pose file ../outside/0.txt leads outside {release.root.resolve()} "
        f"(to {tmp_path.resolve() / 'outside' / '0.txt'}); refusing to read it"
    )
    assert_nothing_published(root)


def test_a_qa_file_symlinked_from_outside_is_refused(release, tmp_path):
    (tmp_path / "outside").mkdir()
    outside = tmp_path / "outside" / "qa_more.jsonl"
    write_jsonl(outside, [record("q9", 2, 0, [S2F0], "NuInteract_RD&P", "prediction", "<gauss> more?")])
    (release.root / "qa_more.jsonl").symlink_to(outside)
    root = tmp_path / "out"
    with pytest.raises(DataError) as e:
        build(ReleaseConfig(), root, str(release.root))
    assert str(e.value) == (
        f"record file qa_more.jsonl leads outside {release.root.resolve()} (to {outside.resolve()}); "
        "refusing to read it"
    )
    assert_nothing_published(root)


def test_paths_that_stay_inside_the_source_still_import(release, tmp_path):
    (release.root / "links").mkdir()
    (release.root / "links" / "s2f0.pth").symlink_to(release.root / S2F0)
    inside = [f"gauss/scene_0002/../scene_0002/{Path(S2F0).name}", "links/s2f0.pth"]
    q4 = record("q4", 2, 0, inside, "NuInteract_Planning", "planning_turn_left", "<gauss> Should we turn?")
    write_jsonl(release.root / "qa_val.jsonl", [q4])
    ds = GSQADataset(build(ReleaseConfig(), tmp_path / "out", str(release.root)))
    assert_gaussians(ds.scene("scene_0002").frame(0).gaussians(), expected(release.tensors[S2F0]))
