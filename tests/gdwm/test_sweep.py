"""`gdwm sweep` end to end on local Ray with the toy stages: shared stages run once (counted from the stages' own
log and from MLflow), trials are child runs of one sweep run, resume and extension never duplicate a run."""

from __future__ import annotations

import signal
import statistics
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from gdwm.cli import main
from gdwm.tracking.params import PARAMS_BASE_TAG, full_params
from tests.gdwm.test_run import Toy, _ok

pytestmark = pytest.mark.heavy(3.5)


def _sweep(toy: Toy, *overrides: str, **inject: str) -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", "gdwm", "sweep", f"workdir={toy.work}", f"data.root={toy.data}", *overrides]
    return subprocess.run(args, env=toy.env(**inject), capture_output=True, text=True, timeout=600)


def _trials(toy: Toy) -> dict[str, object]:
    return {r.data.tags["gdwm.row"]: r for r in toy.runs("trial")}


@pytest.fixture(scope="module")
def swept(tmp_path_factory) -> Toy:
    toy = Toy(tmp_path_factory.mktemp("sweep"))
    r = _sweep(toy, "sweep=toy_ablation")
    _ok(r)
    toy.stdout = r.stdout
    return toy


def test_shared_stages_run_exactly_once(swept):
    # 3 trials x (3 scenes x 2 per-scene stages + tokenizer + lora + evaluate_qa) = 27 as independent runs
    assert Counter(s for s, _ in swept.executions()) == {
        "reconstruct": 3,
        "distill": 3,
        "tokenizer": 1,
        "lora": 3,
        "evaluate_qa": 3,
    }
    stage_runs = Counter(r.data.tags["gdwm.stage"] for r in swept.runs())
    assert stage_runs == {"reconstruct": 1, "distill": 1, "tokenizer": 1, "lora": 3, "evaluate_qa": 3}
    assert "sweep: 3 trials, 9 stage executions run (15 as independent runs without a cache)" in swept.stdout
    assert "(shared by 3 trials)" in swept.stdout  # tokenizer


def test_rows_and_trials_carry_the_environment_record_of_the_sweep_run(swept):
    # created with the record's tags (gdwm.runner.Layout.open), not tagged after: the same tags either way
    (parent,) = swept.runs("sweep")
    record = {k: parent.data.tags[k] for k in ("gdwm.env", "gdwm.env_run", "gdwm.commit")}
    assert record["gdwm.env_run"] == parent.info.run_id and len(record["gdwm.env"]) >= 12
    runs = swept.runs("row") + swept.runs("trial")
    assert len(runs) == 6
    assert [{k: r.data.tags.get(k) for k in record} for r in runs] == [record] * 6


