"""`gdwm run` end to end through the real CLI on local Ray (2 CPUs, token auth on), with test stages.

Executions are counted from the stages' own log (tests/gdwm/stages.py) and from MLflow stage runs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import mlflow
import pytest

from gdwm.cache import CACHE_KEYS, Cache
from gdwm.tracking.params import full_params
from tests.gdwm.toydata import make_dataset

pytestmark = pytest.mark.heavy(5)

REPO = Path(__file__).resolve().parents[2]
ALL = ["reconstruct", "distill", "tokenizer", "lora", "evaluate_qa", "diffusion", "evaluate_gen"]


class Toy:
    """One workdir + dataset + injection dir; runs the CLI against them."""

    def __init__(self, root: Path):
        self.root = root
        self.data = root / "ds"
        self.work = root / "w"
        if not self.data.exists():
            make_dataset(self.data)

    def env(self, **inject: str) -> dict:
        # RAY_AUTH_MODE too: an in-process ray.init earlier in the session sets it, and the CLI must run as from a
        # user's shell (mode unset, token auth on by default)
        env = {k: v for k, v in os.environ.items() if not k.startswith("GDWM_TEST_") and k != "RAY_AUTH_MODE"}
        env.update(
            PYTHONPATH=str(REPO), GDWM_CONF_PATH=str(REPO / "tests" / "conf"), GDWM_TEST_DIR=str(self.root), **inject
        )
        return env

    def args(self, *overrides: str) -> list[str]:
        base = ["experiment=toy", f"workdir={self.work}", f"data.root={self.data}"]
        return [sys.executable, "-m", "gdwm", "run", *base, *overrides]

    def run(self, *overrides: str, **inject: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            self.args(*overrides), env=self.env(**inject), capture_output=True, text=True, timeout=300
        )

    def executions(self) -> list[tuple[str, str]]:
        log = self.root / "executions.log"
        lines = log.read_text().splitlines() if log.exists() else []
        return [tuple(line.split()[:2]) for line in lines]

    def runs(self, kind: str = "stage") -> list:
        client = mlflow.MlflowClient(f"sqlite:///{self.work.resolve()}/mlflow.db")
        exp = client.get_experiment_by_name("gdwm")
        return [
            r for r in client.search_runs([exp.experiment_id], max_results=1000) if r.data.tags.get("gdwm.kind") == kind
        ]

    def client(self) -> mlflow.MlflowClient:
        return mlflow.MlflowClient(f"sqlite:///{self.work.resolve()}/mlflow.db")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"


def _ok(r: subprocess.CompletedProcess) -> None:
    assert r.returncode == 0, f"exit {r.returncode}\nSTDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"


@pytest.fixture(scope="module")
def first_run(tmp_path_factory) -> Toy:
    toy = Toy(tmp_path_factory.mktemp("first"))
    r = toy.run()
    _ok(r)
    toy.first_stderr = r.stderr
    return toy


def _copy(src: Toy, dst: Path) -> Toy:
    shutil.copytree(src.root, dst, dirs_exist_ok=True, ignore=shutil.ignore_patterns("marker-*"))
    (dst / "executions.log").write_text("")
    return Toy(dst)


def test_first_run_executes_every_stage_once(first_run):
    ex = first_run.executions()
    assert Counter(s for s, _ in ex) == {
        "reconstruct": 3,
        "distill": 3,
        "tokenizer": 1,
        "lora": 1,
        "evaluate_qa": 1,
        "diffusion": 1,
        "evaluate_gen": 1,
    }
    runs = first_run.runs()
    assert sorted(r.data.tags["gdwm.stage"] for r in runs) == sorted(ALL)
    assert {r.info.status for r in runs} == {"FINISHED"}
    parent = first_run.runs("run")
    assert len(parent) == 1 and parent[0].info.status == "FINISHED"
    assert {r.data.tags["mlflow.parentRunId"] for r in runs} == {parent[0].info.run_id}
    # training curves are step-aware; per-scene metrics carry the scene
    tok = next(r for r in runs if r.data.tags["gdwm.stage"] == "tokenizer")
    assert [m.step for m in first_run.client().get_metric_history(tok.info.run_id, "loss")] == [0, 1, 2, 3]
    # per-scene actors load their heavy state once each: 3 scenes on a pool of 2 -> at most 2 setups, not 3 (a scene
    # goes to whichever actor is placed and idle: on a loaded machine the first may take all three)
    assert 1 <= len((first_run.root / "setups.log").read_text().splitlines()) <= 2
    rec = next(r for r in runs if r.data.tags["gdwm.stage"] == "reconstruct")
    assert {"scene-0000/psnr", "scene-0001/psnr", "scene-0002/psnr"} <= set(rec.data.metrics)


def test_runs_with_ray_token_auth_on(first_run):
    from gdwm.events import read_events

    (events,) = (first_run.work / "logs").glob("run-toy-*/events.jsonl")
    start = next(e for e in read_events(events) if e.kind == "launch")
    assert "Ray token authentication on" in start.message
    # on without saying so on every launch: Ray's own notice is not repeated in gdwm's output
    assert "Token authentication is enabled" not in first_run.first_stderr


def test_status_lists_the_runs(first_run):
    r = subprocess.run(
        [sys.executable, "-m", "gdwm", "status", f"workdir={first_run.work}"],
        capture_output=True,
        text=True,
        env=first_run.env(),
        timeout=120,
    )
    _ok(r)
    assert "no sweeps in" in r.stdout
    (row,) = [line for line in r.stdout.splitlines() if "run-toy-" in line]
    assert "│ done " in row and "│ 7 " in row  # its state and how many stages it ran


def test_identical_rerun_is_all_cache_hits(first_run, tmp_path):
    toy = _copy(first_run, tmp_path)
    before = {r.info.run_id for r in toy.runs()}
    r = toy.run()
    _ok(r)
    assert toy.executions() == []
    assert {r.info.run_id for r in toy.runs()} == before
    assert "all 11 stage outputs cached and verified; nothing to run" in r.stdout


def test_seeds_run_one_trial_each_and_share_seed_free_stages(first_run, tmp_path):
    """seeds=[0,1,2] after a seed-0 run: seed 0 is all cache hits, seeds 1 and 2 run only the seeded stages and what
    follows them; seed 2 fails, the run reports it (exit 1) and the row aggregates the two seeds that finished."""
    from tests.gdwm.stages import seed_noise

    toy = _copy(first_run, tmp_path)
    r = toy.run("seeds=[0,1,2]", "targets=[evaluate_qa]", GDWM_TEST_FAIL="lora:seed=2")
    assert r.returncode == 1 and "injected failure in lora:seed=2" in r.stderr
    assert sorted(s for s, _ in toy.executions()) == ["evaluate_qa", "lora", "lora", "tokenizer", "tokenizer"]
    (parent,) = [x for x in toy.runs("run") if x.data.tags.get("gdwm.seeds") == "0,1,2"]
    trials = {x.data.tags["gdwm.seed"]: x for x in toy.runs("trial")}
    assert {k: t.info.status for k, t in trials.items()} == {"0": "FINISHED", "1": "FINISHED", "2": "FAILED"}
    assert {t.data.tags["mlflow.parentRunId"] for t in trials.values()} == {parent.info.run_id}
    assert trials["2"].data.tags["gdwm.failed_stage"] == "lora"
    # the run holds the config as params; a trial's run what differs from it: its seed and the seeds it sets
    for seed in ("1", "2"):
        assert dict(trials[seed].data.params) == {"seed": seed, "model.llm.seed": seed, "model.selector.seed": seed}
    assert full_params(trials["1"].data.params, parent.data.params)["stage.toy_lora.rank"] == "4"
    acc = [12 * (4 + seed_noise(s)) for s in (0, 1)]  # rank 4, 3 steps, 4 dims
    assert parent.data.metrics["acc"] == pytest.approx(sum(acc) / 2) and parent.data.tags["gdwm.n.acc"] == "2"
    assert parent.info.status == "FAILED"
    # its table says how many seeds each cell has
    args = ["compare", f"workdir={toy.work}", f"args.runs=[{parent.info.run_id}]", "args.formats=[markdown]",
            f"args.out={tmp_path / 'report'}"]  # fmt: skip
    c = subprocess.run(
        [sys.executable, "-m", "gdwm", *args], env=toy.env(), capture_output=True, text=True, timeout=300
    )
    _ok(c)
    md = (tmp_path / "report" / "nuinteract.md").read_text()
    assert f"{sum(acc) / 2:.2f} ± {statistics.stdev(acc):.2f} (n=2)" in md and "(n=k): k of 3 seeds finished" in md


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["seeds=[]"], "gdwm run: seeds: no seeds given"),
        (["seeds=[0,1.5]"], "seeds"),
        (["seeds=[0,1]", "seed=3"], "gdwm run: override 'seed=3' sets the trial seed"),
    ],
)
def test_bad_seeds_exit_2(tmp_path, args, message):
    toy = Toy(tmp_path)
    r = toy.run(*args)
    assert r.returncode == 2, r.stderr[-2000:]
    assert message in r.stderr
    assert not (toy.work / "mlflow.db").exists()


def test_lora_change_reruns_lora_and_descendants_only(first_run, tmp_path):
    toy = _copy(first_run, tmp_path)
    _ok(toy.run("stage.toy_lora.rank=8"))
    assert sorted(s for s, _ in toy.executions()) == sorted(["lora", "evaluate_qa", "diffusion", "evaluate_gen"])
    assert Counter(r.data.tags["gdwm.stage"] for r in toy.runs())["lora"] == 2


def test_targets_run_only_ancestors(first_run, tmp_path):
    toy = _copy(first_run, tmp_path)
    _ok(toy.run("stage.toy_lora.rank=16", "targets=[evaluate_qa]"))
    assert sorted(s for s, _ in toy.executions()) == ["evaluate_qa", "lora"]


def test_flipped_byte_is_detected_and_recomputed(first_run, tmp_path):
    toy = _copy(first_run, tmp_path)
    cache = Cache(toy.work / "cache")
    entry = next(m for m in cache.entries("reconstruct") if m.scene == "scene-0001")
    f = Path(cache.materialize(entry)) / "points.npy"
    st = f.stat()
    data = bytearray(f.read_bytes())
    data[-1] ^= 0xFF
    f.write_bytes(bytes(data))
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    _ok(toy.run())
    # only the corrupted scene recomputes; its key (from config) is unchanged, so nothing downstream reruns
    assert toy.executions() == [("reconstruct", "scene-0001")]
    assert cache.lookup("reconstruct", entry.key).files == entry.files
    # history stays history: the recompute has its own run, linked to the original, which keeps its scenes
    original, again = sorted(
        (r for r in toy.runs() if r.data.tags["gdwm.stage"] == "reconstruct"), key=lambda r: r.info.start_time
    )
    assert original.data.tags["gdwm.scenes"] == "scene-0000,scene-0001,scene-0002"
    assert again.data.tags["gdwm.scenes"] == "scene-0001" and again.info.status == "FINISHED"
    assert again.data.tags["gdwm.recomputes"] == original.info.run_id
    assert again.data.tags["gdwm.cache_key"] == original.data.tags["gdwm.cache_key"]


def test_dry_run_prints_plan_without_running(first_run, tmp_path):
    toy = _copy(first_run, tmp_path)
    r = subprocess.run(
        [*toy.args("stage.toy_diffusion.steps=3"), "--dry-run"],
        env=toy.env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    _ok(r)
    assert toy.executions() == []
    lines = {tuple(line.split("│")[1:4]) for line in r.stdout.splitlines() if line.count("│") >= 5}
    status = {(a.strip(), b.strip()): c.strip() for a, b, c in lines}
    assert status[("reconstruct", "scene-0002")] == "cached"
    assert status[("diffusion", "-")] == "to run" and status[("evaluate_gen", "-")] == "to run"
    assert status[("lora", "-")] == "cached"
    assert "9 cached, 2 to run" in r.stdout
    res = {tuple(c.strip() for c in line.split("│")[1:6:4]) for line in r.stdout.splitlines() if line.count("│") >= 5}
    assert ("distill", "gpu: 1 CPU, 0 GPU, x2") in res  # cluster=local: a pool of 2 scene actors
    assert ("diffusion", "train: 1 CPU, 0 GPU, in-process") in res  # and Ray Train with num_workers=0


def test_killed_scene_worker_is_retried_and_outputs_match(first_run, tmp_path):
    toy = Toy(tmp_path)
    _ok(toy.run(GDWM_TEST_KILL="reconstruct:scene-0001"))
    assert (tmp_path / "marker-reconstruct-scene-0001").exists()
    ex = toy.executions()
    assert ex.count(("reconstruct", "scene-0001")) == 2  # the killed attempt and its retry
    ref, got = Cache(first_run.work / "cache"), Cache(toy.work / "cache")
    for m in ref.entries("reconstruct") + ref.entries("distill"):
        mine = got.lookup(m.stage, m.key)
        assert mine is not None and mine.files == m.files, (m.stage, m.scene)


# a real worker group (num_workers=1): tests/gdwm/test_checkpoints.py covers the resume rule in process and the CLI
def test_killed_train_worker_resumes_from_last_checkpoint(tmp_path):
    toy = Toy(tmp_path)
    r = toy.run("targets=[tokenizer]", "cluster.resources.train.num_workers=1", GDWM_TEST_KILL="tokenizer:step=1")
    _ok(r)
    assert (tmp_path / "marker-tokenizer-step").exists()
    tok = next(r for r in toy.runs() if r.data.tags["gdwm.stage"] == "tokenizer")
    client = toy.client()
    steps = [m.step for m in client.get_metric_history(tok.info.run_id, "loss")]
    starts = [m.value for m in client.get_metric_history(tok.info.run_id, "start")]
    assert steps.count(0) == 1, steps  # never restarted from step 0
    assert max(steps) == 3
    assert min(starts) == 0 and max(starts) >= 1, starts  # the restarted worker began after a checkpoint
    assert tok.info.status == "FINISHED"


def test_failing_stage_exits_1_naming_it_and_keeps_the_cache(first_run, tmp_path):
    toy = _copy(first_run, tmp_path)
    r = toy.run("stage.toy_diffusion.steps=5", GDWM_TEST_FAIL="evaluate_gen:None")
    assert r.returncode == 1, r.stderr
    assert "stage 'evaluate_gen' failed: ValueError: injected failure in evaluate_gen:None" in r.stderr
    failed = [x for x in toy.runs() if x.info.status == "FAILED"]
    assert [x.data.tags["gdwm.stage"] for x in failed] == ["evaluate_gen"]
    err = toy.client().download_artifacts(failed[0].info.run_id, "error.txt", str(tmp_path))
    assert "ValueError: injected failure in evaluate_gen:None" in Path(err).read_text()
    assert sorted(s for s, _ in toy.executions()) == ["diffusion", "evaluate_gen"]
    # the new diffusion entry is kept: fixing the failure reruns only evaluate_gen
    (tmp_path / "executions.log").write_text("")
    _ok(toy.run("stage.toy_diffusion.steps=5"))
    assert toy.executions() == [("evaluate_gen", "-")]


@pytest.mark.parametrize("policy", ["fail", "skip"])
def test_scene_error_policy(first_run, tmp_path, policy):
    toy = _copy(first_run, tmp_path)
    r = toy.run(
        "stage.toy_distill.dim=5",
        f"run.on_scene_error={policy}",
        "targets=[distill]",
        GDWM_TEST_FAIL="distill:scene-0002",
    )
    ex = toy.executions()
    assert sorted(ex) == [("distill", "scene-0000"), ("distill", "scene-0001"), ("distill", "scene-0002")]
    cache = Cache(toy.work / "cache")
    if policy == "fail":
        assert r.returncode == 1
        assert (
            "stage 'distill' scene(s) ['scene-0002'] failed: ValueError: injected failure in distill:scene-0002"
            in r.stderr
        )
    else:
        _ok(r)
        assert "1 scene(s) skipped" in r.stdout
    # the scenes that worked are cached either way
    new = [m for m in cache.entries("distill") if m.config == {"stage.toy_distill": {"dim": 5}}]
    assert sorted(m.scene for m in new) == ["scene-0000", "scene-0001"]
    if policy == "skip":
        # the run's cache_keys.json (what `gdwm cache gc` keeps for it) named all three planned scenes while it ran;
        # its end replaced that with the two entries it used
        run = toy.runs("run")[0]
        used = json.loads(Path(toy.client().download_artifacts(run.info.run_id, CACHE_KEYS, str(tmp_path))).read_text())
        assert used["distill"] == sorted(m.key for m in new)


def _start_blocked(toy: Toy, block: str) -> subprocess.Popen:
    """Start `gdwm run` in its own session and return once the stage named in ``block`` is waiting."""
    stage_name = block.split(":")[0]
    proc = subprocess.Popen(
        toy.args(),
        env=toy.env(GDWM_TEST_BLOCK=block),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    deadline = time.time() + 240
    while not (toy.root / f"blocked-{stage_name}").exists():
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            raise AssertionError(f"{stage_name} never started: {proc.communicate()[1][-2000:]}")
        time.sleep(0.2)
    return proc


def test_sigkilled_driver_resumes_without_duplicates(tmp_path):
    toy = Toy(tmp_path)
    proc = _start_blocked(toy, "lora:step=1")
    try:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        # Ray fate-shares workers with their driver: the blocked lora worker must die too.
        log = (tmp_path / "executions.log").read_text().splitlines()
        worker = int(next(line for line in log if line.startswith("lora ")).split()[3])
        deadline = time.time() + 60
        while _alive(worker):
            assert time.time() < deadline, f"lora worker {worker} outlived its SIGKILLed driver"
            time.sleep(0.2)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert {r.info.status for r in toy.runs()} >= {"RUNNING"}  # lora's run was left behind
    before = Counter(s for s, _ in toy.executions())
    assert before == {"reconstruct": 3, "distill": 3, "tokenizer": 1, "lora": 1}
    (tmp_path / "executions.log").write_text("")
    _ok(toy.run())
    assert sorted(s for s, _ in toy.executions()) == sorted(["lora", "evaluate_qa", "diffusion", "evaluate_gen"])
    runs = toy.runs() + toy.runs("run")
    assert [r.info.status for r in runs if r.info.status != "FINISHED"] == []
    per_key = Counter(r.data.tags["gdwm.cache_key"] for r in toy.runs())
    assert max(per_key.values()) == 1
    assert len(toy.runs("run")) == 1  # the same parent run continued
    # lora resumed from its checkpoint of step 1: step 0 was logged once, the second attempt started at 2
    lora = next(r for r in toy.runs() if r.data.tags["gdwm.stage"] == "lora")
    client = toy.client()
    assert [m.step for m in client.get_metric_history(lora.info.run_id, "loss")].count(0) == 1
    assert sorted({m.value for m in client.get_metric_history(lora.info.run_id, "start")}) == [0.0, 2.0]


def test_sigterm_ends_every_run_killed(tmp_path):
    toy = Toy(tmp_path)
    proc = _start_blocked(toy, "tokenizer")
    try:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err[-2000:]
    status = {r.data.tags.get("gdwm.stage", "parent"): r.info.status for r in toy.runs() + toy.runs("run")}
    assert status == {"reconstruct": "FINISHED", "distill": "FINISHED", "tokenizer": "KILLED", "parent": "KILLED"}
