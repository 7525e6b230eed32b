"""NuInstruct's released annotation files on the converted nuScenes fixture: import and every refusal, exactly."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from pipelines.data.benchmark import UNMATCHED_FILE, summary_counts
from pipelines.data.layout import CAMERAS, DataError
from pipelines.data.nuinstruct import NuInstructConfig, build
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_benchmarks import (
    NUINSTRUCT,
    OMNIDRIVE,
    UNMATCHED,
    nuinstruct_record,
    tok,
    write_nuinstruct,
    write_omnidrive,
)
from tests.pipelines.data.test_nuscenes import assert_nothing_published


@pytest.fixture(scope="module")
def imported(converted, tmp_path_factory) -> GSQADataset:
    src = write_nuinstruct(tmp_path_factory.mktemp("src"))
    return GSQADataset(
        build(NuInstructConfig(nuscenes=str(converted)), tmp_path_factory.mktemp("out") / "ni", str(src))
    )


def test_records_attach_to_their_current_sample(imported):
    rows = {json.loads(r["gt"])["id"]: r for r in imported.qa().to_pylist()}
    assert len(rows) == 14  # 7 train + 7 test; the one on an unknown sample is not attached
    r = rows["104"]  # test.json, risk-overtaking on scene-0002's frame 2 (sample_list [frame 1, frame 2])
    assert (r["scene_token"], r["frame_idx"], r["split"]) == ("scene-0002", 2, "val")
    assert (r["task"], r["category"]) == ("risk", "risk-overtaking")
    assert r["conversations"] == [
        {"from": "human", "value": "<gauss>Which objects may overtake the ego car?"},
        {"from": "gpt", "value": NUINSTRUCT["annotations/test.json"][4]["Answer"]},  # as released
    ]
    assert r["views"] == list(CAMERAS) and r["image"][1] == "scenes/scene-0002/images/CAM_FRONT_RIGHT/00002.png"
    assert r["gauss"] == ["scenes/scene-0002/gaussians/00002.arrow"]
    gt = json.loads(r["gt"])
    assert gt == {"benchmark": "NuInstruct", "record": "annotations/test.json record 4 (qa_id 104)", "id": "104",
                  "released_split": "test", "sample_token": tok(2, 2), "scene_token": None}  # fmt: skip
    assert {r["split"] for r in rows.values() if r["scene_token"] == "scene-0001"} == {"train"}


def test_per_subtask_counts_and_unmatched_are_recorded(imported):
    counts = summary_counts(imported.root)
    assert counts[("risk", "risk-overtaking", "train")] == counts[("risk", "risk-overtaking", "val")] == 1
    assert sum(counts.values()) == 14 and len({(t, c) for t, c, _ in counts}) == 7
    b = imported.meta["benchmark"]
    assert (b["records"], b["matched"], b["released_splits"]) == (15, 14, {"test": "val", "train": "train"})
    assert b["unmatched"] == {"records": 1, "sample_tokens": 1, "named": [UNMATCHED], "file": UNMATCHED_FILE}
    assert json.loads((imported.root / UNMATCHED_FILE).read_text()) == {UNMATCHED: 1}
    assert imported.meta["scene_splits"] == {"scene-0001": "train", "scene-0002": "val"}
    assert imported.meta["tables"] == ["boxes2d", "boxes3d", "cameras", "ego_poses", "frames", "images", "lidar", "qa",
                                       "scenes"]  # fmt: skip


def _refused(converted: Path, tmp_path: Path, files: dict, message: str) -> None:
    src = write_nuinstruct(tmp_path / "src", files)
    (root := tmp_path / "out" / "nuinstruct").parent.mkdir(exist_ok=True)
    with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
        build(NuInstructConfig(nuscenes=str(converted)), root, str(src))
    assert_nothing_published(root)


def _train(*records: dict) -> dict:
    return {"annotations/train.json": list(records)}


def test_a_record_missing_a_field(converted, tmp_path):
    r = nuinstruct_record(7, "perception-speed", 1, 1, "How fast is the car?", "4.5")
    del r["Answer"]
    _refused(converted, tmp_path, _train(r), "annotations/train.json record 0 (qa_id 7): field 'Answer' missing")


def test_an_answer_that_does_not_parse_for_its_metric(converted, tmp_path):
    far = nuinstruct_record(8, "perception-distance", 1, 1, "How far is the car?", "quite far")
    _refused(converted, tmp_path, _train(far), "annotations/train.json record 0 (qa_id 8): field 'Answer' does not "
             "parse for perception-distance's metric (a number or an (x, y) vector): 'quite far'")  # fmt: skip
    box = nuinstruct_record(9, "risk-crossing", 1, 1, "Which objects cross?", "<car>[c1,20.0,10.0]")
    _refused(converted, tmp_path, _train(box), "annotations/train.json record 0 (qa_id 9): field 'Answer' does not "
             "parse for risk-crossing's metric (a list of <class>[camera,x1,y1,x2,y2] objects (or none)): "
             "'<car>[c1,20.0,10.0]'")  # fmt: skip


def test_an_unknown_task(converted, tmp_path):
    src = write_nuinstruct(tmp_path / "s", _train(nuinstruct_record(3, "perception-colour", 1, 1, "Colour?", "Grey.")))
    message = "annotations/train.json record 0 (qa_id 3): field 'task' is 'perception-colour', not one of NuInstruct's"
    with pytest.raises(DataError, match=f"^{re.escape(message)} tasks \\(data.subtasks: \\['perception-closest', "):
        build(NuInstructConfig(nuscenes=str(converted)), tmp_path / "o", str(src))


def test_the_same_question_of_a_sample_with_two_answers(converted, tmp_path):
    a = nuinstruct_record(1, "perception-instance_count", 1, 0, "How many cars are around?", "1")
    b = nuinstruct_record(2, "perception-instance_count", 1, 0, "How many cars are around?", "2")
    _refused(converted, tmp_path, _train(a, a, b), "annotations/train.json record 2 (qa_id 2): field 'Answer' is '2', "
             "but annotations/train.json record 0 (qa_id 1) answers the same question of sample scene-0001-sample-0 "
             "(perception-instance_count) with '1'")  # fmt: skip


def test_a_clip_across_two_scenes(converted, tmp_path):
    r = nuinstruct_record(5, "perception-speed", 1, 1, "How fast?", "3")
    r["sample_list"] = [tok(2, 0), tok(1, 1)]
    _refused(converted, tmp_path, _train(r), "annotations/train.json record 0 (qa_id 5): field 'sample_list' names "
             "scene-0002-sample-0, a frame of scene-0002, but its current sample scene-0001-sample-1 is a frame of "
             "scene-0001")  # fmt: skip


def test_a_file_of_another_benchmark(converted, tmp_path):
    src = write_omnidrive(tmp_path / "omni", {k: v for k, v in OMNIDRIVE.items() if k.startswith("desc/train")})
    (root := tmp_path / "out" / "nuinstruct").parent.mkdir()
    rel = sorted(k for k in OMNIDRIVE if k.startswith("desc/train"))[0]
    with pytest.raises(DataError, match=f"^{re.escape(rel)}: a QA file of OmniDrive, not of NuInstruct; import it with "
                                        f"gdwm data import-omnidrive$"):  # fmt: skip
        build(NuInstructConfig(nuscenes=str(converted)), root, str(src))
    assert_nothing_published(root)


def test_no_record_on_the_converted_samples(converted, tmp_path):
    r = {**nuinstruct_record(4, "perception-speed", 1, 1, "How fast?", "3"), "sample_list": [UNMATCHED]}
    _refused(converted, tmp_path, _train(r), f"source={(tmp_path / 'src').resolve()}: none of the 1 NuInstruct records "
             f"names a sample of {converted} (6 frames; unknown: 1 record of 1 sample token: {UNMATCHED}); is "
             "data.nuscenes the conversion of the nuScenes version the benchmark was built on?")  # fmt: skip
