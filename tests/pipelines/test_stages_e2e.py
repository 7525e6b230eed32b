"""The real reconstruct -> distill -> tokenizer -> lora stages through `gdwm run` on a small synthetic_mini, tiny
flavors."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter

import mlflow

from gdwm.cache import Cache


def test_gdwm_run_reconstruct_distill_tokenizer_lora(tmp_path):
    args = [
        sys.executable,
        "-m",
        "gdwm",
        "run",
        f"workdir={tmp_path}",
        "targets=[lora]",
        "stage/reconstruct=tiny",
        "stage/distill=tiny",
        "stage/tokenizer=tiny",
        "stage/lora=tiny",
        "data.num_scenes=2",
        "data.width=64",
        "data.height=36",
    ]
    r = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    assert "generating synthetic_mini" in r.stdout  # the data was absent and made first
    cache = Cache(tmp_path / "cache")
    rec, dis = cache.entries("reconstruct"), cache.entries("distill")
    assert sorted(m.scene for m in rec) == ["scene-0000", "scene-0001"] == sorted(m.scene for m in dis)
    assert all(any(f.path == "gaussians/00000.arrow" for f in m.files) for m in rec + dis)
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path.resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    runs = {x.data.tags.get("gdwm.stage"): x for x in client.search_runs([exp.experiment_id])}
    assert runs["reconstruct"].info.status == runs["distill"].info.status == "FINISHED"
    steps = [m.step for m in client.get_metric_history(runs["reconstruct"].info.run_id, "scene-0000/loss")]
    assert steps[:3] == [0, 10, 20]  # per-iteration losses with steps, per scene
    assert "scene-0001/heldout_l1_reduction" in runs["distill"].data.metrics
    assert len(client.get_metric_history(runs["distill"].info.run_id, "scene-0000/l_distill")) >= 3
    # stage 1 and stage 2: per-step losses, a saved world model, the held-out monitor
    tok_loss = client.get_metric_history(runs["tokenizer"].info.run_id, "loss")
    assert [m.step for m in tok_loss] == [0, 1, 2, 3]  # stage.tokenizer: tiny has 4 steps, logged every step
    (tok,), (lo,) = cache.entries("tokenizer"), cache.entries("lora")
    assert {"world.json", "adapter.pt", "llm/model.safetensors", "llm/tokenizer.json"} <= {f.path for f in tok.files}
    assert {"lora/adapter_model.safetensors", "val_predictions.parquet"} <= {f.path for f in lo.files}
    assert runs["lora"].data.metrics["val/loss_lm"] > 0
    assert runs["tokenizer"].data.metrics["skipped/train/instruction_without_gauss_placeholder"] == 1  # traj QA
    # a second run is all cache hits
    again = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "nothing to run" in again.stdout
    assert Counter(x.data.tags.get("gdwm.stage") for x in client.search_runs([exp.experiment_id]))["distill"] == 1
