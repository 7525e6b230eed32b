"""A synthetic MLflow store for the ``gdwm compare`` tests, in the layout ``gdwm run`` and the sweep write.

- sweep ``abl`` (the latest of that name): one row run per row (``gdwm.kind=row``, ``gdwm.seeds=0,1,2``) with a
  trial run per seed; D lost seed 2, F kept only seed 0, every trial of E failed (E is FAILED); the row runs log a
  stale aggregate (-1.0) so a test sees the table read the trials;
- an older sweep ``abl`` from before seeds: a trial directly under the sweep (a row of one trial);
- a stage run with a loss curve linked to A's seed-0 trial, a stage run that is no row;
- a single-seed plain ``gdwm run`` that kept its 96 QA predictions (``gdwm.samples.evaluate_qa``) and names
  ``accuracy`` below as their scorer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from gdwm.tracking import TrackingBackend

EXPERIMENT = "gdwm"  # the default tracking.experiment, so the CLI finds it with workdir=... alone

METRICS = ("nuinteract/rdp_bleu", "nuinteract/vg2d_map", "nuinteract/avg", "nuinstruct/mae", "nuinteract/plan_acc")
SEEDS = (0, 1, 2)
# label -> (factors, per seed: values of METRICS, None = not logged; a missing seed failed). Expected marks
# (test_compare, Welch's t-test over seeds, alpha 0.05): BLEU C and B best (p = 0.55), D second; 2D mAP B and D
# best (equal means), A second; MAE (lower) B best, D second, A and C none; Avg D best, C and B second (p = 0.32);
# plan_acc is 0 everywhere: no marks; F (one seed of three) is highest everywhere and takes no mark.
ROWS = {
    "A": (
        {"Coarse Selection": "Voxel Top-K", "Alignment": "none"},
        {0: (60.0, 34.0, 59.0, 3.0, 0.0), 1: (61.0, 36.0, 59.5, 3.05, 0.0), 2: (60.5, 35.0, 59.2, 3.1, 0.0)},
    ),
    "B": (
        {"Coarse Selection": "Voxel Top-K", "Alignment": "KL"},
        {0: (69.0, 48.0, 61.0, 2.4, 0.0), 1: (70.5, 49.0, 61.5, 2.5, 0.0), 2: (69.8, 48.5, 61.2, 2.45, 0.0)},
    ),
    "C": (
        {"Coarse Selection": "Driving-Aware", "Alignment": "KL"},
        {0: (70.2, None, 61.3, 3.05, 0.0), 1: (69.4, None, 61.6, 3.0, 0.0), 2: (70.9, None, 61.4, 3.1, 0.0)},
    ),
    "D": (
        {"Coarse Selection": "Driving-Aware", "Alignment": "KL & 50%_x"},
        {0: (65.0, 47.5, 62.7, 2.70, 0.0), 1: (65.6, 49.5, 62.8, 2.71, 0.0)},
    ),
    "E": ({"Coarse Selection": "Driving-Aware", "Alignment": "none"}, {}),
    "F": ({"Coarse Selection": "Voxel Top-K", "Alignment": "KL & 50%_x"}, {0: (75.0, 50.0, 65.0, 2.0, 0.0)}),
}
E_LOGGED = {"nuinteract/rdp_bleu": 99.0}
"""What E's seed 0 logged before it failed: shown dimmed, never marked."""
LOSS = [2.0, 1.5, 1.2, 1.0]
N_SAMPLES = 96
CORRECT = (np.random.default_rng(0).random(N_SAMPLES) < 0.6).astype(np.int64)
"""The plain run's per-sample 0/1 answers."""


def accuracy(table: pa.Table, wanted=None) -> dict[str, float]:
    """The scorer the plain run's tag names: NuInteract Avg. = 100 x the mean of the 0/1 ``correct`` column."""
    return {"nuinteract/avg": 100.0 * pc.mean(table.column("correct")).as_py()}


