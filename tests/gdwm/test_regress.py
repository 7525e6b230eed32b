"""`gdwm regress` on the toy pipeline: passes against its own baseline, fails naming the metric a weakened model
pushes past its tolerance (direction-aware), exits 2 on a bad suite, logs a regression run with table and trend."""

from __future__ import annotations

import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from gdwm.cli import main
from gdwm.regress import CheckTest, Direction, MetricCheck, check, failed
from tests.gdwm.test_run import Toy, _ok

pytestmark = pytest.mark.heavy(4)


def _regress(toy: Toy, *overrides: str) -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", "gdwm", "regress", f"workdir={toy.work}", f"data.root={toy.data}", *overrides]
    return subprocess.run(args, env=toy.env(), capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def baselined(tmp_path_factory) -> Toy:
    toy = Toy(tmp_path_factory.mktemp("regress"))
    r = _regress(toy, "benchmark=toy_nightly", "--set-baseline")
    _ok(r)
    assert "no baseline yet" in r.stdout and "recorded run" in r.stdout
    return toy


def test_passes_against_its_own_baseline(baselined):
    r = _regress(baselined, "benchmark=toy_nightly")
    _ok(r)
    # toy lora rank 4, 3 steps: plan_acc = 48 and MAE = 100 / 49, unchanged (a cache hit)
    assert "nuinteract/plan_acc" in r.stdout and "48" in r.stdout and "REGRESSION" not in r.stdout
    runs = baselined.runs("regression")
    assert len(runs) == 2 and {x.data.tags["gdwm.verdict"] for x in runs} == {"pass"}
    (base,) = [x for x in runs if x.data.tags.get("gdwm.baseline") == "true"]
    latest = next(x for x in runs if x.info.run_id != base.info.run_id)
    assert latest.data.tags["gdwm.baseline_run"] == base.info.run_id
    assert latest.data.metrics["nuinstruct/mae"] == pytest.approx(100 / 49)
    arts = {a.path for a in baselined.client().list_artifacts(latest.info.run_id)}
    assert {"regression.md", "trend.png"} <= arts


def test_weakened_model_fails_naming_the_metric(baselined):
    # the weakened model: plan_acc 12, MAE 100/13
    r = _regress(baselined, "benchmark=toy_nightly", "experiment=toy", "stage.toy_lora.rank=1")
    assert r.returncode == 1, r.stderr[-3000:]
    assert "regression: nuinteract/plan_acc 48 -> 12 (tolerance 1 ↑)" in r.stderr
    assert "regression: nuinstruct/mae 2.041 -> 7.692 (tolerance 10% ↓)" in r.stderr  # lower is better
    runs = baselined.runs("regression")
    assert "fail" in {x.data.tags["gdwm.verdict"] for x in runs}


def test_better_model_is_improved_not_a_regression(baselined):
    # a better model: plan_acc 96, MAE lower
    r = _regress(baselined, "benchmark=toy_nightly", "experiment=toy", "stage.toy_lora.rank=8")
    _ok(r)
    assert r.stdout.count("improved") == 2


def test_bad_suite_exits_2(tmp_path):
    toy = Toy(tmp_path)
    r = _regress(toy, "benchmark=toy_bad")
    assert r.returncode == 2
    assert "sideways" in r.stderr and "direction" in r.stderr
    assert not (toy.work / "mlflow.db").exists()


@pytest.fixture(scope="module")
def seeded(tmp_path_factory) -> Toy:
    toy = Toy(tmp_path_factory.mktemp("regress_seeds"))
    _ok(_regress(toy, "benchmark=toy_seeds", "--set-baseline"))
    return toy


def _acc(rank: float, seeds) -> list[float]:
    from tests.gdwm.stages import seed_noise

    return [12 * (rank + seed_noise(s)) for s in seeds]  # toy lora: 3 steps x 4 dims of (rank + noise(seed))


def test_seeded_baseline_records_mean_spread_and_samples(seeded):
    (base,) = seeded.runs("regression")
    acc = _acc(4, (0, 1, 2))
    m = base.data.metrics
    assert m["nuinteract/plan_acc"] == pytest.approx(statistics.fmean(acc))
    assert m["std/nuinteract/plan_acc"] == pytest.approx(statistics.stdev(acc)) and m["n/nuinteract/plan_acc"] == 3
    assert base.data.tags["gdwm.seeds"] == "0,1,2"
    files = {a.path for a in seeded.client().list_artifacts(base.info.run_id, "samples/evaluate_qa")}
    assert files == {f"samples/evaluate_qa/seed_{s}.parquet" for s in (0, 1, 2)}
    assert base.data.tags["gdwm.scorer.evaluate_qa"] == "tests.gdwm.stages:score_toy"


def test_other_seeds_of_the_same_model_do_not_fire(seeded):
    # seeds 3-5 of the same model: the mean of plan_acc drops by 2.5 std of a difference of two 3-seed means
    r = _regress(seeded, "benchmark=toy_seeds", "seeds=[3,4,5]")
    _ok(r)
    base, now = _acc(4, (0, 1, 2)), _acc(4, (3, 4, 5))
    sigma = (statistics.variance(base) / 3 + statistics.variance(now) / 3) ** 0.5  # Welch's, from both runs
    shift = (statistics.fmean(base) - statistics.fmean(now)) / sigma
    assert 2.4 < shift < 3  # a drop a fixed tolerance of 1.0 would have called a regression
    assert "REGRESSION" not in r.stdout and "mean of seeds [3, 4, 5]" in r.stdout
    assert f"3σ = {3 * sigma:.3g}" in r.stdout


def test_a_planted_regression_fires(seeded):
    r = _regress(seeded, "benchmark=toy_seeds", "experiment=toy", "stage.toy_lora.rank=1")
    assert r.returncode == 1, r.stderr[-3000:]
    before, after = statistics.fmean(_acc(4, (0, 1, 2))), statistics.fmean(_acc(1, (0, 1, 2)))
    assert f"regression: nuinteract/plan_acc {before:.4g} -> {after:.4g} (tolerance 3σ = " in r.stderr
    # the MAE check: 20% worse, and significantly so in a paired bootstrap over the 40 held-out samples
    assert "regression: nuinstruct/mae" in r.stderr and "(tolerance 20%, bootstrap ↓)" in r.stderr


def test_check_with_sigma_and_bootstrap():
    checks = [
        MetricCheck("a", Direction.higher, {"sigma": 2}),
        MetricCheck("b", Direction.higher, 0.0, test=CheckTest.bootstrap),
        MetricCheck("c", Direction.lower, 0.0, test=CheckTest.bootstrap),
        MetricCheck("d", Direction.higher, {"sigma": 2}),
    ]
    base = {"a": 10.0, "std/a": 1.0, "n/a": 2.0, "b": 5.0, "c": 1.0, "d": 3.0}
    now = {"a": 7.5, "n/a": 1.0, "b": 4.0, "c": 1.5, "d": 3.0}
    cis = {"b": (-2.0, 0.5), "c": (0.2, 0.8)}  # b: not significant; c: MAE significantly up
    rows = {r.metric: r for r in check(checks, base, now, cis.get)}
    # one seed now: sigma of the difference from the baseline's spread, 1.0 x sqrt(1/2 + 1/1); 2.5 worse > 2 x 1.22
    assert rows["a"].verdict == "REGRESSION" and rows["a"].tolerance == "2σ = 2.45 ↑"
    assert rows["b"].verdict == "ok (not significant)"
    assert rows["c"].verdict == "REGRESSION"
    assert rows["d"].verdict == "no spread"  # the baseline had one seed: sigma is undefined, and that fails
    assert [r.metric for r in failed(list(rows.values()))] == ["a", "c", "d"]
    assert check([MetricCheck("b", test=CheckTest.bootstrap)], {"b": 2.0}, {"b": 1.0})[0].verdict == "untestable"


def test_sigma_counts_both_runs_spreads():
    # Welch's standard error of the difference of two 3-seed means: sqrt(1^2/3 + 3^2/3) = 1.826; 3 of it = 5.48
    a = [MetricCheck("a", Direction.lower, {"sigma": 3})]
    base = {"a": 10.0, "std/a": 1.0, "n/a": 3.0}
    (row,) = check(a, base, {"a": 15.0, "std/a": 3.0, "n/a": 3.0})
    assert row.verdict == "ok" and row.allowed == pytest.approx(3 * (1 / 3 + 9 / 3) ** 0.5)
    # the baseline's spread alone (1 x sqrt(2/3) x 3 = 2.45) would have called 5 worse a regression
    assert check(a, base, {"a": 15.0, "n/a": 1.0})[0].verdict == "REGRESSION"
    assert check(a, base, {"a": 15.6, "std/a": 3.0, "n/a": 3.0})[0].verdict == "REGRESSION"


@pytest.mark.parametrize(
    ("tolerance", "message"),
    [({"sigma": -1}, "needs K >= 0"), ({"sgima": 3}, "a number or {sigma: K}"), ("x", "a number >= 0 or")],
)
def test_bad_tolerance_names_the_metric(tolerance, message):
    with pytest.raises(ValueError, match=r"metric 'm': tolerance") as e:
        MetricCheck("m", tolerance=tolerance)
    assert message in str(e.value)


def test_sigma_without_seeds_exits_2(tmp_path):
    toy = Toy(tmp_path)
    r = _regress(toy, "benchmark=toy_seeds", "seeds=[0]")
    assert r.returncode == 2
    assert "nuinteract/plan_acc has tolerance {sigma: K}, which needs >= 2 seeds" in r.stderr
    assert not (toy.work / "mlflow.db").exists()


def test_every_benchmark_module_is_registered_by_name():
    from importlib.metadata import entry_points
    from pathlib import Path

    from gdwm.regress import BENCHMARK_GROUP

    bench = Path(__file__).resolve().parents[2] / "benchmarks"
    modules = {p.stem.removeprefix("bench_") for p in bench.glob("bench_*.py")}
    registered = {ep.name: ep.value for ep in entry_points(group=BENCHMARK_GROUP)}
    assert registered == {name: f"benchmarks.bench_{name}:run" for name in modules}


def _toy_bench(quick: bool = False) -> list:
    from types import SimpleNamespace

    return [SimpleNamespace(metric="Median ms (quick)" if quick else "median ms", value=2)]


def test_perf_metrics_run_registered_benchmarks_and_name_a_missing_one(monkeypatch):
    from importlib.metadata import EntryPoint

    from gdwm import regress
    from gdwm.regress import RegressError, perf_metrics

    eps = [
        EntryPoint("toy", f"{__name__}:_toy_bench", "gdwm.benchmarks"),
        EntryPoint("broken", "tests.gdwm.no_such_module:run", "gdwm.benchmarks"),
    ]
    monkeypatch.setattr(regress, "entry_points", lambda group: [e for e in eps if group == "gdwm.benchmarks"])
    assert perf_metrics(["toy"]) == {"perf/toy/median_ms_quick": 2.0}
    with pytest.raises(RegressError) as e:
        perf_metrics(["toy", "selct"])
    assert str(e.value) == (
        "benchmark.perf: no performance benchmark 'selct' (entry-point group gdwm.benchmarks has: broken, toy)"
    )
    with pytest.raises(RegressError, match=r"^benchmark.perf: performance benchmark 'broken' "
                       r"\(tests.gdwm.no_such_module:run\) does not import: No module named"):  # fmt: skip
        perf_metrics(["broken"])


@pytest.mark.parametrize(
    "args, message",
    [
        (["benchmark.metrics=[]"], "benchmark 'toy_nightly': no metrics to watch (benchmark.metrics is empty): a gate "
                                   "that checks nothing would always pass"),
        (["benchmark.baseline=0123456789abcdef0123456789abcdef"],
         "benchmark.baseline: no run '0123456789abcdef0123456789abcdef' in "),
        ([], "benchmark 'toy_nightly': no baseline in "),
        (["benchmark.name=../nightly"], "benchmark.name='../nightly' starts with '.'"),
    ],
)  # fmt: skip
def test_a_gate_that_would_check_nothing_exits_2_before_launch(tmp_path, monkeypatch, capsys, args, message):
    """No metrics, a baseline id that does not exist or no baseline at all: refused before Ray starts or any stage
    recomputes (a nightly gate that checks nothing must not report success)."""
    toy = Toy(tmp_path)
    monkeypatch.setenv("GDWM_CONF_PATH", str(Path(__file__).parents[1] / "conf"))
    rc = main(["regress", "benchmark=toy_nightly", f"workdir={toy.work}", f"data.root={toy.data}", *args])
    err = " ".join(capsys.readouterr().err.split())
    assert rc == 2 and err.startswith(f"gdwm regress: {message}"), err
    assert not (tmp_path / "executions.log").exists() and not (toy.work / "cache").exists()


def test_a_reported_row_is_never_a_regression_baseline(tmp_path):
    from gdwm.compare.references import Reference, log_references
    from gdwm.compare.runs import Source
    from gdwm.config import BenchmarkConfig
    from gdwm.regress import RegressError, _baseline, markdown
    from gdwm.tracking import TrackingBackend

    b = TrackingBackend(f"sqlite:///{tmp_path}/mlflow.db", "gdwm", str(tmp_path / "mlartifacts"))
    b.system_metrics_interval_s = 0
    (ref,) = log_references(b, [Reference("DriveMonkey", Source("DriveMonkey", "Tab. 1", "2025"), {"m": 52.12})])
    b.set_tags(ref, {"gdwm.baseline": "true", "gdwm.benchmark": "nightly"})  # even tagged like one
    with pytest.raises(RegressError) as e:
        _baseline(b, BenchmarkConfig(name="nightly", baseline=ref))
    assert str(e.value) == (
        f"benchmark.baseline={ref}: a reported row (gdwm.kind=reference, numbers copied from DriveMonkey) cannot be "
        "a regression baseline; name a measured run, or record one with --set-baseline"
    )
    assert _baseline(b, BenchmarkConfig(name="nightly")) is None  # the tagged search looks at regression runs only
    # regress prints its numbers rounded half up, as every table does: 24.775 is 24.78, not Python's 24.77
    rows = check(
        [MetricCheck("nuinteract/avg", Direction.higher, 1.0)], {"nuinteract/avg": 24.0}, {"nuinteract/avg": 24.775}
    )
    assert f"{24.775:.4g}" == "24.77" and "| nuinteract/avg | 24 | 24.78 | +0.775 | 1 ↑ | improved |" in markdown(rows)
