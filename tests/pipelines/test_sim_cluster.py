"""The real pipelines on ``cluster=sim``: their training groups get fake GPUs (Ray resources without CUDA here) and
run their CPU kernels; the understanding branch and the diffusion model train with 2 workers across the sim's nodes.
"""

from __future__ import annotations

from pathlib import Path

import mlflow
import pytest
import torch

from gdwm.cache import Cache
from tests.gdwm.test_cluster_sim import _placement
from tests.pipelines.conftest import TINY_RUN, gdwm_cli

pytestmark = pytest.mark.heavy(2.5)

GEN = ["stage/diffusion_vae=tiny", "stage/diffusion=tiny"]


@pytest.mark.timeout(1800)
def test_tiny_pipelines_train_on_the_sim_clusters_fake_gpus(tmp_path):
    work = tmp_path / "w"
    targets = "targets=[evaluate_qa,diffusion]"
    r = gdwm_cli("run", f"workdir={work}", f"data.root={work / 'data'}", *TINY_RUN, *GEN, targets, "cluster=sim",
                 "run.live=false", timeout=1700)  # fmt: skip
    assert "head + 2 worker node(s) x 2 CPU, 2 GPU, token auth on" in r.stdout
    if not torch.cuda.is_available():
        assert "stages placed on GPUs run their CPU kernels" in r.stdout
    placed = _placement(r.stdout)
    # tokenizer, lora and diffusion: a Ray Train group of 2 workers (1 fake GPU each) per stage
    assert sum(p.get("RayTrainWorker", 0) for p in placed.values()) == 6, placed
    client = mlflow.MlflowClient(f"sqlite:///{work.resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    runs = {
        r.data.tags["gdwm.stage"]: r for r in client.search_runs([exp.experiment_id]) if "gdwm.stage" in r.data.tags
    }
    assert {"tokenizer", "lora", "evaluate_qa", "diffusion_vae", "diffusion"} <= set(runs)
    assert {r.info.status for r in runs.values()} == {"FINISHED"}
    assert {r.data.tags["gdwm.cluster"] for r in runs.values()} == {"sim"}
    for stage in ("tokenizer", "lora", "diffusion"):
        world = client.download_artifacts(runs[stage].info.run_id, "train/world.txt", str(tmp_path / stage))
        assert Path(world).read_text() == "world_size=2", stage
    assert len(Cache(work / "cache").entries("evaluate_qa")) == 1
