"""Every row of an ablation table trains on the same task families: trajectory QA carries the <gauss> placeholder
like every other family, and the understanding stages log the samples per family as the params ``tasks/<family>``."""

from __future__ import annotations

import shutil
from dataclasses import asdict
from pathlib import Path

import pytest

from gdwm.stage import StageContext, UpstreamOutput
from model_zoo.adapter import FineAdapterConfig, ProjectionConfig
from model_zoo.alignment import AlignmentConfig
from model_zoo.llm.qwen3_vl import LLMConfig
from model_zoo.selectors import SelectorConfig
from pipelines.data.layout import GAUSS_TOKEN, TASKS
from pipelines.data.reader import GSQADataset
from pipelines.stages.llm import llm
from pipelines.stages.tokenizer import tokenizer
from pipelines.understanding.config import TokenizerStageConfig, WorldConfig
from pipelines.understanding.data import gaussians_path
from tests.pipelines.recon.test_reconstruct import Recorder
from tests.pipelines.understanding.conftest import make_distilled


def test_trajectory_qa_reads_the_scene_through_the_gauss_placeholder(synth_small):
    qa = GSQADataset(synth_small).qa().to_pylist()
    traj = [r for r in qa if r["task"] == "traj"]
    assert traj
    for r in traj:
        human = next(c["value"] for c in r["conversations"] if c["from"] == "human")
        assert human.startswith(f"Based on {GAUSS_TOKEN}, there are last 4 frames of ego trajectory: [PT, ")
        assert human.count(GAUSS_TOKEN) == 1


@pytest.fixture(scope="module")
def distilled_one_frame_excluded(synth_small, tmp_path_factory) -> dict[str, Path]:
    """Distilled scenes with one training frame excluded by QC (no Gaussian file), as reconstruction QC leaves it."""
    dirs = make_distilled(synth_small, tmp_path_factory.mktemp("distilled"), d_z=4, points=50)
    ds = GSQADataset(synth_small)
    train_frames = sorted({(r["scene_token"], r["frame_idx"]) for r in ds.qa(split="train").to_pylist()})
    scene, frame = train_frames[len(train_frames) // 2]
    gaussians_path(dirs[scene], frame).unlink()
    return dirs


TINY_LLM = LLMConfig(tiny=True, hidden_size=32, intermediate_size=64, pretrain_steps=0)


def run_llm_stage(data: Path, out: Path) -> UpstreamOutput:
    """The llm stage in-process: the tiny LLM the tokenizer stage starts from."""
    config = {"model.llm": asdict(TINY_LLM)}
    ctx = StageContext("llm", "l" * 64, config, out, {}, data, "fp", Recorder(), out / "ck", {})
    out.mkdir(parents=True)
    return UpstreamOutput("llm", "l" * 64, out, llm.fn(ctx))


def run_tokenizer_stage(data: Path, dirs: dict[str, Path], out: Path, gaussian_tokens: bool) -> Recorder:
    """The tokenizer stage in-process with no steps (nothing trains, so no Ray); its tracker records the params."""
    built = run_llm_stage(data, out.with_name(out.name + "-llm"))
    config = {
        "model.world": asdict(WorldConfig(gaussian_tokens=gaussian_tokens)),
        "model.selector": asdict(SelectorConfig(name="driving_aware", k_c=16)),
        "model.projection": asdict(ProjectionConfig(fourier_features=2)),
        "model.fine_adapter": asdict(FineAdapterConfig(name="query_xattn", k_f=4, heads=2)),
        "model.alignment": asdict(AlignmentConfig(name="kl")),
        "model.llm": asdict(TINY_LLM),
        "stage.tokenizer": asdict(TokenizerStageConfig(steps=0, eval_samples=0)),
    }
    rec = Recorder()
    up = {"llm": built, "distill": UpstreamOutput("distill", "d" * 64, None, {}, dirs)}
    ctx = StageContext("tokenizer", "t" * 64, config, out, up, data, "fp", rec, out / "ck", {}, seed=0)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    tokenizer.fn(ctx)
    return rec


def test_gaussian_and_image_only_rows_train_on_the_same_task_families(
    synth_small, distilled_one_frame_excluded, tmp_path
):
    rows = {
        g: run_tokenizer_stage(synth_small, distilled_one_frame_excluded, tmp_path / str(g), gaussian_tokens=g)
        for g in (True, False)
    }
    gaussian = {k: v for k, v in rows[True].params.items() if k.startswith("tasks/")}
    image_only = {k: v for k, v in rows[False].params.items() if k.startswith("tasks/")}
    assert gaussian == image_only
    assert sorted(gaussian) == sorted(f"tasks/{t}" for t in TASKS) and gaussian["tasks/traj"] > 0
    ds = GSQADataset(synth_small)
    on_disk = [r for r in ds.qa(split="train").to_pylist()]
    kept = [
        r for r in on_disk if gaussians_path(distilled_one_frame_excluded[r["scene_token"]], r["frame_idx"]).is_file()
    ]
    assert 0 < len(kept) < len(on_disk)  # the QC-excluded frame's samples are left out of both rows alike
    assert sum(gaussian.values()) == len(kept)
    assert {t: sum(r["task"] == t for r in kept) for t in TASKS} == {k[len("tasks/") :]: v for k, v in gaussian.items()}
