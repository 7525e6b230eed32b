"""OmniDrive-nuScenes' released desc/conv/vqa files on the converted nuScenes fixture: import and refusals."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from pipelines.data.benchmark import summary_counts
from pipelines.data.layout import CAMERAS, DataError
from pipelines.data.omnidrive import QUESTION, OmniDriveConfig, build
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_benchmarks import NUINSTRUCT, OMNIDRIVE, UNMATCHED, tok, write_omnidrive
from tests.pipelines.data.test_nuscenes import assert_nothing_published


@pytest.fixture(scope="module")
def imported(converted, tmp_path_factory) -> GSQADataset:
    src = write_omnidrive(tmp_path_factory.mktemp("src"))
    return GSQADataset(build(OmniDriveConfig(nuscenes=str(converted)), tmp_path_factory.mktemp("out") / "o", str(src)))


def test_descriptions_dialogue_and_vqa_by_sample_and_folder_split(imported):
    rows = {json.loads(r["gt"])["record"]: r for r in imported.qa().to_pylist()}
    desc = rows[f"desc/val/{tok(2, 0)}.json record 0"]
    assert (desc["task"], desc["category"], desc["split"]) == ("desc", "scene_description", "val")
    assert desc["conversations"] == [
        {"from": "human", "value": "<gauss>" + QUESTION},
        {"from": "gpt", "value": OMNIDRIVE[f"desc/val/{tok(2, 0)}.json"]["description"]},
    ]
    assert (desc["scene_token"], desc["frame_idx"], desc["views"]) == ("scene-0002", 0, list(CAMERAS))
    conv = rows[f"conv/train/{tok(1, 0)}.json record 1"]
    assert conv["conversations"][1]["value"] == "Yes, a grey car drives ahead in the same lane."
    assert (conv["task"], conv["category"], conv["split"]) == ("conv", "general_dialogue", "train")
    assert summary_counts(imported.root) == {
        ("desc", "scene_description", "train"): 2,
        ("conv", "general_dialogue", "train"): 2,
        ("vqa", "vqa", "train"): 1,
        ("desc", "scene_description", "val"): 1,
        ("conv", "general_dialogue", "val"): 1,
    }
    assert imported.meta["benchmark"]["unmatched"]["named"] == [UNMATCHED]


def _refused(converted: Path, tmp_path: Path, files: dict, message: str) -> None:
    src = write_omnidrive(tmp_path / "src", files)
    (root := tmp_path / "out" / "omnidrive").parent.mkdir(exist_ok=True)
    with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
        build(OmniDriveConfig(nuscenes=str(converted)), root, str(src))
    assert_nothing_published(root)


def test_a_pair_missing_its_answer_and_a_description_missing(converted, tmp_path):
    conv = f"conv/train/{tok(1, 0)}.json"
    _refused(converted, tmp_path, {conv: [{"question": "Is it raining?", "answer": "Yes."}, {"question": "Why?"}]},
             f"{conv} record 1: field 'answer' missing")  # fmt: skip
    desc = f"desc/train/{tok(1, 0)}.json"
    _refused(
        converted, tmp_path / "d", {desc: {"action": "Keep lane."}}, f"{desc} record 0: field 'description' missing"
    )


def test_a_sample_described_twice_differently(converted, tmp_path):
    files = {f"desc/train/{tok(1, 0)}.json": {"description": "A wet road."},
             f"desc/val/{tok(1, 0)}.json": {"description": "A dry road."}}  # fmt: skip
    _refused(converted, tmp_path, files, f"desc/val/{tok(1, 0)}.json record 0: field 'description' is 'A dry road.', "
             f"but desc/train/{tok(1, 0)}.json record 0 answers the same question of sample {tok(1, 0)} "
             "(scene_description) with 'A wet road.'")  # fmt: skip


def test_a_file_of_another_benchmark(converted, tmp_path):
    files = {f"conv/val/{tok(2, 1)}.json": NUINSTRUCT["annotations/test.json"]}
    _refused(converted, tmp_path, files, f"conv/val/{tok(2, 1)}.json: a QA file of NuInstruct, not of OmniDrive; "
             "import it with gdwm data import-nuinstruct")  # fmt: skip


def test_an_unknown_part(converted, tmp_path):
    with pytest.raises(DataError, match=r"^data.parts: unknown part\(s\) \['keywords'\] \(OmniDrive's: \['desc', "
                                        r"'conv', 'vqa'\]\)$"):  # fmt: skip
        build(OmniDriveConfig(nuscenes=str(converted), parts=["desc", "keywords"]), tmp_path / "o", str(tmp_path))
