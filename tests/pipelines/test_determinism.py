"""A trial is bit-identical wherever it runs: twice from scratch in two workdirs, and again as one of three trials of
a sweep running side by side (the real stages, tiny flavors, local Ray on 2 CPUs)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gdwm.cache import Cache
from tests.pipelines.conftest import TINY_RUN as TINY
from tests.pipelines.conftest import gdwm_cli as _gdwm

pytestmark = [pytest.mark.heavy(3), pytest.mark.xdist_group("tiny_run")]

REPO = Path(__file__).resolve().parents[2]


def _evaluation(work: Path) -> dict[str, tuple[bytes, dict]]:
    """evaluate_qa's predictions (bytes) and metrics per cache key."""
    cache = Cache(work / "cache")
    out = {}
    for m in cache.entries("evaluate_qa"):
        d = Path(cache.materialize(m))
        out[m.key] = ((d / "predictions.parquet").read_bytes(), json.loads((d / "metrics.json").read_text()))
    return out


def _files(work: Path) -> dict[tuple[str, str | None, str], dict[str, str]]:
    """Every cache entry's files and their sha256, by (stage, scene, key)."""
    cache = Cache(work / "cache")
    stages = ("reconstruct", "distill", "tokenizer", "lora", "evaluate_qa")
    return {(m.stage, m.scene, m.key): {f.path: f.sha256 for f in m.files} for s in stages for m in cache.entries(s)}


@pytest.fixture(scope="module")
def twice(tiny_run, tmp_path_factory) -> tuple[Path, dict, dict, dict, dict]:
    """The shared tiny run, and the same command from scratch in a second workdir (same data)."""
    other = tmp_path_factory.mktemp("det") / "b"
    runs = [(_evaluation(tiny_run.work), _files(tiny_run.work))]
    _gdwm("run", f"workdir={other}", f"data.root={tiny_run.data}", *TINY)
    runs.append((_evaluation(other), _files(other)))
    return tiny_run.data, runs[0][0], runs[1][0], runs[0][1], runs[1][1]


def test_two_runs_from_scratch_give_the_same_bytes(twice):
    _, a, b, files_a, files_b = twice
    assert list(a) == list(b)  # one trial, the same cache key in both workdirs
    ((preds_a, metrics_a),), ((preds_b, metrics_b),) = a.values(), b.values()
    assert preds_a == preds_b
    assert metrics_a == metrics_b and metrics_a["count/answered"] == 24
    # and so is every stage's every file on the way: the trained models, the LoRA adapter and its card included
    assert len(files_a) == 7 and files_a == files_b


def test_the_same_trial_in_a_concurrent_sweep_gives_the_same_bytes(twice, tmp_path):
    data, alone = twice[:2]
    r = _gdwm("sweep", "sweep=tiny_concurrent", f"workdir={tmp_path}", f"data.root={data}")
    assert "sweep: 3 trials" in r.stdout
    swept = _evaluation(tmp_path)
    assert len(swept) == 3
    (key,) = alone
    assert swept[key] == alone[key]  # predictions bytes and metrics
    others = [v[0] for k, v in swept.items() if k != key]
    assert all(p != alone[key][0] for p in others)  # the other rows are other models
