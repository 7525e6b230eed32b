"""Data is verified, not trusted: the dataset's files are checked against dataset.json (a stat each; a file whose
size or mtime differs is re-hashed), and a dataset built with other parameters than requested is refused (exit 2)."""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from omegaconf import OmegaConf

import gdwm.datasets as datasets
from gdwm.cli import main
from gdwm.datasets import DataMismatch, check_dataset, check_params, describe, verification_line, verify_dataset
from pipelines.data.layout import QA_SCHEMA, DatasetWriter, image_relpath
from tests.gdwm.test_run import Toy, _ok
from tests.gdwm.toydata import make_dataset


@pytest.fixture
def hashed(monkeypatch) -> list[str]:
    """The files verify_dataset reads in full."""
    calls: list[str] = []
    real = datasets.file_sha256

    def counting(path):
        calls.append(Path(path).name)
        return real(path)

    monkeypatch.setattr(datasets, "file_sha256", counting)
    return calls


def _meta(root: Path) -> dict:
    return json.loads((root / "dataset.json").read_text())


def edit_scenes_table(root: Path) -> None:
    """Rewrite scenes.parquet in place with one row's description changed."""
    path = root / "scenes.parquet"
    table = pq.read_table(path)
    desc = table.column("description").to_pylist()
    desc[1] = "edited by hand"
    i = table.schema.get_field_index("description")
    pq.write_table(table.set_column(i, "description", pa.array(desc, pa.string())), path)


# ---- verify_dataset ----------------------------------------------------------------------------------------------
def test_untouched_dataset_keeps_its_fingerprint_without_reading_a_file(tmp_path, hashed):
    root = make_dataset(tmp_path / "ds")
    v = verify_dataset(root, _meta(root))
    assert v.fingerprint == _meta(root)["fingerprint"]
    assert hashed == [] and v.changed == [] and v.rehashed == [] and not v.legacy
    assert v.files == 7 and describe(root, _meta(root), v) is None


def test_edited_table_changes_the_fingerprint_and_is_named(tmp_path, hashed):
    root = make_dataset(tmp_path / "ds")
    edit_scenes_table(root)
    v = verify_dataset(root, _meta(root))
    assert v.fingerprint != _meta(root)["fingerprint"]
    assert v.changed == ["scenes.parquet"] and hashed == ["scenes.parquet"]  # only the file whose stat differs
    msg = describe(root, _meta(root), v)
    assert "scenes.parquet changed (re-hashed) since it was written; stages that read the data will re-run" in msg


def test_same_size_edit_is_caught_by_mtime(tmp_path, hashed):
    root = make_dataset(tmp_path / "ds")
    path = root / "frames.parquet"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    st = path.stat()
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # a later write, however fast the clock ticks
    v = verify_dataset(root, _meta(root))
    assert v.changed == ["frames.parquet"] and v.fingerprint != _meta(root)["fingerprint"]


def test_touched_file_is_rehashed_but_not_changed(tmp_path, hashed):
    root = make_dataset(tmp_path / "ds")
    os.utime(root / "qa.parquet", ns=(1, 1))
    v = verify_dataset(root, _meta(root))
    assert v.fingerprint == _meta(root)["fingerprint"]
    assert v.changed == [] and v.rehashed == ["qa.parquet"] == hashed
    assert "same content" in describe(root, _meta(root), v)


def test_added_and_removed_files_count_as_changes(tmp_path, hashed):
    root = make_dataset(tmp_path / "ds")
    fp = _meta(root)["fingerprint"]
    (root / "scenes" / "extra").mkdir(parents=True)
    (root / "scenes" / "extra" / "note.txt").write_text("x")
    v = verify_dataset(root, _meta(root))
    assert v.changed == v.added == ["scenes/extra/note.txt"] and v.fingerprint != fp
    (root / "scenes" / "extra" / "note.txt").unlink()
    (root / "boxes2d.parquet").unlink()
    v = verify_dataset(root, _meta(root))
    assert v.changed == v.removed == ["boxes2d.parquet"] and v.fingerprint != fp
    assert "boxes2d.parquet removed since it was written" in describe(root, _meta(root), v)


