"""A synthetic MLflow store for the ``gdwm compare`` tests: one sweep of five trials (one missing a metric, one
FAILED), a stage run with a loss curve, a plain ``gdwm run`` and a stage run that is no row."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from gdwm.tracking import TrackingBackend

EXPERIMENT = "gdwm"  # the default tracking.experiment, so the CLI finds it with workdir=... alone

METRICS = ("nuinteract/rdp_bleu", "nuinteract/vg2d_map", "nuinteract/avg", "nuinstruct/mae")
# label -> (factors, values of METRICS; None = not logged). Expected marks (test_compare): BLEU C best, B and D tie
# second; 2D mAP B, D (C missing); MAE (lower) B, D (A and C tie at 3.08); Avg D, C. E failed with the top BLEU.
TRIALS = {
    "A": ({"Coarse Selection": "Voxel Top-K", "Alignment": "none"}, (68.78, 34.95, 59.23, 3.08)),
    "B": ({"Coarse Selection": "Voxel Top-K", "Alignment": "KL"}, (69.97, 48.59, 61.24, 2.41)),
    "C": ({"Coarse Selection": "Driving-Aware", "Alignment": "KL"}, (70.19, None, 61.37, 3.08)),
    "D": ({"Coarse Selection": "Driving-Aware", "Alignment": "KL & 50%_x"}, (69.97, 48.10, 62.71, 2.90)),
    "E": ({"Coarse Selection": "Driving-Aware", "Alignment": "none"}, (99.0, None, None, None)),
}
LOSS = [2.0, 1.5, 1.2, 1.0]


@dataclass
class Store:
    workdir: Path
    uri: str
    experiment_id: str
    sweep_id: str
    trials: dict[str, str]
    """label -> run id."""
    plain_run: str
    stage_run: str

    def backend(self) -> TrackingBackend:
        return TrackingBackend(self.uri, EXPERIMENT, str(self.workdir / "mlartifacts"))


def log_store(workdir: Path) -> Store:
    """Everything the tests compare, written with the same backend ``gdwm run`` uses."""
    b = TrackingBackend(f"sqlite:///{workdir}/mlflow.db", EXPERIMENT, str(workdir / "mlartifacts"))
    old = b.create_run("sweep-abl-old", {"gdwm.kind": "sweep", "gdwm.sweep": "abl"})  # earlier: not picked
    b.end_run(b.create_run("trial-old", {"gdwm.kind": "trial", "gdwm.row": "old"}, parent_run_id=old))
    b.end_run(old)
    time.sleep(0.01)  # start times are in ms: the newer sweep must start later
    sweep = b.create_run("sweep-abl", {"gdwm.kind": "sweep", "gdwm.sweep": "abl"})
    trials = {}
    for index, (label, (factors, values)) in enumerate(TRIALS.items()):
        tags = {"gdwm.kind": "trial", "gdwm.row": label, "gdwm.trial_index": str(index)}
        tags |= {f"gdwm.factor.{k}": v for k, v in factors.items()}
        if label == "E":
            tags |= {"gdwm.failed_stage": "lora", "gdwm.error": "RuntimeError: CUDA out of memory\ntraceback..."}
        run_id = b.create_run(f"trial-{label}", tags, parent_run_id=sweep)
        b.log_metrics(run_id, {m: v for m, v in zip(METRICS, values, strict=True) if v is not None})
        b.end_run(run_id, "FAILED" if label == "E" else "FINISHED")
        trials[label] = run_id
    b.system_metrics_interval_s = 0  # no sampler thread on the test's stage run
    stage = b.create_run("lora-1234", {"gdwm.stage": "lora", "gdwm.kind": "stage", "gdwm.trial": trials["A"]}, sweep)
    for step, loss in enumerate(LOSS):
        b.log_metrics(stage, {"loss": loss, "system/cpu_utilization_percentage": 50.0}, step=step)
    b.log_metrics(stage, {"lora_final": 1.0})
    b.end_run(stage)
    b.end_run(sweep)
    plain = b.create_run("run-gaussiandwm_pp", {"gdwm.kind": "run"})
    b.log_params(plain, {"model": {"selector": {"name": "driving_aware"}}})
    b.log_metrics(plain, {"nuinteract/avg": 50.0, "gen/shift_1m/fid": 9.5})
    b.end_run(plain)
    return Store(workdir, b.uri, b.experiment_id, sweep, trials, plain, stage)