def test_one_parent_a_run_per_row_and_a_child_per_trial(swept):
    (parent,) = swept.runs("sweep")
    assert parent.info.status == "FINISHED" and parent.data.tags["gdwm.sweep"] == "toy_ablation"
    assert parent.data.tags["gdwm.stage_executions"] == "9" and parent.data.tags["gdwm.trials"] == "3"
    rows = {r.data.tags["gdwm.row"]: r for r in swept.runs("row")}
    assert sorted(rows) == ["rank 2", "rank 4", "rank 8"]
    assert {r.data.tags["mlflow.parentRunId"] for r in rows.values()} == {parent.info.run_id}
    trials = _trials(swept)
    assert sorted(trials) == ["rank 2", "rank 4", "rank 8"]
    assert {k: t.data.tags["mlflow.parentRunId"] for k, t in trials.items()} == {
        k: r.info.run_id for k, r in rows.items()
    }
    assert {t.info.status for t in trials.values()} | {r.info.status for r in rows.values()} == {"FINISHED"}
    assert {t.data.tags["gdwm.seed"] for t in trials.values()} == {"0"}
    # one seed: the row's aggregate is that seed's value, with n = 1 and no std
    assert rows["rank 8"].data.metrics["acc"] == 96.0 and rows["rank 8"].data.tags["gdwm.n.acc"] == "1"
    assert "acc/std" not in rows["rank 8"].data.metrics and "n/acc" not in rows["rank 8"].data.metrics
    assert rows["rank 8"].data.params["factor.Rank"] == "8"
    assert trials["rank 8"].data.tags["gdwm.factor.Rank"] == "8"
    # the sweep's run holds the config its rows share, a row's run what differs (its factors' keys) and its factors,
    # a one-seed trial's run what differs from its row (nothing) and its factors
    shared = parent.data.params
    assert len(shared) > 100 and "stage.toy_lora.rank" not in shared
    assert not any(k.startswith("factor.") for k in shared)
    assert {r.data.tags[PARAMS_BASE_TAG] for r in rows.values()} == {parent.info.run_id}
    assert rows["rank 8"].data.params == {"factor.Rank": "8", "stage.toy_lora.rank": "8"}
    assert trials["rank 8"].data.params == {"factor.Rank": "8"}
    full = full_params(trials["rank 8"].data.params, rows["rank 8"].data.params, shared)
    assert full == shared | {"factor.Rank": "8", "stage.toy_lora.rank": "8"}
    # the toy evaluate_qa sums lora weights that grow by `rank` per step (3 steps, 4 dims)
    assert {k: t.data.metrics["acc"] for k, t in trials.items()} == {"rank 2": 24.0, "rank 4": 48.0, "rank 8": 96.0}
    # every trial links the stage runs it used; the shared tokenizer run is the same for all three
    tok = {t.data.tags["gdwm.stage_run.tokenizer"] for t in trials.values()}
    assert len(tok) == 1 and tok <= {r.info.run_id for r in swept.runs()}
    assert len({t.data.tags["gdwm.stage_run.lora"] for t in trials.values()}) == 3


def test_compare_reads_each_rows_whole_config_through_its_sweeps_run(swept):
    from gdwm.compare.runs import select
    from gdwm.tracking.backend import TrackingBackend

    (parent,) = swept.runs("sweep")
    backend = TrackingBackend(f"sqlite:///{swept.work.resolve()}/mlflow.db", "gdwm")
    rows = {r.label: r for r in select(backend, sweep="toy_ablation").rows}
    backend.close()
    assert sorted(rows) == ["rank 2", "rank 4", "rank 8"]
    for label, row in rows.items():
        rank = label.split()[1]
        assert row.params == parent.data.params | {"factor.Rank": rank, "stage.toy_lora.rank": rank}
        assert row.param("seed") == "0" and row.param("stage.toy_lora.rank") == rank  # shared, own


def test_rows_record_what_differs_from_their_sweeps_run_unless_they_lack_one_of_its_keys(tmp_path):
    from types import SimpleNamespace

    import mlflow

    from gdwm.runner import Layout
    from gdwm.tracking import NewRun, TrackingClient
    from gdwm.tracking.backend import TrackingBackend

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    backend = TrackingBackend(uri, "gdwm", str(tmp_path / "art"))
    tracking, client = TrackingClient(backend), mlflow.MlflowClient(uri)
    sweep = backend.create_run("sweep-x", {})

    def row(rank: str, **params: str) -> tuple:
        return SimpleNamespace(factors={"R": rank}), NewRun(rank, {}, sweep, {"factor.R": rank, "r": rank, **params})

    # a sweep run made by this launch gets what its new rows share (factors never)
    a, b = row("2", x="1", only_a="1"), row("4", x="1")
    Layout(None, "sweep:x", "toy")._trim_rows(tracking, sweep, [a, b])
    assert client.get_run(sweep).data.params == {"x": "1"}
    assert (a[1].params, a[1].tags) == ({"factor.R": "2", "r": "2", "only_a": "1"}, {PARAMS_BASE_TAG: sweep})
    assert (b[1].params, b[1].tags) == ({"factor.R": "4", "r": "4"}, {PARAMS_BASE_TAG: sweep})
    # a later launch's rows under the sweep run found again: one lacking a key it holds records its whole config
    later = Layout(None, "sweep:x", "toy")
    later._sweep_params = {"x": "1"}
    c, d = row("6"), row("8", x="1")
    later._trim_rows(tracking, sweep, [c, d])
    assert (c[1].params, c[1].tags) == ({"factor.R": "6", "r": "6"}, {})
    assert (d[1].params, d[1].tags) == ({"factor.R": "8", "r": "8"}, {PARAMS_BASE_TAG: sweep})
    assert client.get_run(sweep).data.params == {"x": "1"}  # not written again
    # a sweep run of gdwm before rows recorded differences holds no params: its new rows record everything
    old = Layout(None, "sweep:x", "toy")
    old._sweep_params = {}
    e = row("9", x="1")
    old._trim_rows(tracking, sweep, [e])
    assert (e[1].params, e[1].tags) == ({"factor.R": "9", "r": "9", "x": "1"}, {})
    backend.close()


