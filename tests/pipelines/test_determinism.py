"""A trial is bit-identical wherever it runs: from scratch alone (the session's tiny run), and from scratch again in
another workdir as one of three trials of a sweep running side by side (the real stages, tiny flavors, local Ray on
2 CPUs): every file of every stage entry, the predictions and the metrics."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gdwm.cache import Cache
from tests.pipelines.conftest import gdwm_cli as _gdwm

pytestmark = pytest.mark.heavy(3)

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
def swept(tiny_run, tmp_path_factory) -> tuple[Path, str]:
    """The tiny run's trial from scratch again, in another workdir (same data), as one of the three trials of a sweep
    running side by side: its first row is the tiny run's config."""
    work = tmp_path_factory.mktemp("det") / "sweep"
    r = _gdwm("sweep", "sweep=tiny_concurrent", f"workdir={work}", f"data.root={tiny_run.data}")
    return work, r.stdout


def test_the_trial_from_scratch_again_gives_the_same_bytes_in_every_entry(tiny_run, swept):
    alone, again = _files(tiny_run.work), _files(swept[0])
    # one trial alone: 2 scenes reconstructed and distilled, the tokenizer, LoRA and evaluation; the same keys
    # in the sweep's workdir (its other rows add entries of their own), every file of each the same bytes
    assert len(alone) == 7 and {k: again.get(k) for k in alone} == alone


def test_the_same_trial_in_a_concurrent_sweep_gives_the_same_predictions_and_metrics(tiny_run, swept):
    work, stdout = swept
    alone = _evaluation(tiny_run.work)
    assert "sweep: 3 trials" in stdout
    swept_eval = _evaluation(work)
    assert len(swept_eval) == 3
    (key,) = alone
    ((preds, metrics),) = alone.values()
    assert metrics["count/answered"] == 24
    assert swept_eval[key] == (preds, metrics)  # predictions bytes and metrics
    others = [v[0] for k, v in swept_eval.items() if k != key]
    assert all(p != preds for p in others)  # the other rows are other models