def test_dataset_json_without_files_is_hashed_once_and_says_rebuild(tmp_path, hashed):
    root = make_dataset(tmp_path / "ds")
    meta = _meta(root)
    del meta["files"], meta["params"]  # as an older gdwm wrote it
    v = verify_dataset(root, meta)
    assert v.legacy and v.fingerprint == meta["fingerprint"] and len(hashed) == 7
    msg = describe(root, meta, v)
    assert "records no per-file hashes" in msg and "and match its fingerprint" in msg and "rebuild it" in msg
    edit_scenes_table(root)
    v = verify_dataset(root, meta)
    assert v.fingerprint != meta["fingerprint"]
    assert "no longer match: stages that read the data will re-run" in describe(root, meta, v)


def test_check_dataset_warns_once_per_state(tmp_path, hashed, capsys):
    root = make_dataset(tmp_path / "ds")
    data = OmegaConf.create({"name": "toy"})
    edit_scenes_table(root)
    first = check_dataset(data, root, _meta(root))
    assert first["fingerprint"] != first["recorded_fingerprint"] == _meta(root)["fingerprint"]
    again = check_dataset(data, root, _meta(root))  # the next trial of a sweep: same files, nothing read again
    assert again["fingerprint"] == first["fingerprint"] and hashed == ["scenes.parquet"]
    assert capsys.readouterr().err.count("warning: dataset") == 1


# ---- parameters --------------------------------------------------------------------------------------------------
def test_params_must_match_the_request(tmp_path):
    meta = {"params": {"num_scenes": 1, "seed": 0, "weathers": ["clear", "fog"]}}
    data = OmegaConf.create({"name": "synthetic_mini", "needs_source": False, "num_scenes": 1, "seed": 0})
    data.build_command = "gdwm data synth"  # the config names its build command; the message repeats it
    data.weathers = ["clear", "fog"]
    check_params(data, tmp_path, meta)  # lists compare as plain lists
    check_params(data, tmp_path, {})  # nothing recorded (an older dataset): nothing to compare
    data.num_scenes, data.seed = 3, 7
    with pytest.raises(DataMismatch) as e:
        check_params(data, tmp_path, meta)
    assert str(e.value) == (
        f"data.num_scenes: requested 3, but the dataset at {tmp_path} was built with 1; data.seed: requested 7, "
        f"built with 0; use another data.root or rebuild it (gdwm data synth data=synthetic_mini data.num_scenes=3 "
        f"data.seed=7 overwrite=true)"
    )
    with pytest.raises(DataMismatch, match=r"data\.lidar: requested nothing"):
        check_params(data, tmp_path, {"params": {"lidar": True}})  # another builder's dataset


# ---- gdwm run ----------------------------------------------------------------------------------------------------
# the unit tests above show the edit changes the fingerprint, which every stage key holds; this is the real run
def test_edited_table_reruns_the_stages_that_read_the_data(tmp_path):
    toy = Toy(tmp_path)
    _ok(toy.run("targets=[distill]"))
    first = Counter(s for s, _ in toy.executions())
    assert first == {"reconstruct": 3, "distill": 3}
    edit_scenes_table(toy.data)
    (toy.root / "executions.log").write_text("")
    r = toy.run("targets=[distill]")
    _ok(r)
    assert Counter(s for s, _ in toy.executions()) == first  # every key depends on the data's fingerprint
    assert "scenes.parquet changed (re-hashed) since it was written" in r.stderr
    (toy.root / "executions.log").write_text("")
    r = toy.run("targets=[distill]")  # the edited data's fingerprint is stable: cached now, and still warned about
    _ok(r)
    assert toy.executions() == [] and "cached and verified" in r.stdout and "scenes.parquet" in r.stderr


def test_other_generation_params_exit_2_before_anything_runs(tmp_path):
    make_dataset(tmp_path / "ds", params={"num_scenes": 3, "seed": 0})
    toy = Toy(tmp_path)
    r = toy.run("data.num_scenes=1", "data.seed=7")
    assert r.returncode == 2, r.stderr[-3000:]
    assert (
        f"gdwm run: data.num_scenes: requested 1, but the dataset at {toy.data} was built with 3; "
        f"data.seed: requested 7, built with 0" in r.stderr
    )
    assert toy.executions() == [] and not (toy.work / "mlflow.db").exists()
    r = toy.run("data.num_scenes=3", "--dry-run")  # the values it was built with: planned as usual
    _ok(r)


