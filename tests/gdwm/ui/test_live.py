"""The dashboard's live state: a snapshot turned back into the progress model and fed the events after it gives what
the driver's own model says; a RUNNING run of a dead driver is stale; an old sweep's grid from its runs' tags."""

from __future__ import annotations

import os
import socket
import time

from gdwm.events import Event
from gdwm.progress import Execution, LaunchProgress
from gdwm.ui.live import STALE_AFTER_S, from_snapshot, grid_from_runs, stale_reason


def _launch(clock) -> LaunchProgress:
    trials = {
        "a": [("reconstruct", "r"), ("train", "t1"), ("eval", "e1")],
        "b": [("reconstruct", "r"), ("train", "t2"), ("eval", "e2")],
    }
    ex = [
        Execution("reconstruct", "r", ["a", "b"], scenes_total=3, estimate_s=30.0),
        Execution("train", "t1", ["a"], estimate_s=20.0),
        Execution("train", "t2", ["b"], estimate_s=20.0),
        Execution("eval", "e1", ["a"], estimate_s=5.0),
        Execution("eval", "e2", ["b"], estimate_s=5.0),
    ]
    return LaunchProgress("sweep", "s", "sweep-s-1", trials, ex, clock)


def test_a_snapshot_fed_the_later_events_agrees_with_the_drivers_model():
    now = [1000.0]
    clock = lambda: now[0]  # noqa: E731
    driver = _launch(clock)
    first = [
        Event("stage", "running", stage="reconstruct", key="r", t=1001.0),
        Event("scene", "done", stage="reconstruct", key="r", scene="scene-0", t=1002.0),
        Event("scene", "done", stage="reconstruct", key="r", scene="scene-1", t=1003.0),
    ]
    later = [
        Event("scene", "done", stage="reconstruct", key="r", scene="scene-2", t=1011.0),
        Event("stage", "done", stage="reconstruct", key="r", t=1012.0),
        Event("stage", "running", stage="train", key="t1", t=1013.0),
        Event("step", stage="train", key="t1", step=5, steps=10, loss=0.5, t=1014.0),
        Event("stage", "failed", stage="train", key="t2", cause="stage 'train' failed: ValueError: x", t=1015.0),
        Event("stage", "blocked", stage="eval", key="e2", t=1015.5),
        Event("trial", "failed", trials=["b"], t=1016.0),
    ]
    for ev in first:
        driver.feed(ev)
    now[0] = 1005.0
    snap = driver.snapshot("logs/x/events.jsonl")
    rebuilt = from_snapshot(snap, clock)
    for ev in later:
        driver.feed(ev)
        rebuilt.feed(ev)
    now[0] = 1020.0
    want, got = driver.snapshot(), rebuilt.snapshot()
    assert (
        got["counts"]
        == want["counts"]
        == {"executions": 5, "executions_finished": 3, "trials": 2, "trials_done": 0, "trials_failed": 1}
    )
    for t in ("a", "b"):
        assert got["trials"][t]["state"] == want["trials"][t]["state"]
        for stage, cell in want["trials"][t]["stages"].items():
            mine = got["trials"][t]["stages"][stage]
            for k in ("state", "key", "step", "steps", "loss", "cause", "scenes_done", "scenes_total"):
                assert mine.get(k) == cell.get(k), (t, stage, k)
    assert got["trials"]["b"]["stages"]["reconstruct"]["state"] == "shared"
    assert got["failures"] == want["failures"]


def test_a_running_run_whose_driver_is_gone_is_stale():
    host = socket.gethostname()
    me = f"{host}:{os.getpid()}:{__import__('psutil').Process().create_time():.2f}"
    run = {"status": "RUNNING", "tags": {"gdwm.owner": me}}
    assert stale_reason(run, None, time.time()) == ""
    run["tags"]["gdwm.owner"] = f"{host}:999999:1.0"
    assert stale_reason(run, None, time.time()) == "its driver (pid 999999 on this host) is gone"
    elsewhere = {"status": "RUNNING", "tags": {"gdwm.owner": "node-7:42:1.0"}}
    assert stale_reason(elsewhere, time.time() - 30, time.time()) == ""  # another host: its snapshot is fresh
    assert stale_reason(elsewhere, time.time() - STALE_AFTER_S - 60, time.time()) == (
        "no news from its driver on node-7 for 4 min 00 s"
    )
    assert stale_reason({"status": "FINISHED", "tags": {}}, None, time.time()) == ""


def test_an_old_sweeps_grid_from_its_runs():
    sweep = {"run_id": "S", "status": "FINISHED", "start_time": 1000, "tags": {"gdwm.sweep": "abl"}}
    stage_runs = {
        "rec": {"start_time": 500, "end_time": 900, "tags": {"gdwm.cache_key": "k-rec"}},  # before the sweep: cached
        "tok": {"start_time": 1100, "end_time": 3100, "tags": {"gdwm.cache_key": "k-tok"}},
        "lora1": {"start_time": 3200, "end_time": 4200, "tags": {}},
    }

    def trial(name, status, **tags):
        return {"run_id": name, "name": f"abl/{name}", "status": status, "tags": tags}

    trials = [
        trial(
            "A",
            "FINISHED",
            **{
                "gdwm.stage_run.reconstruct": "rec",
                "gdwm.stage_run.tokenizer": "tok",
                "gdwm.stage_run.lora": "lora1",
                "gdwm.stage_key.lora": "k-l1",
            },
        ),
        trial(
            "B",
            "FAILED",
            **{
                "gdwm.stage_run.reconstruct": "rec",
                "gdwm.stage_run.tokenizer": "tok",
                "gdwm.failed_stage": "lora",
                "gdwm.error": "ValueError: bad rank\ntraceback...",
            },
        ),
    ]
    grid = grid_from_runs(sweep, trials, stage_runs)
    assert grid["stages"] == ["reconstruct", "tokenizer", "lora"]
    a, b = grid["trials"]["A"]["stages"], grid["trials"]["B"]["stages"]
    assert (a["reconstruct"]["state"], a["tokenizer"]["state"], a["lora"]["state"]) == ("cached", "done", "done")
    assert a["tokenizer"]["duration_s"] == 2.0 and a["lora"]["key"] == "k-l1"
    assert (b["tokenizer"]["state"], b["lora"]["state"], b["lora"]["cause"]) == (
        "shared",
        "failed",
        "ValueError: bad rank",
    )
    assert grid["counts"] == {"trials": 2, "trials_done": 1, "trials_failed": 1}
    assert grid["failures"][0]["trials"] == ["B"]
