"""The real stages through `gdwm run` on a small synthetic_mini, tiny flavors: reconstruct -> distill -> tokenizer
-> lora -> evaluate_qa, and lora -> diffusion -> evaluate_gen."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import mlflow
import pyarrow.parquet as pq
import pytest

from gdwm.cache import Cache
from tests.pipelines.conftest import TINY_RUN

pytestmark = pytest.mark.heavy(4)


# the real understanding branch from scratch, on the session's tiny run (tests/pipelines/conftest.py)
def test_gdwm_run_reconstruct_distill_tokenizer_lora_evaluate_qa(tiny_run):
    tmp_path = tiny_run.work  # the run of TINY_RUN from scratch (shared with test_determinism, which only reads it)
    assert "generating synthetic_mini" in tiny_run.stdout  # the data was absent and made first
    assert "QA per task family" in tiny_run.stdout and "on disk" in tiny_run.stdout  # and its summary printed
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
    (tok,), (lo,), (built,) = cache.entries("tokenizer"), cache.entries("lora"), cache.entries("llm")
    assert {"world.json", "adapter.pt", "llm/model.safetensors", "llm/tokenizer.json"} <= {f.path for f in tok.files}
    # the tiny LLM is its own stage, keyed by model.llm and the data only: the tokenizer starts from its weights
    assert {"llm/model.safetensors", "llm/tokenizer.json"} <= {f.path for f in built.files}
    assert tok.upstream["llm"] == built.key and set(built.config) == {"model.llm"}
    assert built.extra["instruction_pairs"] == runs["llm"].data.metrics["instruction_pairs"] > 0
    llm_files = {f.path: f.sha256 for f in built.files}
    assert {f.path: f.sha256 for f in tok.files}["llm/tokenizer.json"] == llm_files["llm/tokenizer.json"]
    assert {"lora/adapter_model.safetensors", "val_predictions.parquet"} <= {f.path for f in lo.files}
    # both trained world models are zoo versions of their stage runs, with lineage; the newest is the candidate
    (tok_v,), (lora_v,) = (client.search_model_versions(f"name = 'gdwm-{n}'") for n in ("tokenizer", "lora"))
    assert (tok_v.run_id, tok_v.tags["gdwm.cache_key"]) == (runs["tokenizer"].info.run_id, tok.key)
    assert tok_v.tags["gdwm.upstream.distill"] == tok.upstream["distill"]
    assert lora_v.tags["gdwm.upstream.tokenizer"] == tok.key
    assert lora_v.tags["gdwm.variant"] == "driving_aware+query_xattn+kl"
    assert client.get_registered_model("gdwm-lora").aliases == {"candidate": 1}
    assert runs["lora"].data.metrics["val/loss_lm"] > 0
    assert "skipped/train/instruction_without_gauss_placeholder" not in runs["tokenizer"].data.metrics
    assert runs["tokenizer"].data.params["tasks/traj"] == runs["lora"].data.params["tasks/traj"] == "1"
    # evaluate_qa: every answered sample in the Parquet artifact, the suites' metrics on the stage and the run
    (ev,) = cache.entries("evaluate_qa")
    assert {"predictions.parquet", "metrics.json", "protocol.json"} <= {f.path for f in ev.files}
    preds = pq.read_table(tmp_path / "cache" / "evaluate_qa" / ev.key[:2] / ev.key / "predictions.parquet")
    assert preds.num_rows == runs["evaluate_qa"].data.metrics["count/answered"] == 24  # stage.evaluate_qa: tiny
    assert set(preds["task"].to_pylist()) <= {"rdp", "vg2d", "vg3d", "plan", "traj"}
    assert "predictions.parquet" in {a.path for a in client.list_artifacts(runs["evaluate_qa"].info.run_id)}
    ev_metrics = {k: v for k, v in runs["evaluate_qa"].data.metrics.items() if not k.startswith("system/")}
    assert 0 <= ev_metrics["nuinteract/rdp_bleu"] <= 100 and "omnidrive/rouge_l" in ev_metrics
    (parent,) = client.search_runs([exp.experiment_id], "tags.`gdwm.kind` = 'run'")
    # the trial's metrics are the stage's scores; its counts are tags (gdwm.count/<name>), not metrics to plot
    scores = {k: v for k, v in ev_metrics.items() if not k.startswith("count/")}
    assert {k: v for k, v in parent.data.metrics.items() if "/" in k} == scores
    assert parent.data.tags["gdwm.count/answered"] == "24"
    assert [a.path for a in client.list_artifacts(parent.info.run_id, "evaluate_qa")] == [
        "evaluate_qa/predictions.parquet"
    ]


def test_a_rerun_is_all_cache_hits_and_lora_from_the_zoo_trains_nothing(tiny_run):
    tmp_path = tiny_run.work
    args = [sys.executable, "-m", "gdwm", "run", *tiny_run.args]
    cache = Cache(tmp_path / "cache")
    (lo,) = cache.entries("lora")
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path.resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    # a second run is all cache hits
    again = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "nothing to run" in again.stdout
    assert Counter(x.data.tags.get("gdwm.stage") for x in client.search_runs([exp.experiment_id]))["distill"] == 1
    assert len(client.search_model_versions("name LIKE 'gdwm-%'")) == 2  # a cache hit registers nothing
    # lora taken from the zoo: nothing trains, the pinned version's world model is the output, nothing is registered
    from_zoo_args = [a for a in args if a != "targets=[evaluate_qa]"]
    from_zoo_args += ["targets=[lora]", "stage.lora.source=zoo:gdwm-lora@candidate"]
    zoo = subprocess.run(from_zoo_args, capture_output=True, text=True, timeout=300)
    assert zoo.returncode == 0, zoo.stderr[-4000:]
    (from_zoo,) = [m for m in cache.entries("lora") if m.key != lo.key]
    assert from_zoo.config["stage.lora"]["source"] == "zoo:gdwm-lora/1" and from_zoo.extra["trained"] == 0.0
    lora_dir = tmp_path / "cache" / "lora"
    world = [(lora_dir / m.key[:2] / m.key / "world.json").read_text() for m in (lo, from_zoo)]
    assert world[0] == world[1] and len(client.search_model_versions("name LIKE 'gdwm-%'")) == 2


GEN = ["stage/diffusion_vae=tiny", "stage/diffusion=tiny", "stage/evaluate_gen=tiny"]


@pytest.fixture(scope="module")
def gen(tiny_run, tmp_path_factory) -> tuple[Path, list[str]]:
    """A copy of the tiny run's workdir (a workdir is relocatable) and the overrides of the generation branch on it:
    lora -> diffusion -> evaluate_gen over the tiny run's data, reconstruction, distillation, LLM, tokenizer and
    LoRA, which are cache hits there. The copy leaves the tiny run's own workdir as the other tests read it."""
    work = tmp_path_factory.mktemp("gen") / "w"
    shutil.copytree(tiny_run.work, work, symlinks=True)
    args = [
        f"workdir={work}",
        f"data.root={work / 'data'}",
        *(a for a in TINY_RUN if not a.startswith("targets=")),
        *GEN,
    ]
    return work, args


