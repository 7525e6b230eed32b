"""What the three benchmark importers share (pipelines.data.benchmark): telling files apart, the converted dataset
they attach to, and the `gdwm data` commands a user runs."""

from __future__ import annotations

import json
import logging
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pipelines.data.benchmark import cameras_in, foreign, question_text, released_split_in, render
from pipelines.data.layout import DataError
from pipelines.data.nuinstruct import NuInstructConfig
from pipelines.data.nuinstruct import build as build_nuinstruct
from pipelines.data.nuinteract import NuInteractConfig
from pipelines.data.nuinteract import build as build_nuinteract
from pipelines.data.nuscenes import NuScenesConfig
from pipelines.data.nuscenes import build as convert
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_benchmarks import (
    CAPTIONS,
    NUINSTRUCT,
    NUINTERACT_TASKS,
    OMNIDRIVE,
    UNMATCHED,
    nuinstruct_record,
    write_nuinstruct,
    write_nuinteract,
)
from tests.pipelines.data.fixtures_nuscenes import write_nuscenes


@pytest.fixture(scope="module")
def nus(tmp_path_factory):
    return write_nuscenes(tmp_path_factory.mktemp("nus"))


@pytest.fixture(scope="module")
def front_only(nus, tmp_path_factory) -> Path:
    """A conversion of the fixture's CAM_FRONT alone."""
    cfg = NuScenesConfig(width=32, height=18, cameras=["CAM_FRONT"])
    return convert(cfg, tmp_path_factory.mktemp("conv") / "nuscenes", str(nus.root))


def test_files_are_told_apart_by_their_fields():
    assert foreign(NUINSTRUCT["annotations/train.json"]) == "NuInstruct"
    assert foreign(NUINTERACT_TASKS["train/planning.pkl"]) == foreign(CAPTIONS) == "NuInteract"
    assert {foreign(v) for v in OMNIDRIVE.values()} == {"OmniDrive"}
    assert foreign([]) is None and foreign({"major_task": "qa"}) is None


def test_splits_cameras_and_questions():
    assert released_split_in("NuInteract/test/planning_test.pkl") == "test"
    assert released_split_in("annotations/NuInstruct_train.json") == "train"
    assert released_split_in("annotations/all.json") is None
    assert cameras_in(["samples/CAM_BACK/x.jpg", "<CAM_FRONT_LEFT>", "samples/CAM_FRONT_LEFT/y.jpg"]) == [
        "CAM_BACK",
        "CAM_FRONT_LEFT",
    ]  # in the rig's order, each once; CAM_FRONT is not read out of CAM_FRONT_LEFT
    assert question_text("<image>\n<image>\nWhere is it?") == "<gauss>Where is it?"
    assert question_text("<gauss>Where is it?") == "<gauss>Where is it?"


def test_views_the_conversion_left_out_are_not_read(front_only, tmp_path):
    src = write_nuinstruct(tmp_path / "src")
    ds = GSQADataset(build_nuinstruct(NuInstructConfig(nuscenes=str(front_only)), tmp_path / "ni", str(src)))
    assert {tuple(v) for v in ds.qa().column("views").to_pylist()} == {("CAM_FRONT",)}
    assert ds.cameras == ["CAM_FRONT"] and ds.qa().num_rows == 14
    # NuInteract's CAM_BACK caption reads a camera the conversion left out: counted, not attached
    src = write_nuinteract(tmp_path / "nsrc")
    ds = GSQADataset(build_nuinteract(NuInteractConfig(nuscenes=str(front_only)), tmp_path / "nn", str(src)))
    assert ds.meta["benchmark"]["views_not_converted"] == 1 and ds.qa().num_rows == 13
    lines = [str(p) for p in render(ds.root) if isinstance(p, str)]
    assert "not attached: 1 record reading only cameras the conversion left out (CAM_FRONT_RIGHT, CAM_BACK_RIGHT, " \
           "CAM_BACK, CAM_BACK_LEFT, CAM_FRONT_LEFT)" in lines  # fmt: skip


