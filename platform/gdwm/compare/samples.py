"""Per-sample predictions of the trials, for the bootstrap: the artifacts and scorers their tags name.

A trial (or a single-seed run) that kept evaluation stage S's predictions carries
``gdwm.samples.<S>=<artifact path>`` (a Parquet table with a ``sample_id`` column) and
``gdwm.scorer.<S>=<module>:<function>``, ``function(pyarrow.Table) -> {metric: value}`` recomputing S's metrics
from any subset of the rows. The scorer is imported by the name in the tag: the platform names no pipeline package.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

import pyarrow.parquet as pq

from gdwm.compare.runs import Row, Trial
from gdwm.compare.stats import SampleSet
from gdwm.tracking import TrackingBackend

SAMPLES_PREFIX = "gdwm.samples."
SCORER_PREFIX = "gdwm.scorer."
STRATA_PREFIX = "gdwm.strata."
ID_COLUMN = "sample_id"
PROGRESS_BAR = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"


@contextmanager
def quiet_downloads() -> Iterator[None]:
    """No progress bar per download (one per trial and stage would bury the table); MLflow reads it per call."""
    old = os.environ.get(PROGRESS_BAR)
    os.environ[PROGRESS_BAR] = "false"
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(PROGRESS_BAR, None)
        else:
            os.environ[PROGRESS_BAR] = old


@cache
def scorer(spec: str) -> Callable:
    """The function ``module:qualname`` (or ``module.function``) names."""
    module, sep, name = spec.partition(":") if ":" in spec else spec.rpartition(".")
    if not (module and sep and name):
        raise ValueError(f"scorer '{spec}' is not <module>:<function>")
    fn = importlib.import_module(module)
    for part in name.split("."):  # a qualname may name a function inside a class
        fn = getattr(fn, part, None)
    if not callable(fn):
        raise ValueError(f"scorer '{spec}': module {module} has no function {name}")
    return fn


def _load(backend: TrackingBackend, trial: Trial, stage: str, path: str, dst: Path) -> SampleSet:
    spec = trial.tags.get(SCORER_PREFIX + stage)
    if not spec:
        raise ValueError(f"no tag {SCORER_PREFIX}{stage} names the function that scores them")
    fn = scorer(spec)
    with quiet_downloads():
        local = backend.client.download_artifacts(trial.run_id, path, str(dst / trial.run_id))
    return sample_set(local, fn, trial.tags.get(STRATA_PREFIX + stage), path)


def sample_set(local: str | Path, fn: Callable, strata: str | None, name: str) -> SampleSet:
    """A downloaded per-sample table as the statistics take it (read into memory: the folder may be temporary)."""
    table = pq.read_table(local)
    for col in (ID_COLUMN, strata):
        if col and col not in table.column_names:
            raise ValueError(f"{name} has no column '{col}' (columns: {', '.join(table.column_names)})")
    groups = table.column(strata).to_pylist() if strata else None
    return SampleSet(table.column(ID_COLUMN).to_pylist(), table, fn, groups)


def load_samples(backend: TrackingBackend, rows: list[Row], dst: Path) -> list[str]:
    """Fill ``samples`` of every counted trial of the rows that did not fail, downloading into ``dst``.

    Returns one line per sample set that could not be read; the statistics then fall back to the seeds for it, so
    a deleted artifact or a renamed scorer costs the intervals, not the table."""
    problems = []
    for row in rows:
        if row.failed:
            continue
        for trial in row.counted:
            for key, path in trial.tags.items():
                if not key.startswith(SAMPLES_PREFIX):
                    continue
                stage = key[len(SAMPLES_PREFIX) :]
                try:
                    trial.samples[stage] = _load(backend, trial, stage, path, dst)
                except Exception as e:  # any unreadable set degrades to seed-level statistics
                    seed = "" if trial.seed is None else f" seed {trial.seed}"
                    problems.append(
                        f"row {row.label}{seed} (run {trial.run_id}), {key}={path}: {type(e).__name__}: {e}"
                    )
    return problems
