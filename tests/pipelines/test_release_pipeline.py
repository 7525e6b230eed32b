"""The public GaussianDWM release end to end: a pipeline that starts from its Gaussians (no reconstruct, no distill),
plans that refuse, before launch, stages whose dataset tables the release lacks, and the ablation sweep on it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch

from gdwm.compare.runs import newest_per_row
from pipelines.data.gaussiandwm import ReleaseConfig, build
from pipelines.data.layout import held_tables
from pipelines.data.reader import GSQADataset, gaussians_from_table, read_arrow
from pipelines.data.synth.config import SynthConfig
from pipelines.stages.given import given_gaussians, identity_autoencoder
from pipelines.understanding.model import load_decoders
from tests.pipelines.data.fixtures_release import write_release

TINY = ["stage/tokenizer=tiny", "stage/lora=tiny", "stage/evaluate_qa=tiny", "model.llm.pretrain_steps=20"]


def _gdwm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A workdir holding the release fixture imported as ``gaussiandwm_release``."""
    tmp = tmp_path_factory.mktemp("release")
    release = write_release(tmp / "release")
    build(ReleaseConfig(), tmp / "w" / "data" / "gaussiandwm_release", str(release.root))
    return tmp / "w"


def test_a_dataset_records_the_tables_it_holds(work, synth_small):
    release = GSQADataset(work / "data" / "gaussiandwm_release")
    assert release.meta["tables"] == ["clip_text", "frames", "gaussians", "qa", "scenes", "world"]
    synth = GSQADataset(synth_small).meta["tables"]
    assert synth == ["boxes2d", "boxes3d", "cameras", "depth", "ego_poses", "frames", "images", "lidar", "qa",
                     "routes", "scenes"]  # fmt: skip
    assert held_tables(synth_small, GSQADataset(synth_small).meta["files"]) == synth  # recorded = what is there
    assert SynthConfig().tables == synth  # what a dry run assumes before generating it


def test_the_demo_pipeline_on_a_gaussians_only_dataset_is_refused_before_anything_starts(work):
    before = sorted(p.relative_to(work) for p in work.rglob("*"))
    r = _gdwm("run", "--dry-run", "experiment=demo", "data=gaussiandwm_release", f"workdir={work}")
    assert r.returncode == 2, r.stderr[-2000:]
    root = work / "data" / "gaussiandwm_release"
    assert (
        f"gdwm run: dataset 'gaussiandwm_release' at {root} (tables: clip_text, frames, gaussians, qa, scenes, "
        "world) lacks inputs:\n  stage 'reconstruct' needs 'cameras' (projects the Gaussians into every camera), "
        "'ego_poses' (places every frame's LiDAR and cameras in the scene), 'images' (fits the Gaussians to the "
        "camera images), 'lidar' (initialises the Gaussians from the aggregated LiDAR)\n"
    ) in r.stderr
    assert "  stage 'distill' needs 'cameras' (renders the features into every camera), 'images'" in r.stderr
    assert "stage 'tokenizer' needs 'ego_poses' (the driving-aware selector" in r.stderr
    assert "stage 'evaluate_gen' needs 'cameras'" in r.stderr and "Traceback" not in r.stderr
    # a launch is refused the same way, and neither wrote anything
    launch = _gdwm("run", "experiment=demo", "data=gaussiandwm_release", f"workdir={work}", "targets=[distill]")
    assert launch.returncode == 2 and "stage 'reconstruct' needs 'cameras'" in launch.stderr
    assert sorted(p.relative_to(work) for p in work.rglob("*")) == before


def test_the_journal_sweep_on_the_release_refuses_the_rows_it_cannot_feed(work):
    r = _gdwm("sweep", "--dry-run", "sweep=journal_ablation", "experiment=gaussiandwm_release", f"workdir={work}")
    assert r.returncode == 2, r.stderr[-2000:]
    err = r.stderr
    assert "sweep 'journal_ablation': dataset 'gaussiandwm_release'" in err
    assert "row '+ Alignment': stage 'tokenizer' needs 'images' (L_KL aligns the world tokens to the image" in err
    assert "row '+ Driving-Aware': stage 'tokenizer' needs 'ego_poses'" in err
    assert "row '+ Distillation (GaussianDWM++)': stage 'distill' needs 'cameras'" in err
    assert "row 'Voxel Top-K + Similarity'" not in err
    assert err.rstrip().endswith("run the other rows alone with \"sweep.only=['Voxel Top-K + Similarity']\"")