def test_report_written_and_logged_to_the_sweep_run(swept):
    md = (swept.work / "reports" / "toy_ablation" / "nuinteract.md").read_text()
    assert "**96.00 [" in md and "<u>48.00 [" in md  # plan accuracy: best and second, each with its interval
    (parent,) = swept.runs("sweep")
    logged = {a.path for a in swept.client().list_artifacts(parent.info.run_id, "compare/nuinteract")}
    assert "compare/nuinteract/nuinteract.html" in logged


def test_rerun_is_all_cached_and_extending_runs_only_new_stages(swept, tmp_path):
    from tests.gdwm.test_run import _copy

    toy = _copy(swept, tmp_path)
    dry = _sweep(toy, "sweep=toy_ablation_more", "--dry-run")
    _ok(dry)
    assert "2 stage executions to run, 0 shared, 18 cached" in dry.stdout
    _ok(_sweep(toy, "sweep=toy_ablation_more"))
    assert sorted(s for s, _ in toy.executions()) == ["evaluate_qa", "lora"]  # only the new row's
    trials = _trials(toy)
    assert sorted(trials) == ["rank 2", "rank 4", "rank 6", "rank 8"] and len(toy.runs("trial")) == 4
    assert len(toy.runs("sweep")) == 1  # the same sweep run continued
    assert trials["rank 6"].data.metrics["acc"] == 72.0
    assert trials["rank 6"].data.params == {"factor.Rank": "6"}  # its new row's run holds the config
    # under the sweep's run the first launch made, which holds what its rows shared
    (sweep_run,) = toy.runs("sweep")
    row6 = next(r for r in toy.runs("row") if r.data.tags["gdwm.row"] == "rank 6")
    assert row6.data.params == {"factor.Rank": "6", "stage.toy_lora.rank": "6"}
    assert row6.data.tags[PARAMS_BASE_TAG] == sweep_run.info.run_id
    assert len(toy.runs("row")) == 4


def test_bad_row_is_rejected_before_launch(tmp_path):
    toy = Toy(tmp_path)
    r = _sweep(toy, "sweep=toy_bad_row")
    assert r.returncode == 2
    assert "sweep 'toy_bad_row' row 'typo'" in r.stderr and "stage.toy_lora.rnak" in r.stderr
    assert not (toy.work / "mlflow.db").exists() and not (tmp_path / "executions.log").exists()


def test_failing_trial_does_not_stop_the_others(tmp_path):
    toy = Toy(tmp_path)
    r = _sweep(toy, "sweep=toy_grid")
    assert r.returncode == 1
    assert "trial 'short, stage.toy_lora.rank=-1' failed at lora" in r.stderr
    trials = _trials(toy)
    assert {k: t.info.status for k, t in trials.items()} == {
        "short, stage.toy_lora.rank=3": "FINISHED",
        "short, stage.toy_lora.rank=-1": "FAILED",
        "long, stage.toy_lora.rank=3": "FINISHED",
        "long, stage.toy_lora.rank=-1": "FAILED",
    }
    bad = trials["long, stage.toy_lora.rank=-1"]
    assert bad.data.tags["gdwm.failed_stage"] == "lora" and "rank must be >= 0" in bad.data.tags["gdwm.error"]
    assert Counter(s for s, _ in toy.executions())["tokenizer"] == 2  # short and long: two keys
    md = (toy.work / "reports" / "toy_grid" / "nuinteract.md").read_text()
    assert "failed at lora" in md


