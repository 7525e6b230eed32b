"""Every failure is one line without GDWM_DEBUG: Ray's wrapped errors, a dead tracking actor, a config group set to
null, a disk that fills mid-run (its runs ended by the next run)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
import uuid
from collections import Counter
from pathlib import Path

import pytest
import ray

from gdwm.errors import one_line
from gdwm.tracking import open_tracking
from gdwm.tracking.backend import TrackingError
from tests.gdwm.test_run import Toy

pytestmark = pytest.mark.heavy(1.5)


@ray.remote
def _fails():
    raise KeyError("scene-0007")


@ray.remote
class _Broken:
    def __init__(self):
        raise FileNotFoundError(2, "No such file or directory", "/nope/x")

    def ready(self):
        return 1


def test_ray_errors_become_the_original_error_and_where(ray_local):
    with pytest.raises(ray.exceptions.RayTaskError) as task:
        ray.get(_fails.remote())
    assert one_line(task.value) == "KeyError: 'scene-0007' (in Ray task _fails)"
    with pytest.raises(ray.exceptions.ActorDiedError) as actor:
        ray.get(_Broken.remote().ready.remote())
    assert one_line(actor.value) == (
        "Ray task _Broken.__init__ failed to start: FileNotFoundError: [Errno 2] No such file or directory: '/nope/x'"
    )
    multi = ValueError("first line\nsecond line")
    multi.gdwm_hint = "runs ended"
    assert one_line(multi) == "ValueError: first line; runs ended"


def test_a_tracking_actor_that_cannot_start_is_one_line_naming_the_store(ray_local):
    class Cfg:
        uri = "sqlite:////proc/nope/mlflow.db"
        experiment = "gdwm"
        artifact_location = None
        single_writer = True

    with pytest.raises(TrackingError) as e:
        open_tracking(Cfg())
    assert str(e.value) == (
        "tracking.uri=sqlite:////proc/nope/mlflow.db: the tracking actor (TrackingBackend.__init__) failed to start: "
        "FileNotFoundError: [Errno 2] No such file or directory: '/proc/nope'"
    )


def test_a_config_group_set_to_null_is_exit_2_naming_it(tmp_path):
    r = subprocess.run([sys.executable, "-m", "gdwm", "run", "cluster=null", f"workdir={tmp_path}"],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 2
    want = "gdwm: config error: cluster=null: cluster is a config group; choose one of a100x16, local, sim"
    assert r.stderr.strip() == want


def test_a_store_that_cannot_be_opened_is_one_line_exit_1(tmp_path):
    toy = Toy(tmp_path)
    r = toy.run("tracking.uri=sqlite:////proc/nope/mlflow.db")
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("gdwm")]
    assert lines == [
        "gdwm run: TrackingError: tracking.uri=sqlite:////proc/nope/mlflow.db: the tracking actor "
        "(TrackingBackend.__init__) failed to start: "
        "FileNotFoundError: [Errno 2] No such file or directory: '/proc/nope'"
    ]
    assert "Traceback" not in r.stderr


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MiB tmpfs (root and mount(8) needed: skipped elsewhere, CI included)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if (
        shutil.which("mount") is None
        or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mnt)], capture_output=True).returncode
    ):
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_a_disk_that_fills_mid_run(small_disk, tmp_path):
    toy = Toy(tmp_path / "t")
    toy.work = small_disk / "w"
    hog = small_disk / f"hog-{uuid.uuid4().hex[:6]}"
    r = toy.run(GDWM_TEST_FILL=f"evaluate_qa:{hog}")
    assert r.returncode == 1
    err = [ln for ln in r.stderr.splitlines() if not ln.startswith(("20", "(", " "))]
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert err[0].startswith("gdwm run: TrackingError: tracking store write failed: ")
    assert "database or disk is full" in err[0] or "No space left on device" in err[0]
    assert err[0].endswith("its runs stay RUNNING until the next gdwm run or sweep on this store ends them")
    hog.unlink()  # space again: the next run ends what was left RUNNING, then finishes the work
    (toy.root / "executions.log").write_text("")
    r = toy.run()
    assert r.returncode == 0, r.stderr[-3000:]
    statuses = Counter(x.info.status for x in toy.runs() + toy.runs("run"))
    assert "RUNNING" not in statuses and statuses["FINISHED"] >= 7
    # only what the full disk left undone runs again: evaluate_qa and what had not finished beside it (diffusion
    # runs beside lora and evaluate_qa, so whether it finished before the disk filled is the scheduler's choice)
    again = {line.split()[0] for line in (toy.root / "executions.log").read_text().splitlines()}
    assert "evaluate_qa" in again and again <= {"evaluate_qa", "diffusion", "evaluate_gen"}, again


def test_a_scene_filling_the_node_s_memory_ends_the_run_with_one_line_naming_stage_and_scene(tmp_path):
    """Ray's OOM killer ends the worker of reconstruct's scene-0001 (the threshold set just above what the machine
    uses now): the run exits 1 at once (no minutes of Ray's retries) with one line naming stage and scene."""
    import psutil

    toy = Toy(tmp_path)
    vm = psutil.virtual_memory()
    threshold = min(0.95, (vm.total - vm.available + 6e9) / vm.total)  # 3 GB above the machine's use now
    env = {"GDWM_TEST_HOG": "reconstruct:scene-0001", "RAY_memory_usage_threshold": f"{threshold:.3f}",
           "RAY_memory_monitor_refresh_ms": "100"}  # fmt: skip
    t0 = time.monotonic()
    r = toy.run("targets=[reconstruct]", "run.live=false", **env)
    took = time.monotonic() - t0
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 1, r.stderr[-3000:]
    m = re.fullmatch(
        r"gdwm run: stage 'reconstruct' scene\(s\) \['scene-0001'\] failed: out of memory: Ray's OOM killer ended the "
        r"worker \(it held [\d.]+GB\), the node's memory being [\d.]+GB used / [\d.]+GB limit; give the stage more "
        r"memory or fewer parallel workers \(cluster.resources\); traceback: (\S+)",
        last,
    )
    assert m, last
    assert "OutOfMemoryError" in Path(m[1]).read_text()  # Ray's whole report is in the named file
    assert "Top 10 memory users" not in r.stdout + r.stderr and took < 240
