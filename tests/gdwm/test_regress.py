"""`gdwm regress` on the toy pipeline: passes against its own baseline, fails naming the metric a weakened model
pushes past its tolerance (direction-aware), exits 2 on a bad suite, logs a regression run with table and trend."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.gdwm.test_run import Toy, _ok


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


@pytest.mark.slow
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