def test_sigkilled_driver_resumes_the_sweep_without_duplicates(tmp_path):
    toy = Toy(tmp_path)
    args = [sys.executable, "-m", "gdwm", "sweep", "sweep=toy_ablation", f"workdir={toy.work}", f"data.root={toy.data}"]
    proc = subprocess.Popen(args, env=toy.env(GDWM_TEST_BLOCK="lora:step=1"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip
    try:
        deadline = time.time() + 240
        while not (tmp_path / "blocked-lora").exists():
            assert proc.poll() is None and time.time() < deadline, proc.communicate()[1][-3000:]
            time.sleep(0.2)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "RUNNING" in {r.info.status for r in toy.runs("trial")}  # left behind by the killed driver
    _ok(_sweep(toy, "sweep=toy_ablation"))
    runs = toy.runs("trial") + toy.runs("sweep") + toy.runs()
    assert [r.info.status for r in runs if r.info.status != "FINISHED"] == []
    assert len(toy.runs("trial")) == 3 and len(toy.runs("sweep")) == 1
    assert max(Counter(r.data.tags["gdwm.cache_key"] for r in toy.runs()).values()) == 1
    assert Counter(s for s, _ in toy.executions())["tokenizer"] == 1  # finished before the kill: not redone


def test_seeds_share_seed_free_stages_and_aggregate_per_row(tmp_path):
    """2 rows x 3 seeds: reconstruct and distill (seed-free) run once, tokenizer once per seed (shared by the rows),
    lora and evaluate_qa once per (row, seed); each row's run holds mean, std and n over its seeds."""
    toy = Toy(tmp_path)
    r = _sweep(toy, "sweep=toy_seeds")
    _ok(r)
    stage_runs = Counter(x.data.tags["gdwm.stage"] for x in toy.runs())
    assert stage_runs == {"reconstruct": 1, "distill": 1, "tokenizer": 3, "lora": 6, "evaluate_qa": 6}
    assert Counter(s for s, _ in toy.executions()) == {
        "reconstruct": 3, "distill": 3, "tokenizer": 3, "lora": 6, "evaluate_qa": 6,
    }  # fmt: skip
    # the seed enters a seeded stage's config (so its key) and params; a seed-free stage's config has none
    lora_params = sorted(x.data.params["seed"] for x in toy.runs() if x.data.tags["gdwm.stage"] == "lora")
    assert lora_params == ["0", "0", "1", "1", "2", "2"]
    assert all("seed" not in x.data.params for x in toy.runs() if x.data.tags["gdwm.stage"] == "distill")
    assert "sweep: 6 trials, 17 stage executions run (30 as independent runs without a cache)" in r.stdout
    rows = {x.data.tags["gdwm.row"]: x for x in toy.runs("row")}
    (shared,) = (x.data.params for x in toy.runs("sweep"))
    trials = toy.runs("trial")
    assert len(trials) == 6 and sorted(t.data.tags["gdwm.seed"] for t in trials) == ["0", "0", "1", "1", "2", "2"]
    # a trial's run records what differs from its row's config (the seed) and its factors; the row the rest
    for t in trials:
        seed, row = t.data.tags["gdwm.seed"], rows[t.data.tags["gdwm.row"]]
        own = dict(t.data.params)
        assert own.pop("factor.Rank") == row.data.params["factor.Rank"] and shared["seed"] == "0"
        # the row's config is its first seed's: seed 0 differs in nothing; the others in `seed` and what it sets
        assert sorted(own) == ([] if seed == "0" else ["model.llm.seed", "model.selector.seed", "seed"])
        assert set(own.values()) <= {seed}
        assert full_params(t.data.params, row.data.params, shared)["seed"] == seed
    from tests.gdwm.stages import seed_noise

    # rank 4, 3 steps, 4 dims: acc = 12 * (4 + noise(seed))
    acc = [12 * (4 + seed_noise(s)) for s in (0, 1, 2)]
    m = rows["rank 4"].data.metrics
    assert m["acc"] == pytest.approx(sum(acc) / 3) and rows["rank 4"].data.tags["gdwm.n.acc"] == "3"
    assert m["acc/std"] == pytest.approx(statistics.stdev(acc))
    per_seed = {t.data.tags["gdwm.seed"]: t.data.metrics["acc"] for t in trials if t.data.tags["gdwm.row"] == "rank 4"}
    assert per_seed == pytest.approx({"0": acc[0], "1": acc[1], "2": acc[2]})
    assert {t.data.tags["mlflow.parentRunId"] for t in trials if t.data.tags["gdwm.row"] == "rank 4"} == {
        rows["rank 4"].info.run_id
    }


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["sweep=toy_seeds", "seeds=[]"], "seeds: no seeds given"),
        (["sweep=toy_seeds", "seeds=[0,-1]"], "invalid value for 'seeds[1]': -1 (must be >= 0 and <= 4294967295)"),
        (["sweep=toy_seeds", "seeds=[0,x]"], "seeds"),
        (["sweep=toy_seeds", "seeds=[1,1]"], "seeds: seed(s) [1] listed twice"),
        (["sweep=toy_grid", "seeds=[0,1]", "+sweep.grid.seed=[1,2]"], "grid key 'seed' sets a seed itself"),
        (["sweep=toy_seeds", "seed=3"], "command-line override 'seed=3' sets the trial seed"),
    ],
)
def test_bad_seeds_exit_2_naming_the_key(tmp_path, args, message):
    toy = Toy(tmp_path)
    r = _sweep(toy, *args)
    assert r.returncode == 2, r.stderr[-2000:]
    assert message in r.stderr
    assert not (tmp_path / "executions.log").exists()


