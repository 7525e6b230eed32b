"""The cluster path in one run: a toy sweep on ``cluster=sim`` (head + 2 worker nodes, token auth), its cache on a
loopback S3 (moto, credentials from the environment) and its tracking on a loopback MLflow server with basic-auth,
against the same sweep on ``cluster=local`` with the local cache and sqlite store: the same cache entries, byte for
byte, and the same numbers; stages ran on both nodes (from Ray's actor table, the ``sim placement:`` line).

The short checks of each part stay in ``make test``: test_cluster_sim.py (the 2-node sim and its token),
test_cache_s3.py (the cache on moto), test_capacity.py (shapes).
"""

from __future__ import annotations

import mlflow
import pytest

from gdwm.cache import Cache
from tests.gdwm.servers import BUCKET, Moto, mlflow_auth_server
from tests.gdwm.test_cluster_sim import SIM, _placement
from tests.gdwm.test_run import Toy, _ok
from tests.gdwm.test_sweep import _sweep

pytestmark = pytest.mark.heavy(3.5)

STAGES = ("reconstruct", "distill", "tokenizer", "lora", "evaluate_qa")


def _entries(cache: Cache) -> dict[str, list]:
    """Stage -> its entries' (key, scene, files with size and sha256)."""
    return {s: sorted((m.key, m.scene, m.files) for m in cache.entries(s)) for s in STAGES}


@pytest.mark.timeout(1500)
def test_toy_sweep_on_sim_with_s3_and_an_auth_server_equals_the_local_sweep(tmp_path, monkeypatch):
    moto = Moto()
    moto.client().create_bucket(Bucket=BUCKET)
    (tmp_path / "mlflow").mkdir()
    try:
        with mlflow_auth_server(tmp_path / "mlflow") as server:
            sim = Toy(tmp_path / "sim")
            # secrets travel in the environment only: nothing on the command line names them
            env = {**moto.env(), **server.creds("trainer"), "GDWM_LOCAL_CACHE": str(tmp_path / "s3-copies")}
            r = _sweep(sim, "sweep=toy_ablation", *SIM, "tracking=server", f"cache.uri=s3://{BUCKET}/sweep", **env)
            _ok(r)
            assert server.trainer_password not in r.stdout + r.stderr and moto.env()["AWS_SECRET_ACCESS_KEY"] not in (
                r.stdout + r.stderr
            )
            assert "head + 2 worker node(s) x 2 CPU, 2 GPU, token auth on" in r.stdout
            assert "sweep: 3 trials, 9 stage executions run (15 as independent runs without a cache)" in r.stdout
            placed = _placement(r.stdout)
            assert sorted(placed) == ["sim-worker-1", "sim-worker-2"]
            assert all(p.get("SceneWorker", 0) >= 1 for p in placed.values()), placed  # per-scene stages: both
            # the tokenizer and the three LoRA trainings: groups of 2 workers each
            assert sum(p.get("RayTrainWorker", 0) for p in placed.values()) == 8
            assert not (sim.work / "cache").exists()  # nothing went to the local default
            for k, v in {**server.creds("admin"), **moto.env()}.items():  # this process reads both stores too
                monkeypatch.setenv(k, v)
            client = mlflow.MlflowClient(server.uri)
            exp = client.get_experiment_by_name("gdwm")
            remote = client.search_runs([exp.experiment_id], max_results=1000)
        s3_entries = _entries(Cache(moto.uri("sweep")))
    finally:
        moto.stop()

    local = Toy(tmp_path / "local")
    _ok(_sweep(local, "sweep=toy_ablation"))
    assert s3_entries == _entries(Cache(local.work / "cache"))
    assert [len(s3_entries[s]) for s in STAGES] == [3, 3, 1, 3, 3]  # per-scene: one entry per scene

    def by_kind(runs, kind):
        return [r for r in runs if r.data.tags.get("gdwm.kind") == kind]

    assert {r.info.status for r in remote} == {"FINISHED"}  # nothing RUNNING, nothing failed
    kinds = {k: len(by_kind(remote, k)) for k in ("sweep", "row", "trial", "stage")}
    assert kinds == {"sweep": 1, "row": 3, "trial": 3, "stage": 9}  # no run twice
    mine = {r.data.tags["gdwm.row"]: r.data.metrics for r in by_kind(remote, "trial")}
    theirs = {r.data.tags["gdwm.row"]: r.data.metrics for r in local.runs("trial")}
    assert mine == theirs and {k: v["acc"] for k, v in mine.items()} == {"rank 2": 24.0, "rank 4": 48.0, "rank 8": 96.0}
    clusters = {r.data.tags["gdwm.stage"]: r.data.tags.get("gdwm.cluster") for r in by_kind(remote, "stage")}
    assert set(clusters.values()) == {"sim"}