def test_sweep_only_keeps_the_rows_the_release_feeds_and_names_an_unknown_row(work):
    only = _gdwm("sweep", "--dry-run", "sweep=journal_ablation", "experiment=gaussiandwm_release", f"workdir={work}",
                 "sweep.only=['Voxel Top-K + Similarity']", *TINY)  # fmt: skip
    assert only.returncode == 0, only.stderr[-2000:]
    header = next(line for line in only.stdout.splitlines() if "trial" in line and "distill" in line)
    assert [c.strip() for c in header.split("┃")[1:-1]] == ["trial", "distill", "llm", "tokenizer", "lora",
                                                            "evaluate_qa"]  # fmt: skip
    bad = _gdwm("sweep", "--dry-run", "sweep=journal_ablation", "experiment=gaussiandwm_release", f"workdir={work}",
                "sweep.only=[nope]")  # fmt: skip
    assert bad.returncode == 2 and "sweep.only names no row ['nope'] (rows: ['Voxel Top-K + Similarity'," in bad.stderr


def test_the_given_stage_hands_on_the_releases_gaussians_and_codes_as_they_are(work, tmp_path):
    from gdwm.stage import StageContext
    from tests.pipelines.recon.test_reconstruct import Recorder

    data = work / "data" / "gaussiandwm_release"
    config = {"stage.distill": {"encoder": "langsplat", "feature_tokenizer": "langsplat3"}}
    out = tmp_path / "scene_0000"
    out.mkdir()
    ctx = StageContext("distill", "g" * 64, config, out, {}, data, "fp", Recorder(), tmp_path / "ck", {},
                       scene="scene_0000")  # fmt: skip
    metrics = given_gaussians.fn(ctx)
    src = sorted((data / "scenes" / "scene_0000" / "gaussians").glob("*.arrow"))
    assert [p.name for p in sorted((out / "gaussians").glob("*.arrow"))] == [p.name for p in src]
    assert all((out / "gaussians" / p.name).read_bytes() == p.read_bytes() for p in src)
    codes = gaussians_from_table(read_arrow(src[0], "frame 0"))["feature"]
    assert metrics["feature_dim"] == 3 and metrics["frames"] == len(src)
    (cfg, decoder), = load_decoders({"scene_0000": out}).values()  # fmt: skip
    with torch.no_grad():
        decoded = decoder(torch.from_numpy(np.asarray(codes, dtype=np.float32)))
    np.testing.assert_array_equal(decoded.numpy(), codes)  # D_F is the identity: the features are the codes
    assert (cfg.d_f, cfg.d_z) == (3, 3) and identity_autoencoder(4)[0].layers == 1


def test_the_newest_run_of_a_row_is_the_row():
    runs = [
        {"run_id": "a", "start_time": 1, "tags": {"gdwm.kind": "row", "gdwm.row": "x"}},
        {"run_id": "b", "start_time": 2, "tags": {"gdwm.kind": "row", "gdwm.row": "y"}},
        {"run_id": "c", "start_time": 3, "tags": {"gdwm.kind": "row", "gdwm.row": "x"}},
    ]
    assert [r["run_id"] for r in newest_per_row(runs)] == ["b", "c"]


GEN = ["stage/diffusion_vae=tiny", "stage/diffusion=tiny", "stage/evaluate_gen=tiny"]


def test_a_tiny_release_experiment_runs_through_evaluate_qa_and_evaluate_gen_on_local_ray(work):
    r = _gdwm("run", "experiment=gaussiandwm_release", f"workdir={work}", "targets=[evaluate_qa,evaluate_gen]", *TINY,
              *GEN)  # fmt: skip
    assert r.returncode == 0, r.stderr[-4000:]
    client = mlflow.MlflowClient(f"sqlite:///{work.resolve()}/mlflow.db")
    exp = client.get_experiment_by_name("gdwm")
    runs = {x.data.tags.get("gdwm.stage"): x for x in client.search_runs([exp.experiment_id])}
    stages = ("llm", "distill", "tokenizer", "lora", "evaluate_qa", "diffusion_vae", "diffusion", "evaluate_gen")
    assert set(stages) <= set(runs) and "reconstruct" not in runs
    assert all(runs[s].info.status == "FINISHED" for s in stages)
    ev = runs["evaluate_qa"].data.metrics
    assert ev["count/answered"] == 2  # the fixture's val QA: both frames have Gaussians
    assert 0 <= ev["nuinteract/rdp_bleu"] <= 100
    assert runs["tokenizer"].data.params["tasks/rdp"] == "2"  # training samples read the imported Gaussians
    assert runs["distill"].data.metrics["scene_0000/feature_dim"] == 3.0
    gen = runs["evaluate_gen"].data.metrics
    assert gen["count/heldout_samples"] == 1 and gen["count/heldout_views"] >= 1  # the one val world record
    assert 0 < gen["gen/world/psnr"] < 100 and 0 <= gen["gen/world/ssim"] <= 1