def test_rows_resolving_to_the_same_stage_keys_exit_2_naming_both(tmp_path):
    toy = Toy(tmp_path)
    r = _sweep(toy, "sweep=toy_duplicate_rows", "--dry-run")
    assert r.returncode == 2
    assert (
        "sweep 'toy_duplicate_rows': rows 'rank 4' and 'rank four again' resolve to the same stage keys (one model "
        "under two labels); make their overrides differ or drop one"
    ) in " ".join(r.stderr.split())
    assert not (toy.work / "mlflow.db").exists()


@pytest.mark.parametrize(
    "override, message",
    [
        ("sweep.name=../../escaped", "sweep.name='../../escaped' starts with '.'"),
        ("sweep.name=/tmp/anywhere", "sweep.name='/tmp/anywhere' holds '/'"),
        ("sweep.rows.0.label=a/b", "sweep.rows[0].label='a/b' holds '/'"),
        ("sweep.rows.1.label=..", "sweep.rows[1].label='..' starts with '.'"),
    ],
)
def test_names_that_become_paths_are_plain_names_else_exit_2(tmp_path, monkeypatch, capsys, override, message):
    """A sweep file shared by others carries its name and labels: `../../escaped` would put the reports outside the
    workdir, an absolute name anywhere. Refused before anything is planned or written."""
    monkeypatch.setenv("GDWM_CONF_PATH", str(Path(__file__).parents[1] / "conf"))
    rc = main(["sweep", "sweep=toy_ablation", override, f"workdir={tmp_path / 'w'}", "--dry-run"])
    err = " ".join(capsys.readouterr().err.split())
    assert rc == 2 and message in err and "a name that becomes a path must be one plain path component" in err
    assert not (tmp_path / "w").exists() and not (tmp_path.parent / "escaped").exists()