def test_the_dataset_attached_to_must_be_a_conversion(front_only, tmp_path):
    src = write_nuinstruct(tmp_path / "src")
    missing = (
        "data.nuscenes=/nowhere: no converted nuScenes dataset there (convert one first: gdwm data convert-nuscenes"
    )
    with pytest.raises(DataError, match=f"^{re.escape(missing)} source=DIR, or point data.nuscenes at it\\)$"):
        build_nuinstruct(NuInstructConfig(nuscenes="/nowhere"), tmp_path / "a", str(src))
    first = build_nuinstruct(NuInstructConfig(nuscenes=str(front_only)), tmp_path / "ni", str(src))
    with pytest.raises(DataError, match=f"^data.nuscenes={re.escape(str(first))}: dataset 'nuinstruct' already holds "
                                        f"NuInstruct's QA; attach to the converted nuScenes dataset it was built on "
                                        f"\\({re.escape(str(front_only))}\\)$"):  # fmt: skip
        build_nuinstruct(NuInstructConfig(nuscenes=str(first)), tmp_path / "b", str(src))


def test_an_old_conversion_without_scene_tokens_is_matched_by_sample(front_only, tmp_path, caplog):
    old = tmp_path / "old"
    old.mkdir()
    for p in front_only.iterdir():  # the same dataset, as the converter wrote it before it recorded scene tokens
        (old / p.name).symlink_to(p)
    (old / "dataset.json").unlink()
    meta = json.loads((front_only / "dataset.json").read_text())
    del meta["scene_tokens"]
    (old / "dataset.json").write_text(json.dumps(meta))
    src = write_nuinstruct(tmp_path / "src", {"annotations/train.json": NUINSTRUCT["annotations/train.json"]})
    with caplog.at_level(logging.WARNING, logger="pipelines.data.benchmark"):
        ds = GSQADataset(build_nuinstruct(NuInstructConfig(nuscenes=str(old)), tmp_path / "ni", str(src)))
    assert ds.qa().num_rows == 7
    assert (
        f"{old} was converted before scene tokens were recorded: records' scene tokens are not checked" in caplog.text
    )


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=300)


def test_import_and_info_on_the_command_line(front_only, tmp_path):
    """`gdwm data import-nuinstruct` then `gdwm data info`: the QA per subtask and split, and the unmatched sample;
    a refused file is one line on stderr, exit 1, nothing published."""
    src = write_nuinstruct(tmp_path / "src")
    work = tmp_path / "w"
    r = _gdwm("data", "import-nuinstruct", f"source={src}", f"workdir={work}", f"data.nuscenes={front_only}")
    assert r.returncode == 0, r.stderr
    info = _gdwm("data", "info", "data=nuinstruct", f"workdir={work}")
    assert info.returncode == 0, info.stderr
    out = " ".join(info.stdout.split())
    for task, subtask in [("perception", "perception-distance"), ("risk", "risk-overtaking"), ("risk", "risk-non")]:
        assert f"│ {task} │ {subtask} │ 1 │ 1 │" in out
    assert "NuInstruct: 14 of 15 records on frames of" in out
    assert f"unmatched: 1 record of 1 sample token not in the converted dataset, left out: {UNMATCHED}" in out
    assert "(released splits: test -> val, train -> train; exact repeats dropped: 0)" in out

    bad = nuinstruct_record(3, "perception-distance", 1, 1, "How far?", "(10.0, 1.0)")
    del bad["sample_list"]
    write_nuinstruct(tmp_path / "bad", {"annotations/val.json": [bad]})
    r = _gdwm("data", "import-nuinstruct", f"source={tmp_path / 'bad'}", f"workdir={tmp_path / 'w2'}",
              f"data.nuscenes={front_only}")  # fmt: skip
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        "gdwm data import-nuinstruct: DataError: annotations/val.json record 0 (qa_id 3): field 'sample_list' missing"
    ]
    assert not (tmp_path / "w2" / "data").exists() or not any((tmp_path / "w2" / "data").iterdir())
