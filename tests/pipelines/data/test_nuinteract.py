"""NuInteract's released task files and dense captions on the converted nuScenes fixture: import and refusals."""

from __future__ import annotations

import json
import os
import pickle
import re
from pathlib import Path

import pytest

from pipelines.data.benchmark import summary_counts
from pipelines.data.layout import CAMERAS, DataError
from pipelines.data.nuinteract import CAMERA_QUESTION, SURROUND_QUESTION, NuInteractConfig, build
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_benchmarks import (
    CAPTIONS,
    NUINSTRUCT,
    UNMATCHED,
    nuinteract_record,
    tok,
    write_nuinteract,
)
from tests.pipelines.data.test_nuscenes import assert_nothing_published


@pytest.fixture(scope="module")
def imported(converted, tmp_path_factory) -> GSQADataset:
    src = write_nuinteract(tmp_path_factory.mktemp("src"))
    return GSQADataset(build(NuInteractConfig(nuscenes=str(converted)), tmp_path_factory.mktemp("out") / "n", str(src)))


def _by_id(ds: GSQADataset) -> dict[str, dict]:
    return {json.loads(r["gt"])["id"]: r for r in ds.qa().to_pylist()}


def test_task_records_keep_group_subtask_answer_and_views(imported):
    rows = _by_id(imported)
    g1 = rows["g1"]
    assert (g1["task"], g1["category"], g1["split"]) == ("vg2d", "2D_perception_location", "train")
    assert g1["conversations"][0]["value"] == "<gauss>Where is the car ahead?"  # InternVL's <image> placeholder gone
    assert g1["conversations"][1]["value"] == "<CAM_FRONT> <box>[[420, 380, 610, 520]]</box>"
    assert (g1["scene_token"], g1["frame_idx"], g1["views"]) == ("scene-0001", 0, ["CAM_FRONT"])
    assert rows["p1"]["views"] == ["CAM_FRONT", "CAM_BACK"] and rows["p1"]["task"] == "plan"
    # the test file of region description and 2D grounding: a box makes a record vg2d; no task field: the file's name
    mixed = "2D Region Description Prediction and Visual Grounding"
    assert [(rows[i]["task"], rows[i]["category"], rows[i]["split"]) for i in ("t1", "t2", "t3")] == [
        ("rdp", mixed, "val"), ("vg2d", mixed, "val"), ("vg2d", mixed, "val")
    ]  # fmt: skip
    assert json.loads(rows["tp"]["gt"])["released_split"] == "test"
    assert "tu" not in rows  # its sample is not in the conversion


def test_dense_captions_become_a_record_per_view_and_a_surround_one(imported):
    caps = {k.split("/")[-1]: r for k, r in _by_id(imported).items() if k.startswith("caption/")}
    assert sorted(caps) == ["CAM_BACK", "CAM_FRONT", "FRONT+BACK"]
    g = CAPTIONS[0]["gemini_caption"]
    front = caps["CAM_FRONT"]
    assert front["conversations"] == [
        {"from": "human", "value": "<gauss>" + CAMERA_QUESTION.format(direction="front", camera="CAM_FRONT")},
        {"from": "gpt", "value": g["CAM_FRONT"]},
    ]
    assert caps["FRONT+BACK"]["conversations"][1]["value"] == g["FRONT"] + g["BACK"]
    assert caps["FRONT+BACK"]["conversations"][0]["value"] == "<gauss>" + SURROUND_QUESTION
    assert caps["FRONT+BACK"]["views"] == list(CAMERAS) and caps["CAM_BACK"]["views"] == ["CAM_BACK"]
    # released without a split: their scene's (scene-0001 has only train records)
    assert {(r["task"], r["category"], r["split"], r["frame_idx"]) for r in caps.values()} == {
        ("rdp", "caption", "train", 0)
    }


def test_counts_per_subtask_and_the_unmatched_sample(imported):
    counts = summary_counts(imported.root)
    assert counts[("rdp", "caption", "train")] == 3 and counts[("vg3d", "perception", "val")] == 1
    assert sum(v for (_, _, s), v in counts.items() if s == "val") == 5 and sum(counts.values()) == 14
    b = imported.meta["benchmark"]
    assert (b["records"], b["matched"]) == (15, 14) and b["unmatched"]["named"] == [UNMATCHED]
    assert b["released_splits"] == {"-": "train", "test": "val", "train": "train"}


def test_images_are_linked_not_copied(imported, converted):
    rel = "scenes/scene-0001/images/CAM_FRONT/00000.png"
    assert (imported.root / rel).stat().st_ino == (converted / rel).stat().st_ino
    assert imported.meta["scene_tokens"] == {"scene-0001": "scene-0001", "scene-0002": "scene-0002"}


