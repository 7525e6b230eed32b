"""`gdwm reproduce` end to end through the real CLI on the toy pipeline (local Ray, 2 CPUs), with a fake library.

Pipeline ``toy_lib`` is the toy DAG whose lora scales the rank by the major version of ``toylib``, a fake distribution
(a dist-info) on PYTHONPATH, as the cache's library tests plant one (tests/gdwm/test_code_keys.py). A trial recorded
with toylib 1.0 is reproduced in a fresh workdir: equal in every metric and cache entry; then with toylib 2.0 the
report names the metrics that moved, the entries whose key and bytes moved, and the library with both versions. Bad
input exits 2 before anything runs.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gdwm.environment.runs import CONFIG_ARTIFACT
from tests.gdwm.test_run import Toy, _ok

pytestmark = pytest.mark.heavy(1.5)

TARGETS = "targets=[evaluate_qa]"  # the QA branch only: 9 cache entries (3 + 3 per-scene, tokenizer, lora, eval)


class LibToy(Toy):
    def __init__(self, root: Path):
        super().__init__(root)
        self.site = root / "site"
        self.library("1.0")

    def library(self, version: str) -> None:
        """Install a fake ``toylib`` distribution of ``version`` (what importlib.metadata reports)."""
        for old in self.site.glob("toylib-*.dist-info"):
            for f in old.iterdir():
                f.unlink()
            old.rmdir()
        dist = self.site / f"toylib-{version}.dist-info"
        dist.mkdir(parents=True)
        (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: toylib\nVersion: {version}\n")

    def env(self, **inject: str) -> dict:
        env = super().env(**inject)
        env["PYTHONPATH"] = f"{self.site}:{env['PYTHONPATH']}"
        return env

    def args(self, *overrides: str) -> list[str]:
        return [*super().args("pipeline=toy_lib", TARGETS), *overrides]

    def run(self, *overrides: str, **inject: str) -> subprocess.CompletedProcess:
        return subprocess.run(self.args(*overrides), env=self.env(**inject), capture_output=True, text=True,
                              timeout=900)  # fmt: skip

    def reproduce(self, *args: str) -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "gdwm", "reproduce", *args]
        return subprocess.run(cmd, env=self.env(), capture_output=True, text=True, timeout=900, cwd=self.root)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> LibToy:
    toy = LibToy(tmp_path_factory.mktemp("reproduce"))
    _ok(toy.run())
    [run] = toy.runs("run")
    toy.run_id = run.info.run_id
    return toy


def _rows(report: dict, kind: str) -> list[dict]:
    [trial] = report["trials"]
    return trial[kind]


def test_a_toy_trial_reproduces_equal_in_every_metric_and_entry(recorded):
    fresh = recorded.root / "again"
    r = recorded.reproduce(recorded.run_id, f"workdir={fresh}", f"args.store={recorded.work}")
    _ok(r)
    assert f"reproducing run {recorded.run_id}: 'run-toy_lib-" in r.stdout
    assert f"running again in the fresh workdir {fresh}" in r.stdout
    report = json.loads((fresh / "reproduce.json").read_text())
    metrics, entries = _rows(report, "metrics"), _rows(report, "entries")
    assert {m["metric"] for m in metrics} == {"acc", "nuinteract/plan_acc", "nuinstruct/mae"}
    assert {m["verdict"] for m in metrics} == {"equal"}
    assert [(e["stage"], e["verdict"]) for e in entries] == (
        [("reconstruct", "equal (1 file)")] * 3 + [("distill", "equal (1 file)")] * 3
        + [("tokenizer", "equal (1 file)"), ("lora", "equal (1 file)"), ("evaluate_qa", "equal (2 files)")]
    )  # fmt: skip
    assert all(e["recorded"] == e["reproduced"] for e in entries)
    assert report["trials"][0]["environment"] == []
    assert "environment: the same (" in r.stdout
    assert "reproduced: every metric and cache entry of 1 trial(s) equal" in r.stdout
    # from scratch, in the fresh workdir: its own cache and store; the recorded store gained nothing
    assert (fresh / "mlflow.db").is_file() and len(list((fresh / "cache" / "reconstruct").glob("*"))) >= 3
    assert len(recorded.runs("run")) == 1 and len(recorded.runs("sweep")) == 0


def test_a_library_change_names_the_library_and_the_metrics_it_moved(recorded):
    recorded.library("2.0")  # the lora's rank x 2: plan_acc 48 -> 96
    try:
        fresh = recorded.root / "lib2"
        r = recorded.reproduce(recorded.run_id[:12], f"workdir={fresh}", f"args.store={recorded.work}")
    finally:
        recorded.library("1.0")
    assert r.returncode == 1, r.stdout[-3000:] + r.stderr[-3000:]
    report = json.loads((fresh / "reproduce.json").read_text())
    metrics = {m["metric"]: m for m in _rows(report, "metrics")}
    assert (metrics["nuinteract/plan_acc"]["recorded"], metrics["nuinteract/plan_acc"]["reproduced"]) == ("48", "96")
    assert metrics["nuinteract/plan_acc"]["verdict"] == "differs by +48 (+100.00%)"
    assert metrics["nuinstruct/mae"]["verdict"].startswith("differs by ")
    entries = {e["stage"]: e["verdict"] for e in _rows(report, "entries")}
    assert entries["reconstruct"] == entries["tokenizer"] == "equal (1 file)"
    assert entries["lora"] == "bytes differ (weights.npy); key differs: library toylib 1.0 -> 2.0"
    assert entries["evaluate_qa"] == "bytes differ (metrics.json, predictions.parquet); key differs: upstream: lora"
    assert report["trials"][0]["environment"] == ["toylib 1.0 -> 2.0"]
    assert "environment differences (recorded -> now):\n  toylib 1.0 -> 2.0" in r.stdout
    assert "not reproduced: 1 of 1 trial(s) differ" in r.stdout


def test_bad_input_exits_2_naming_the_run_and_the_key(recorded, tmp_path):
    store = f"args.store={recorded.work}"
    unknown = recorded.reproduce("0123456789abcdef0123456789abcdef", store, f"workdir={tmp_path / 'a'}")
    assert unknown.returncode == 2
    assert unknown.stderr.strip() == (
        f"gdwm reproduce: no run '0123456789abcdef0123456789abcdef' in store sqlite:///{recorded.work}/mlflow.db: a "
        "run of another store? name its store with args.store=WORKDIR (or a tracking URI)"
    )
    # a run of another store: this store's run id, looked up in a store where it is not
    other = LibToy(tmp_path / "other")
    other.work.mkdir(parents=True)
    (other.work / "mlflow.db").write_bytes(b"")
    elsewhere = recorded.reproduce(recorded.run_id, f"args.store={other.work}", f"workdir={tmp_path / 'b'}")
    assert (
        elsewhere.returncode == 2 and f"no run '{recorded.run_id}' in store sqlite:///{other.work}" in elsewhere.stderr
    )
    [stage] = [r for r in recorded.runs() if r.data.tags["gdwm.stage"] == "lora"]
    staged = recorded.reproduce(stage.info.run_id, store, f"workdir={tmp_path / 'c'}")
    assert staged.returncode == 2
    assert staged.stderr.strip() == (
        f"gdwm reproduce: run {stage.info.run_id} is a stage run: reproduce a trial, a row, a gdwm run or a sweep; "
        f"its launch is run {recorded.run_id}"
    )
    # a key removed since the run was recorded: its config.yaml holds a setting today's schema lacks
    art = Path(recorded.client().get_run(recorded.run_id).info.artifact_uri.removeprefix("file://")) / CONFIG_ARTIFACT
    saved = art.read_text()
    try:
        art.write_text(saved.replace("run:\n", "run:\n  old_knob: 3\n", 1))
        removed = recorded.reproduce(recorded.run_id, store, f"workdir={tmp_path / 'd'}")
    finally:
        art.write_text(saved)
    assert removed.returncode == 2
    assert removed.stderr.strip() == (
        f"gdwm reproduce: run {recorded.run_id} (trial '{recorded.runs('run')[0].info.run_name}'): "
        "its recorded config no longer composes: 'run.old_knob' is no setting any more (removed since the run was "
        "recorded?)"
    )
    assert not any((tmp_path / d).exists() for d in "abcd")  # refused before anything ran


# ---- in process: what a run stands for, and the config composed again ------------------------------------------
def test_a_sweep_row_or_run_stands_for_its_trials_in_order(tmp_path):
    from gdwm.reproduce import ReproduceError, trial_runs
    from gdwm.tracking import TrackingBackend

    b = TrackingBackend(f"sqlite:///{tmp_path}/mlflow.db", "gdwm", str(tmp_path / "art"))
    sweep = b.create_run("sweep", {"gdwm.kind": "sweep"})
    ids = {}
    for index in (1, 0):  # rows found in any order come back in table order, their seeds in seed order
        row = b.create_run(f"row{index}", {"gdwm.kind": "row", "gdwm.trial_index": str(index)}, sweep)
        for seed in (2, 0):
            ids[index, seed] = b.create_run(f"t{index}{seed}", {"gdwm.kind": "trial", "gdwm.seed": str(seed)}, row)
        ids[index] = row
    stage = b.create_run("lora", {"gdwm.kind": "stage", "gdwm.stage": "lora"}, sweep)

    def of(run_id):
        return [r.info.run_id for r in trial_runs(b, b.client.get_run(run_id))]

    assert of(sweep) == [ids[0, 0], ids[0, 2], ids[1, 0], ids[1, 2]]
    assert of(ids[1]) == [ids[1, 0], ids[1, 2]] and of(ids[1, 2]) == [ids[1, 2]]
    with pytest.raises(ReproduceError, match=f"run {stage} is a stage run: .* its launch is run {sweep}"):
        of(stage)


def test_a_recorded_config_is_set_over_todays(tmp_path):
    from gdwm.config import load_config
    from gdwm.reproduce import ReproduceError, moved, overlay

    cfg = load_config([f"workdir={tmp_path}"])
    recorded = OmegaConf.to_container(cfg, resolve=True)
    recorded["stage"]["lora"]["rank"] = 3  # a recorded value wins over today's default
    recorded["pipeline"]["stages"].pop("evaluate_gen")  # a free-form mapping becomes the recorded one exactly
    del recorded["run"]["max_retries"]  # a setting new since the recording keeps today's default, and is listed
    assert overlay(cfg, recorded) == ["run.max_retries"]
    assert cfg.stage.lora.rank == 3 and "evaluate_gen" not in cfg.pipeline.stages
    recorded["cache"]["old_knob"] = 1
    with pytest.raises(ReproduceError, match=r"^'cache.old_knob' is no setting any more \(removed since"):
        overlay(load_config([f"workdir={tmp_path}"]), recorded)
    recorded["cache"].pop("old_knob")
    recorded["run"]["max_retries"] = "many"
    with pytest.raises(ReproduceError, match=r"^'run.max_retries': the recorded value 'many' is not valid any more"):
        overlay(load_config([f"workdir={tmp_path}"]), recorded)
    assert moved({"a": "/w/cache", "b": ["sqlite:////w/mlflow.db"], "c": "/work"}, "/w", "/new") == {
        "a": "/new/cache", "b": ["sqlite:////new/mlflow.db"], "c": "/work"}  # fmt: skip
