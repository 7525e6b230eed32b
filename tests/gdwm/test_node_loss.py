"""Losing a worker node of ``cluster=sim`` mid-sweep or mid-stage: the launch finishes, training resumes from its
last checkpoint on shared storage (the workdir), a per-scene stage's scenes rerun on the surviving node, and MLflow
and the cache hold each stage once.

The node is lost the way a machine is: every process of it (its raylet and the workers under it) gets SIGKILL.
Which processes those are comes from the cluster's state file (``<workdir>/sim-cluster/<pid>.json``) and the
process tree; the node chosen is the one that hosts the training group blocked after its step-1 checkpoint, or a
scene actor blocked inside a scene (``GDWM_TEST_BLOCK``, tests/gdwm/stages.py).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from gdwm.cache import Cache
from tests.gdwm.test_run import Toy

pytestmark = pytest.mark.heavy(3)


def _children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (from /proc)."""
    parents: dict[int, list[int]] = {}
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                ppid = int((p / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            parents.setdefault(ppid, []).append(int(p.name))
    out, todo = [], [pid]
    while todo:
        kids = parents.get(todo.pop(), [])
        out += kids
        todo += kids
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"driver exited {proc.returncode} before {path.name}\n{out[-3000:]}\n{err[-3000:]}")
        assert time.monotonic() < end, f"no {path.name} after {timeout} s"
        time.sleep(0.2)


@pytest.mark.timeout(1200)
def test_losing_the_training_node_mid_sweep_resumes_from_the_last_checkpoint_and_finishes(tmp_path):
    toy = Toy(tmp_path)
    args = [sys.executable, "-m", "gdwm", "sweep", "sweep=toy_ablation", f"workdir={toy.work}", f"data.root={toy.data}",
            "cluster=sim", "run.live=false"]  # fmt: skip
    proc = subprocess.Popen(args, env=toy.env(GDWM_TEST_BLOCK="tokenizer:step=1"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        _wait_for(tmp_path / "blocked-tokenizer", proc, 420)
        (state_file,) = (toy.work / "sim-cluster").glob("*.json")
        state = json.loads(state_file.read_text())
        hosts = [n for n in state["nodes"] if any("RayTrainWorker" in _cmdline(c) for c in _children(n["raylet_pid"]))]
        assert len(hosts) == 1, hosts  # the group of 2 (1 GPU each) packs onto one 2-GPU node
        lost = hosts[0]
        for pid in [*_children(lost["raylet_pid"]), *lost["pids"]]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        killed_at = time.monotonic()
        (tmp_path / "release").touch()
        out, err = proc.communicate(timeout=900)
        recovered_s = time.monotonic() - killed_at
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, f"exit {proc.returncode}\n{out[-3000:]}\n{err[-5000:]}"
    print(f"node {lost['name']} lost at tokenizer step 1; the sweep finished {recovered_s:.1f} s later")
    assert "sweep: 3 trials, 9 stage executions run (15 as independent runs without a cache)" in out

    # the training resumed at step 2 from the step-1 checkpoint: steps 0..3 logged once each
    runs = toy.runs()
    assert Counter(r.data.tags["gdwm.stage"] for r in runs) == {
        "reconstruct": 1, "distill": 1, "tokenizer": 1, "lora": 3, "evaluate_qa": 3,
    }  # fmt: skip
    tok = next(r for r in runs if r.data.tags["gdwm.stage"] == "tokenizer")
    client = toy.client()
    assert sorted(m.step for m in client.get_metric_history(tok.info.run_id, "loss")) == [0, 1, 2, 3]
    starts = {m.step: m.value for m in client.get_metric_history(tok.info.run_id, "start")}
    assert starts == {0: 0.0, 1: 0.0, 2: 2.0, 3: 2.0}
    # nothing duplicated, nothing left RUNNING; the rows' numbers are the undisturbed sweep's
    everything = runs + toy.runs("trial") + toy.runs("row") + toy.runs("sweep")
    assert {r.info.status for r in everything} == {"FINISHED"}
    assert [len(toy.runs(k)) for k in ("sweep", "row", "trial")] == [1, 3, 3]
    acc = {r.data.tags["gdwm.row"]: r.data.metrics["acc"] for r in toy.runs("trial")}
    assert acc == {"rank 2": 24.0, "rank 4": 48.0, "rank 8": 96.0}
    cache = Cache(toy.work / "cache")
    assert [len(cache.entries(s)) for s in ("reconstruct", "distill", "tokenizer", "lora", "evaluate_qa")] == [
        3, 3, 1, 3, 3,
    ]  # fmt: skip
    (entry,) = cache.entries("tokenizer")
    # 3 scenes x 64 x 4 features -> target 768 % 5 = 3 per step, 4 steps
    w = np.load(cache.materialize(entry) / "weights.npy")
    assert w.dtype == np.float32 and w.tolist() == [12.0] * 4
    steps = toy.work / "checkpoints" / "tokenizer" / entry.key / "steps"
    assert sorted(p.name for p in steps.iterdir()) == [f"step_{i:09d}" for i in range(4)]
    assert not list((toy.work / "sim-cluster").glob("*.json"))


def test_losing_a_node_mid_per_scene_stage_reruns_its_scenes_on_the_other_node(tmp_path):
    toy = Toy(tmp_path)
    proc = subprocess.Popen(
        toy.args("targets=[reconstruct]", "cluster=sim", "run.live=false"),
        env=toy.env(GDWM_TEST_BLOCK="reconstruct"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for(tmp_path / "blocked-reconstruct", proc, 300)
        (state_file,) = (toy.work / "sim-cluster").glob("*.json")
        state = json.loads(state_file.read_text())
        # the node whose scene actor is inside a scene now (executions.log names the actor's pid)
        log = (tmp_path / "executions.log").read_text().splitlines()
        began = {int(line.split()[3]): line.split()[1] for line in log}
        lost = next(n for n in state["nodes"] if set(began) & set(_children(n["raylet_pid"])))
        survivor = next(n for n in state["nodes"] if n["name"] != lost["name"])
        interrupted = sorted(s for pid, s in began.items() if pid in _children(lost["raylet_pid"]))
        for pid in [*_children(lost["raylet_pid"]), *lost["pids"]]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        # released at once: Ray's task retries on the dead node are refused before it marks the node dead (health
        # checks every second, 3 misses), so the executor's own resubmission is what brings the scenes back
        (tmp_path / "release").touch()
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, f"exit {proc.returncode}\n{out[-3000:]}\n{err[-5000:]}"

    # every scene done once in the cache and in MLflow; the lost node's scenes ran again, on the survivor
    runs = toy.runs()
    assert [r.data.tags["gdwm.stage"] for r in runs] == ["reconstruct"]
    assert {r.info.status for r in runs + toy.runs("run")} == {"FINISHED"} and len(toy.runs("run")) == 1
    psnr = {k for k in runs[0].data.metrics if k.endswith("/psnr")}
    assert psnr == {"scene-0000/psnr", "scene-0001/psnr", "scene-0002/psnr"}
    client = toy.client()
    assert all(len(client.get_metric_history(runs[0].info.run_id, k)) == 1 for k in psnr)  # none logged twice
    assert len(Cache(toy.work / "cache").entries("reconstruct")) == 3
    ran = [s for stage, s in toy.executions() if stage == "reconstruct"]
    assert sorted(set(ran)) == ["scene-0000", "scene-0001", "scene-0002"]
    assert all(ran.count(s) == 2 for s in interrupted) and len(ran) == 3 + len(interrupted), (interrupted, ran)
    placed = {line for line in out.splitlines() if line.startswith("sim placement: ")}
    (line,) = placed
    assert f"{survivor['name']}: SceneWorker x" in line and f"{lost['name']}: SceneWorker" not in line
