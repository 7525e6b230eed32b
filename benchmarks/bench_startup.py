"""A toy ``gdwm run`` on an existing dataset, end to end, split by phase: what the platform itself costs.

The toy pipeline (``experiment=toy``: tests/gdwm/stages.py, seven stages with the real DAG's shape, two per-scene
stages over 3 scenes, three training stages, two evaluations) does next to nothing, so nearly every second of the
command is gdwm's own: the interpreter and imports, config composition, the plan (stage modules, code fingerprints,
data verification), Ray's start, the tracking actor and its MLflow store, the launch's runs, the stages' tasks,
actors and in-process training, and the teardown. Each repeat is a new process in a new workdir (a new MLflow
store, an empty cache) on the same dataset, as a user's first run or a test's is.

Phases come from the driver itself (``gdwm.phases``: ``GDWM_PHASES`` names the file it appends them to); "before
main" is from the command's start to ``gdwm.cli.main`` (the interpreter and gdwm.cli's imports), "unaccounted" what
lies between the recorded phases. Per stage, the wall time from its first event to its last (``events.jsonl``).
"""

from __future__ import annotations

import collections
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

from benchmarks.common import Result
from tests.gdwm.toydata import make_dataset

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 10.0
"""The issue's target for the whole command."""


def toy_run(tmp: Path, ds: Path, n: int) -> dict:
    """One ``gdwm run experiment=toy`` in a new workdir: its wall seconds, phases and stage durations."""
    work, phases = tmp / f"w{n}", tmp / f"phases{n}.jsonl"
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith(("GDWM_TEST_", "RAY_"))},
        "PYTHONPATH": str(REPO),
        "GDWM_CONF_PATH": str(REPO / "tests" / "conf"),
        "GDWM_TEST_DIR": str(tmp),
        "GDWM_PHASES": str(phases),
    }
    cmd = [sys.executable, "-m", "gdwm", "run", "experiment=toy", f"workdir={work}", f"data.root={ds}"]
    cmd.append("run.live=false")
    t0 = time.time()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    cpu = TreeCPU(proc.pid)
    stdout, stderr = proc.communicate()
    t1 = time.time()
    cpu.stop()
    r = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    if r.returncode != 0:
        raise RuntimeError(f"toy gdwm run failed (exit {r.returncode}):\n{r.stderr[-3000:]}")
    recorded = [json.loads(line) for line in phases.read_text().splitlines()]
    main = next(p for p in recorded if p["phase"] == "main")
    mine = [p for p in recorded if p["pid"] == main["pid"]]  # the driver's (not a worker's)
    out: dict[str, float] = collections.OrderedDict()
    out["before main (interpreter, imports)"] = main["start"] - t0
    for p in mine:
        if p["end"] > p["start"]:
            out[p["phase"]] = out.get(p["phase"], 0.0) + p["end"] - p["start"]
    ret = next(p for p in mine if p["phase"] == "return")
    out["after main (interpreter exit)"] = t1 - ret["end"]
    out["unaccounted"] = (t1 - t0) - sum(out.values())
    return {"total": t1 - t0, "cpu": cpu.seconds, "processes": len(cpu.last), "phases": out,
            "stages": stage_durations(work)}  # fmt: skip


class TreeCPU:
    """User + system CPU seconds of a process and all its descendants (Ray's processes and workers), sampled every
    0.1 s until ``stop`` (a process' last 0.1 s may be missed): what a run costs a loaded machine, far less
    sensitive to the load than its wall time."""

    def __init__(self, pid: int):
        self.root = psutil.Process(pid)
        self.last: dict[tuple[int, float], float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.1):
            try:
                procs = [self.root, *self.root.children(recursive=True)]
            except psutil.Error:
                return
            for p in procs:
                try:
                    t = p.cpu_times()
                    self.last[(p.pid, p.create_time())] = t.user + t.system
                except psutil.Error:
                    continue

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def seconds(self) -> float:
        return sum(self.last.values())


def stage_durations(work: Path) -> dict[str, float]:
    """Stage -> seconds from its first event to its last in the launch's ``events.jsonl``."""
    (events,) = (work / "logs").glob("*/events.jsonl")
    first: dict[str, float] = {}
    last: dict[str, float] = {}
    for line in events.read_text().splitlines():
        e = json.loads(line)
        if "stage" in e:
            first.setdefault(e["stage"], e["t"])
            last[e["stage"]] = e["t"]
    return {s: last[s] - first[s] for s in first}


def run(quick: bool = False) -> list[Result]:
    repeats = 1 if quick else 3
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="gdwm-bench-startup-") as tmp:
        tmp = Path(tmp)
        ds = make_dataset(tmp / "ds")
        runs = [toy_run(tmp, ds, n) for n in range(repeats)]
    totals = [r["total"] for r in runs]
    med = statistics.median(totals)
    detail = f"{repeats} runs {[f'{t:.1f}' for t in totals]}; load average {load:.1f} on {os.cpu_count()} CPUs"
    out = [Result("startup", "toy gdwm run on an existing dataset, end to end", med, "s", TARGET_S, detail=detail)]
    cpus = [r["cpu"] for r in runs]
    procs = [r["processes"] for r in runs]
    out.append(Result("startup", "  CPU of the command and its Ray processes", statistics.median(cpus), "s",
                      detail=f"user + system, {procs[0]} processes; runs {[f'{c:.1f}' for c in cpus]}"))  # fmt: skip
    for name in runs[0]["phases"]:
        values = [r["phases"].get(name, 0.0) for r in runs]
        out.append(Result("startup", f"  phase: {name}", statistics.median(values), "s"))
    for name in runs[0]["stages"]:
        values = [r["stages"].get(name, 0.0) for r in runs]
        out.append(Result("startup", f"  stage: {name} (first to last event)", statistics.median(values), "s"))
    return out