@dataclass
class Store:
    workdir: Path
    uri: str
    experiment_id: str
    sweep_id: str
    rows: dict[str, str]
    """label -> row run id."""
    trials: dict[str, dict[int, str]]
    """label -> seed -> trial run id."""
    old_trial: str
    plain_run: str
    stage_run: str

    def backend(self) -> TrackingBackend:
        return TrackingBackend(self.uri, EXPERIMENT, str(self.workdir / "mlartifacts"))


def _plain_run(b: TrackingBackend, workdir: Path) -> str:
    run = b.create_run(
        "run-gaussiandwm_pp",
        {
            "gdwm.kind": "run",
            "gdwm.seed": "0",
            "gdwm.samples.evaluate_qa": "evaluate_qa/predictions.parquet",
            "gdwm.scorer.evaluate_qa": f"{__name__}:accuracy",
        },
    )
    b.log_params(run, {"model": {"selector": {"name": "driving_aware"}}})
    predictions = pa.table({"sample_id": [f"val-{i:03d}" for i in range(N_SAMPLES)], "correct": CORRECT})
    local = workdir / "predictions.parquet"
    pq.write_table(predictions, local)
    b.log_artifact(run, str(local), "evaluate_qa")
    b.log_metrics(run, {**accuracy(predictions), "gen/shift_1m/fid": 9.5})
    b.end_run(run)
    return run


def log_store(workdir: Path) -> Store:
    """Everything the tests compare, written with the same backend ``gdwm run`` uses."""
    b = TrackingBackend(f"sqlite:///{workdir}/mlflow.db", EXPERIMENT, str(workdir / "mlartifacts"))
    old = b.create_run("sweep-abl-old", {"gdwm.kind": "sweep", "gdwm.sweep": "abl"})  # earlier: not picked
    old_trial = b.create_run("trial-old", {"gdwm.kind": "trial", "gdwm.row": "old"}, parent_run_id=old)
    b.log_metrics(old_trial, {"nuinteract/avg": 40.0})
    b.end_run(old_trial)
    b.end_run(old)
    time.sleep(0.01)  # start times are in ms: the newer sweep must start later
    sweep = b.create_run("sweep-abl", {"gdwm.kind": "sweep", "gdwm.sweep": "abl"})
    rows, trials = {}, {}
    for index, (label, (factors, seeds)) in enumerate(ROWS.items()):
        common = {"gdwm.row": label, "gdwm.sweep": "abl"} | {f"gdwm.factor.{k}": v for k, v in factors.items()}
        row = b.create_run(
            f"row-{label}",
            common | {"gdwm.kind": "row", "gdwm.trial_index": str(index), "gdwm.seeds": "0,1,2"},
            parent_run_id=sweep,
        )
        trials[label] = {}
        for seed in SEEDS:
            trial = b.create_run(f"trial-{label}-{seed}", common | {"gdwm.kind": "trial", "gdwm.seed": str(seed)}, row)
            if seed in seeds:
                b.log_metrics(trial, {m: v for m, v in zip(METRICS, seeds[seed], strict=True) if v is not None})
                b.end_run(trial)
            else:
                b.set_tags(trial, {"gdwm.failed_stage": "lora", "gdwm.error": "RuntimeError: CUDA out of memory\n..."})
                if label == "E" and seed == 0:
                    b.log_metrics(trial, E_LOGGED)
                b.end_run(trial, "FAILED")
            trials[label][seed] = trial
        b.log_metrics(row, dict.fromkeys(METRICS, -1.0))  # a stale aggregate: compare must read the trials
        b.end_run(row, "FINISHED" if seeds else "FAILED")
        rows[label] = row
    b.system_metrics_interval_s = 0  # no sampler thread on the test's stage run
    stage = b.create_run("lora-1234", {"gdwm.stage": "lora", "gdwm.kind": "stage", "gdwm.trial": trials["A"][0]}, sweep)
    for step, loss in enumerate(LOSS):
        b.log_metrics(stage, {"loss": loss, "system/cpu_utilization_percentage": 50.0}, step=step)
    b.log_metrics(stage, {"lora_final": 1.0})
    b.end_run(stage)
    b.end_run(sweep)
    plain = _plain_run(b, workdir)
    return Store(workdir, b.uri, b.experiment_id, sweep, rows, trials, old_trial, plain, stage)
