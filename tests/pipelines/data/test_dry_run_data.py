"""A dry run generates nothing: it plans with the scenes the builder would write (``data.planner``); bad
``data.*`` keys exit 2 before anything is generated; SIGTERM during generation leaves no temp directory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pyarrow.parquet as pq
import pytest

from pipelines.data.synth.config import SynthConfig, planned_scenes
from tests.pipelines.conftest import REPO


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=600)


def test_planned_scenes_are_the_scenes_build_writes(synth_small, synth_small_cfg):
    built = pq.read_table(synth_small / "scenes.parquet").column("scene_id").to_pylist()
    assert planned_scenes(synth_small_cfg) == built == ["scene-0000", "scene-0001"]


def test_dry_run_on_an_absent_dataset_plans_without_generating(tmp_path):
    work = tmp_path / "w"
    r = _gdwm("run", "--dry-run", f"workdir={work}", "data.num_scenes=40", "targets=[distill]")
    assert r.returncode == 0, r.stderr[-3000:]
    out = " ".join(r.stdout.split())
    assert f"would generate synthetic_mini (40 scenes) at {work}/data/synthetic_mini" in out
    assert "reconstruct │ 40 scenes │ to run 40" in out and "distill │ 40 scenes │ to run 40" in out
    assert "0 cached, 80 to run" in out
    assert not work.exists()  # nothing written: no dataset, no temp directory, no store


@pytest.mark.parametrize("flag", ["--dry-run", None])
def test_num_scenes_below_one_exits_2_naming_the_key(tmp_path, flag):
    work = tmp_path / "w"
    r = _gdwm("run", *([flag] if flag else []), f"workdir={work}", "data.num_scenes=0")
    assert r.returncode == 2
    assert "invalid value for 'data.num_scenes': 0 (must be >= 1)" in r.stderr  # the schema's range (gdwm.knobs)
    assert "Traceback" not in r.stderr and not work.exists()


def test_planner_checks_the_same_keys_as_the_builder():
    with pytest.raises(ValueError, match=r"data.width must be >= 16 pixels, got 8"):
        planned_scenes(SynthConfig(width=8))


def test_sigterm_during_generation_leaves_no_temp_directory(tmp_path):
    work = tmp_path / "w"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    args = ["data", "synth", f"workdir={work}", "data.num_scenes=400", "data.num_workers=1"]
    proc = subprocess.Popen([sys.executable, "-m", "gdwm", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    data = work / "data"
    deadline = time.time() + 120
    while not (data.exists() and any(p.name.startswith(".synthetic_mini.tmp-") for p in data.iterdir())):
        assert proc.poll() is None and time.time() < deadline, proc.communicate()[1][-2000:]
        time.sleep(0.2)
    time.sleep(1.0)  # a few scenes written into the temp directory
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    assert "gdwm data synth: terminated (SIGTERM); temp directories removed, runs ended" in err
    assert list(data.iterdir()) == []