def _refused(converted: Path, tmp_path: Path, tasks: dict, message: str, captions: list | None = None) -> None:
    src = write_nuinteract(tmp_path / "src", tasks, captions if captions is not None else [])
    (root := tmp_path / "out" / "nuinteract").parent.mkdir(exist_ok=True)
    with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
        build(NuInteractConfig(nuscenes=str(converted)), root, str(src))
    assert_nothing_published(root)


def test_a_record_missing_a_field(converted, tmp_path):
    r = nuinteract_record("x", 1, 0, "Where is the car?", "<box>[[1, 2, 3, 4]]</box>")
    del r["conversations"]
    _refused(converted, tmp_path, {"train/2D Visual Grounding.pkl": [r]},
             "NuInteract/train/2D Visual Grounding.pkl record 0 (id x): field 'conversations' missing")  # fmt: skip


def test_an_answer_without_its_box_or_decision(converted, tmp_path):
    r = nuinteract_record("x", 1, 0, "Where is the car?", "It is ahead, a little to the left.")
    box = "<box>(x1,y1),(x2,y2)</box> or <box>[[x1, y1, x2, y2]]</box>"
    _refused(
        converted,
        tmp_path,
        {"train/2D Visual Grounding.pkl": [r]},
        "NuInteract/train/2D Visual Grounding.pkl record 0 (id x): field 'conversations[1].value' (the answer) has "
        f"no box for 2D visual grounding ({box}): 'It is ahead, a little to the left.'",
    )
    p = nuinteract_record("y", 1, 0, "What should the ego car do?", "Slow down.")
    _refused(
        converted,
        tmp_path / "p",
        {"train/planning.pkl": [p]},
        "NuInteract/train/planning.pkl record 0 (id y): field 'conversations[1].value' (the answer) names none of the "
        "planning decisions ['go straight', 'turn left', 'turn right'] (data.planning_labels): 'Slow down.'",
    )


def test_a_scene_token_of_another_scene(converted, tmp_path):
    r = {**nuinteract_record("z", 1, 0, "Locate it.", "center: (1.0, 2.0, 0.5)"), "scene_token": "scene-0002"}
    _refused(
        converted,
        tmp_path,
        {"train/3D Visual Grounding.pkl": [r]},
        "NuInteract/train/3D Visual Grounding.pkl record 0 (id z): field 'scene_token' is scene-0002 (scene "
        "scene-0002), but sample scene-0001-sample-0 is a frame of scene-0001",
    )


def test_the_same_question_of_a_sample_with_two_answers(converted, tmp_path):
    a = nuinteract_record("a", 1, 1, "What will the car do?", "Keep straight.", "prediction")
    b = nuinteract_record("b", 1, 1, "What will the car do?", "Turn right.", "prediction")
    file = "NuInteract/train/Region Description and Prediction.pkl"
    _refused(
        converted,
        tmp_path,
        {"train/Region Description and Prediction.pkl": [a, b]},
        f"{file} record 1 (id b): field 'conversations[1].value' is 'Turn right.', but {file} record 0 (id a) "
        f"answers the same question of sample {tok(1, 1)} (prediction) with 'Keep straight.'",
    )


def test_a_file_of_another_benchmark(converted, tmp_path):
    _refused(
        converted,
        tmp_path,
        {"test/planning_test.pkl": NUINSTRUCT["annotations/test.json"]},
        "NuInteract/test/planning_test.pkl: a QA file of NuInstruct, not of NuInteract; import it with gdwm data "
        "import-nuinstruct",
    )


def test_an_unknown_task_file_and_a_caption_without_captions(converted, tmp_path):
    _refused(
        converted,
        tmp_path,
        {"train/2D grounding.pkl": []},
        "NuInteract/train/2D grounding.pkl: not one of NuInteract's task files (data.files: ['2D Region Description "
        "Prediction and Visual Grounding', '2D Visual Grounding', '3D Visual Grounding', 'Region Description and "
        "Prediction', 'planning', 'planning_test'])",
    )
    cap = {k: v for k, v in CAPTIONS[0].items() if k != "gemini_caption"}
    _refused(
        converted,
        tmp_path / "c",
        {},
        "all_caption_public/scene-0001.json record 0: field 'gemini_caption' missing",
        captions=[cap],
    )


def test_a_pickle_that_names_code_is_refused(converted, tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    src = write_nuinteract(tmp_path / "src", {}, [])
    path = src / "NuInteract" / "train" / "planning.pkl"
    path.parent.mkdir(parents=True)
    path.write_bytes(pickle.dumps([Evil()]))
    message = "NuInteract/train/planning.pkl: the pickle names posix.system, which is not plain data (lists, dicts, "
    with pytest.raises(
        DataError, match=f"^{re.escape(message)}strings, numbers, numpy arrays\\); refusing to load it$"
    ):
        build(NuInteractConfig(nuscenes=str(converted)), tmp_path / "out", str(src))
