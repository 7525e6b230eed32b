"""What dataset.json records so a reader can verify a dataset: every file's sha256/size/mtime and the builder's
content-determining parameters, with the fingerprint computed from them."""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from pipelines.data.gaussiandwm import ReleaseConfig
from pipelines.data.gaussiandwm import build as import_release
from pipelines.data.layout import (
    DataError,
    DatasetWriter,
    content_params,
    fingerprint_of,
    fingerprint_tree,
    image_relpath,
)
from pipelines.data.nuscenes import NuScenesConfig
from pipelines.data.nuscenes import build as convert_nuscenes
from pipelines.data.synth.config import SynthConfig
from tests.pipelines.data.fixtures_nuscenes import write_nuscenes
from tests.pipelines.data.fixtures_release import write_release


def _meta(root: Path) -> dict:
    return json.loads((root / "dataset.json").read_text())


def _old_fingerprint(root: Path) -> str:
    """The formula as gdwm always computed it: pathlib-sorted files, ``relpath \\0 sha256 \\n``."""
    h = hashlib.sha256()
    for p in sorted(p for p in root.rglob("*") if p.is_file() and p.name != "dataset.json"):
        h.update(f"{p.relative_to(root).as_posix()}\0{hashlib.sha256(p.read_bytes()).hexdigest()}\n".encode())
    return h.hexdigest()


def test_files_and_params_are_recorded(tmp_path):
    root = tmp_path / "ds"
    with DatasetWriter(root, name="tiny", source="test", params={"seed": 3, "sizes": (1, 2)}) as w:
        w.add("frames", scene_id="s0", frame_idx=0, timestamp_us=0, token="t0")
        w.write_image(image_relpath("s0", "CAM_FRONT", 0), np.zeros((4, 8, 3), np.uint8))
        w.extra_meta = {"fingerprint": "not this", "note": "kept"}  # a builder's extras cannot clobber the record
    meta = _meta(root)
    on_disk = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    assert sorted(meta["files"]) == [p for p in on_disk if p != "dataset.json"]
    assert len(meta["files"]) == meta["num_files"] == 8  # 7 tables + 1 image
    for rel, rec in meta["files"].items():
        st = os.stat(root / rel)  # stat after the publishing rename: still what was recorded
        assert rec == {
            "sha256": hashlib.sha256((root / rel).read_bytes()).hexdigest(),
            "size": st.st_size,
            "mtime_ns": st.st_mtime_ns,
        }
    assert meta["params"] == {"seed": 3, "sizes": [1, 2]}
    assert meta["note"] == "kept"
    assert meta["fingerprint"] == fingerprint_tree(root)[0] == _old_fingerprint(root)
    assert meta["fingerprint"] == fingerprint_of({rel: rec["sha256"] for rel, rec in meta["files"].items()})
    assert meta["bytes"] == sum(rec["size"] for rec in meta["files"].values())


def test_fingerprint_order_is_by_path_components():
    # "scenes.parquet" vs "scenes/...": pathlib puts the folder's files first, a plain string sort would not
    a = fingerprint_of({"scenes.parquet": "1", "scenes/x.png": "2"})
    h = hashlib.sha256(b"scenes/x.png\x002\nscenes.parquet\x001\n").hexdigest()
    assert a == h


def test_synthetic_builder_records_what_determines_its_bytes(synth_small, synth_small_cfg):
    meta = _meta(synth_small)
    params = meta["params"]
    assert {k: params[k] for k in ("num_scenes", "num_frames", "width", "height", "seed")} == {
        "num_scenes": 2,
        "num_frames": 10,
        "width": 64,
        "height": 36,
        "seed": 0,
    }
    assert params["weathers"] == list(synth_small_cfg.weathers) and "max_depth_m" in params
    assert not {"name", "root", "builder", "summarizer", "needs_source", "num_workers"} & set(params)
    assert meta["fingerprint"] == fingerprint_tree(synth_small)[0] == _old_fingerprint(synth_small)
    # the params as a composed Hydra config would give them
    assert content_params(OmegaConf.structured(synth_small_cfg), SynthConfig, skip=("num_workers",)) == params


def test_importers_record_their_options(tmp_path):
    release = write_release(tmp_path / "release")
    meta = _meta(import_release(ReleaseConfig(), tmp_path / "gd", str(release.root)))
    assert meta["params"]["feature_dim"] == 3 and meta["params"]["task_map"] == ReleaseConfig().task_map
    assert "name" not in meta["params"] and meta["files"]
    nus = write_nuscenes(tmp_path / "nus")
    cfg = OmegaConf.structured(NuScenesConfig(width=32, height=18))  # as `gdwm data convert-nuscenes` passes it
    meta = _meta(convert_nuscenes(cfg, tmp_path / "conv", str(nus.root)))
    assert {k: meta["params"][k] for k in ("version", "width", "height", "lidar")} == {
        "version": "v1.0-mini",
        "width": 32,
        "height": 18,
        "lidar": True,
    }
    assert isinstance(meta["params"]["cameras"], list) and meta["fingerprint"] == fingerprint_tree(tmp_path / "conv")[0]


def _tiny(root: Path, overwrite: bool = False) -> None:
    with DatasetWriter(root, name="tiny", source="test", overwrite=overwrite) as w:
        w.add("frames", scene_id="s0", frame_idx=0, timestamp_us=0, token="t0")


def test_overwrite_replaces_only_a_dataset_gdwm_wrote(tmp_path, capsys):
    """overwrite=true on a user's folder (a thesis, a results folder) is refused, before anything is generated; an
    earlier dataset is replaced, and an empty folder is filled."""
    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / "chapter1.tex").write_text("years of work")
    with pytest.raises(DataError) as e:
        _tiny(thesis, overwrite=True)
    assert str(e.value) == (
        f"{thesis}: not a gdwm dataset (no dataset.json of gdwm's; chapter1.tex is not gdwm's): overwrite=true "
        "replaces only a dataset gdwm built; choose another data.root"
    )
    from gdwm.cli import main

    rc = main(["data", "synth", f"data.root={thesis}", "overwrite=true", "data.num_scenes=1"])
    assert rc == 1 and "not a gdwm dataset" in capsys.readouterr().err
    assert [p.name for p in thesis.iterdir()] == ["chapter1.tex"] and os.listdir(tmp_path) == ["thesis"]
    _tiny(tmp_path / "ds")
    _tiny(tmp_path / "ds", overwrite=True)  # gdwm's own: replaced
    (tmp_path / "empty").mkdir()
    _tiny(tmp_path / "empty")
    assert _meta(tmp_path / "ds")["name"] == _meta(tmp_path / "empty")["name"] == "tiny"


@pytest.mark.parametrize("umask, mode", [(0o022, 0o755), (0o027, 0o750), (0o002, 0o775)])
def test_a_dataset_folder_gets_the_umask_s_mode(tmp_path, umask, mode):
    """Not the temp dir's 0700: another user, or a pod with another UID on a shared data.root, reads it."""
    old = os.umask(umask)
    try:
        _tiny(tmp_path / "ds")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "ds").stat().st_mode) == mode