def _gdwm(*args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=timeout)


def _stage_runs(client: mlflow.MlflowClient, exp_id: str) -> Counter:
    return Counter(x.data.tags.get("gdwm.stage") for x in client.search_runs([exp_id]) if "gdwm.stage" in x.data.tags)


def test_diffusion_stage_then_generate_and_edit(gen):
    import json

    from pipelines.data.reader import GSQADataset

    tmp_path, args = gen
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path.resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    before = _stage_runs(client, exp.experiment_id)
    r = _gdwm("run", *args, "targets=[evaluate_gen]")
    assert r.returncode == 0, r.stderr[-4000:]
    # the understanding branch's stages were the tiny run's cache hits: only the generation branch ran
    assert _stage_runs(client, exp.experiment_id) - before == Counter(["diffusion_vae", "diffusion", "evaluate_gen"])
    cache = Cache(tmp_path / "cache")
    (entry,) = cache.entries("diffusion")
    assert {"unet/config.json", "vae/config.json", "rgbd.json", "null_token.pt", "metrics.json"} <= {
        f.path for f in entry.files
    }
    (ev,) = cache.entries("evaluate_gen")
    files = {f.path for f in ev.files}
    assert any(p.startswith("samples/shift_1m/") and p.endswith(".png") for p in files)
    metrics = json.loads((tmp_path / "cache" / "evaluate_gen" / ev.key[:2] / ev.key / "metrics.json").read_text())
    assert 0 < metrics["gen/shift_1m/psnr"] < 60 and metrics["gen/shift_-1m/depth_absrel"] >= 0
    assert metrics["count/heldout_views"] == 6  # 1 val scene x 2 frames x (2 shifts + 1 s ahead)
    (parent,) = client.search_runs([exp.experiment_id], "tags.`gdwm.kind` = 'run'", max_results=1,
                                   order_by=["attributes.start_time DESC"])  # fmt: skip
    assert parent.data.metrics["gen/future_1s/psnr"] == metrics["gen/future_1s/psnr"]

    g = _gdwm("generate", *args, "args.scene=scene-0001", "args.frame=1",
              "args.shifts_m=[-1,1]", "args.horizons_s=[1]")  # fmt: skip
    assert g.returncode == 0, g.stderr[-4000:]
    out = tmp_path / "generated" / "scene-0001_001_CAM_FRONT"
    assert sorted(p.name for p in out.glob("*.png")) == sorted(
        f"{n}{s}.png" for n in ("shift_-1m", "shift_1m", "future_1s") for s in ("", "_depth")
    )
    assert (out / "views.mp4").stat().st_size > 1000
    assert "gen/shift_1m/psnr" in g.stdout

    # remove the biggest vehicle in view: the edited region changes, the rest of the picture does not
    frame = GSQADataset(tmp_path / "data").scene("scene-0001").frame(1)  # data.root of the tiny run
    boxes = [b for b in frame.boxes2d("CAM_FRONT") if "ped" not in b["instance_id"]]
    vehicle = max(boxes, key=lambda b: (b["box"][2] - b["box"][0]) * (b["box"][3] - b["box"][1]))["instance_id"]
    e = _gdwm("edit", *args, "args.scene=scene-0001", "args.frame=1", "args.frames=2",
              f"args.edit=Remove vehicle {vehicle} from the scene.")  # fmt: skip
    assert e.returncode == 0, e.stderr[-4000:]
    (edit_dir,) = (tmp_path / "edits").iterdir()
    report = json.loads((edit_dir / "report.json").read_text())
    assert report["frames"] == [1, 2] and report["edited_pixels"] > 0
    assert report["mean_abs_change_in_edited_region"] > 2 * report["mean_abs_change_outside"]
    assert (edit_dir / "edited.mp4").is_file() and len(list(edit_dir.glob("edited_00?.png"))) == 2

    bad = _gdwm("edit", *args, "args.scene=scene-0001", "args.frame=1",
                "args.edit=Remove vehicle scene-0001-car-99 from the scene.")  # fmt: skip
    assert bad.returncode == 1
    assert "scene-0001/frame_001: no vehicle with instance id 'scene-0001-car-99'" in bad.stderr
    runs = mlflow.MlflowClient(f"sqlite:///{tmp_path.resolve()}/mlflow.db").search_runs(
        [mlflow.MlflowClient(f"sqlite:///{tmp_path.resolve()}/mlflow.db").get_experiment_by_name("gdwm").experiment_id],
        "tags.`gdwm.kind` = 'edit'",
    )
    assert len(runs) == 1 and runs[0].data.metrics["edit/change_inside"] == report["mean_abs_change_in_edited_region"]


def test_evaluate_gen_on_llm_predicted_trajectories(gen):
    """Future targets placed by the trajectory the LoRA'd LLM predicts from the 4 history frames (in the generation
    branch's workdir: the diffusion model is a cache hit when the test above made it)."""
    import json

    tmp_path, args = gen
    predicted = ["stage.evaluate_gen.future_poses=predicted", "stage.evaluate_gen.frames=6"]
    p = _gdwm("run", *args, "targets=[evaluate_gen]", *predicted)
    assert p.returncode == 0, p.stderr[-4000:]
    entries = Cache(tmp_path / "cache").entries("evaluate_gen")
    (ev,) = [m for m in entries if m.config["stage.evaluate_gen"]["future_poses"] == "predicted"]
    m = json.loads((tmp_path / "cache" / "evaluate_gen" / ev.key[:2] / ev.key / "metrics.json").read_text())
    pred_views = sum(f.path.startswith("samples/future_pred_1s/") for f in ev.files)
    # the val scene's one trajectory question (reference frame 4 < 6), one horizon: a view or a counted miss
    assert pred_views + m["count/trajectory_without_pose_at_horizon"] == 1
    assert not any(f.path.startswith("samples/future_1s/") for f in ev.files)  # recorded poses not used