def test_data_info_line(tmp_path):
    root = make_dataset(tmp_path / "ds")
    assert verification_line(root).startswith("verified: 7 files match dataset.json")
    edit_scenes_table(root)
    assert verification_line(root).startswith(f"warning: dataset {root}: scenes.parquet changed (re-hashed)")


# ---- bad data is refused before anything runs ------------------------------------------------------------------
def _with_image_and_qa(root: Path) -> Path:
    """Two scenes, each with one image and one 2D grounding QA whose reference answer holds a box."""
    with DatasetWriter(root, name="toy", source="test") as w:
        for i in range(2):
            sid = f"scene-{i:04d}"
            w.add("scenes", scene_id=sid, name=sid, num_frames=1, frame_rate_hz=2.0, description="", weathers=[],
                  source="test")  # fmt: skip
            w.add("frames", scene_id=sid, frame_idx=0, timestamp_us=0, token=sid)
            w.write_image(image_relpath(sid, "CAM_FRONT", 0), np.full((8, 16, 3), 100 + i, np.uint8))
            turns = [{"from": "human", "value": "Where is the car?"},
                     {"from": "gpt", "value": "<CAM_FRONT> <box>(1,2),(5,6)</box>"}]  # fmt: skip
            w.add("qa", sample_id=f"s{i}", scene_token=sid, frame_idx=0, task="vg2d", category="2D_visual_grounding",
                  conversations=turns, image=[], views=[], gauss=[], split="val", gt="{}")  # fmt: skip
    return root


def _dry_run(root: Path, tmp_path: Path, monkeypatch, capsys) -> tuple[int, str]:
    monkeypatch.setenv("GDWM_CONF_PATH", str(Path(__file__).parents[1] / "conf"))
    rc = main(["run", "--dry-run", "experiment=toy", f"data.root={root}", f"workdir={tmp_path / 'w'}"])
    return rc, " ".join(capsys.readouterr().err.split())


def test_a_scene_listed_but_missing_is_refused_naming_the_file(tmp_path, monkeypatch, capsys):
    root = _with_image_and_qa(tmp_path / "ds")
    shutil.rmtree(root / "scenes" / "scene-0001")  # still listed in scenes.parquet and dataset.json
    rc, err = _dry_run(root, tmp_path, monkeypatch, capsys)
    assert rc == 2 and err == (
        f"gdwm run: dataset {root}: scenes/scene-0001/images/CAM_FRONT/00000.png is listed in dataset.json but missing "
        "(1 file missing): the dataset is incomplete; rebuild it (gdwm data synth data=synthetic_mini overwrite=true)"
    )


@pytest.mark.parametrize("bad", ["truncated image", "nan box", "inf box", "negative box"])
def test_bad_data_is_refused_before_compute_naming_the_file(tmp_path, monkeypatch, capsys, bad):
    root = _with_image_and_qa(tmp_path / "ds")
    image = root / image_relpath("scene-0001", "CAM_FRONT", 0)
    if bad == "truncated image":
        image.write_bytes(image.read_bytes()[:40])
        why = f"{image.relative_to(root)}: unreadable image (OpenCV cannot decode it)"
    else:
        box = {"nan box": "(nan,2),(5,6)", "inf box": "(1,2),(inf,6)", "negative box": "(-3,2),(5,6)"}[bad]
        table = pq.read_table(root / "qa.parquet").to_pylist()
        table[1]["conversations"][1]["value"] = f"<CAM_FRONT> <box>{box}</box>"
        pq.write_table(pa.Table.from_pylist(table, schema=QA_SCHEMA), root / "qa.parquet")
        kind = "negative" if bad == "negative box" else "not finite"
        why = f"qa.parquet: sample s1: the reference box {box} is {kind}"
    rc, err = _dry_run(root, tmp_path, monkeypatch, capsys)
    assert rc == 2 and err.startswith(f"gdwm run: dataset {root}: {why}"), err
