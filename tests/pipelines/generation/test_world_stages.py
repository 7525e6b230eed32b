"""The release's generation branch in-process: world_vae -> world_diffusion -> world_evaluate_gen on the release
fixture, with a real world model (the tiny LLM and a tokenizer output with no steps) and distilled release scenes."""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import asdict
from pathlib import Path

import cv2
import pytest
import torch

from gdwm.stage import StageContext, UpstreamOutput
from model_zoo.adapter import FineAdapterConfig, ProjectionConfig
from model_zoo.alignment import AlignmentConfig
from model_zoo.config import DiffusionConfig
from model_zoo.diffusion.rgbd_dual import RGBDDual
from model_zoo.selectors import SelectorConfig
from pipelines.data.layout import DataError
from pipelines.evaluate.config import EvaluateGenConfig
from pipelines.generation.config import DiffusionStageConfig, VaeStageConfig
from pipelines.generation.world import KIND, clip_conditions, world_clips
from pipelines.stages.tokenizer import tokenizer
from pipelines.stages.world import NOT_COMPUTED, world_diffusion, world_evaluate_gen, world_vae
from pipelines.understanding.config import TokenizerStageConfig, WorldConfig
from pipelines.understanding.model import load_world_model
from tests.pipelines.data.test_task_families import TINY_LLM, run_llm_stage
from tests.pipelines.recon.test_reconstruct import Recorder

HW = (16, 24)
MODEL = DiffusionConfig(image_size=HW, unet_channels=(16, 32), vae_channels=(8, 16),
                        cross_attention_dim=TINY_LLM.hidden_size, sample_steps=2)  # fmt: skip
LOCAL = {"num_workers": 0, "num_cpus": 1}  # Ray Train in-process


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny kernels gain nothing from 2 threads and stall badly when other jobs share the cores."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


class Tracker(Recorder):
    """Also keeps the artifacts and texts a training or evaluation stage logs."""

    def __init__(self):
        super().__init__()
        self.artifacts, self.texts = [], {}

    def log_artifact(self, path):
        self.artifacts.append(path)

    def log_text(self, text, name):
        self.texts[name] = text


def _ctx(name: str, config: dict, out: Path, upstream: dict, data: Path, **kw) -> StageContext:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    ck = out.with_name(out.name + "-ck")
    return StageContext(name, name[0] * 64, config, out, upstream, data, "fp", Tracker(), ck, LOCAL,
                        train_settings={"checkpoint_every": 1000, "max_failures": 0}, deterministic=False,
                        **kw)  # fmt: skip


@pytest.fixture(scope="module")
def world_model(release_world, tmp_path_factory) -> UpstreamOutput:
    """A tokenizer output with no steps on the release (a saved world model, as the lora stage's output is): Gaussian
    tokens through a selector that needs no ego path, no image alignment (the release has no camera images)."""
    tmp = tmp_path_factory.mktemp("world_model")
    built = run_llm_stage(release_world.root, tmp / "llm")
    config = {
        "model.world": asdict(WorldConfig()),
        "model.selector": asdict(SelectorConfig(name="voxel_topk", k_c=16)),
        "model.projection": asdict(ProjectionConfig(fourier_features=2)),
        "model.fine_adapter": asdict(FineAdapterConfig(name="query_xattn", k_f=4, heads=2)),
        "model.alignment": asdict(AlignmentConfig(name="none")),
        "model.llm": asdict(TINY_LLM),
        "stage.tokenizer": asdict(TokenizerStageConfig(steps=0, eval_samples=0)),
    }
    up = {"llm": built, "distill": UpstreamOutput("distill", "d" * 64, None, {}, release_world.distilled)}
    ctx = _ctx("tokenizer", config, tmp / "tokenizer", up, release_world.root, seed=0)
    tokenizer.fn(ctx)
    return UpstreamOutput("lora", "l" * 64, ctx.out_dir)


@pytest.fixture(scope="module")
def distill(release_world) -> UpstreamOutput:
    return UpstreamOutput("distill", "d" * 64, None, {}, release_world.distilled)


def test_c_l_is_one_llm_pass_per_sample_over_its_gaussians(release_world, world_model):
    found, _ = world_clips(release_world.ds, "val", release_world.distilled, HW, need_depth=False)
    model = load_world_model(world_model.path).eval()
    c_L = clip_conditions(model, release_world.ds, release_world.distilled, found, 4)
    assert len(c_L) == 3 and c_L[0].ndim == 2 and c_L[0].shape[1] == TINY_LLM.hidden_size
    assert torch.equal(c_L[0], c_L[1]) and torch.equal(c_L[1], c_L[2]) and bool(torch.isfinite(c_L[0]).all())


def test_the_three_stages_train_and_score_the_release_world_samples(release_world, world_model, distill, tmp_path):
    data = release_world.root
    vae_cfg = {"model.diffusion": asdict(MODEL), "stage.diffusion_vae": asdict(VaeStageConfig(steps=20, seed=0))}
    vctx = _ctx("diffusion_vae", vae_cfg, tmp_path / "vae", {}, data)
    vm = world_vae.fn(vctx)
    assert vm["images"] == 1 + 2 * 3 + 1  # w1: reference, 3 frames and depths; w2: reference
    assert vm["vae_loss_final"] < vm["vae_loss_first"]
    assert (vctx.out_dir / "vae" / "config.json").is_file() and (vctx.out_dir / "rgbd.json").is_file()
    assert [(r.name, r.path, r.variant) for r in vctx.registrations] == [("gdwm-vae", "vae", "rgbd_dual-tiny")]

    train = DiffusionStageConfig(steps=40, batch_size=3, lr=2e-3, warmup_steps=0, log_every=10)
    config = {"model.diffusion": asdict(MODEL), "stage.diffusion": asdict(train)}
    up = {"diffusion_vae": UpstreamOutput("diffusion_vae", "v" * 64, vctx.out_dir), "lora": world_model,
          "distill": distill}  # fmt: skip
    dctx = _ctx("diffusion", config, tmp_path / "diffusion", up, data, seed=0)
    dm = world_diffusion.fn(dctx)
    assert dm == {"train_examples": 3, f"train_examples/{KIND}": 3, "train_samples": 1,
                  "count/skipped/train/no_ground_truth": 1}  # fmt: skip
    assert json.loads((dctx.out_dir / "metrics.json").read_text()) == dm
    for f in ("unet/config.json", "vae/config.json", "rgbd.json", "null_token.pt"):
        assert (dctx.out_dir / f).is_file(), f
    assert [(r.name, r.path, r.variant) for r in dctx.registrations] == [
        ("gdwm-unet", ".", "rgbd_dual-tiny+low_level+high_level")
    ]
    losses = [m["loss"] for _, m in dctx.tracker.metrics if "loss" in m]
    assert len(losses) == 5 and all(math.isfinite(v) for v in losses)
    examples = torch.load(dctx.checkpoint_dir / "examples.pt", weights_only=True)
    assert tuple(examples["cond_rgb"].shape) == (3, 3, *HW) and examples["c_L"].shape[-1] == TINY_LLM.hidden_size
    # L_gen on the training examples at the same (t, eps) draws: lower after training than at the start
    before, after = RGBDDual.from_pretrained(dctx.checkpoint_dir / "init"), RGBDDual.from_pretrained(dctx.out_dir)

    def l_gen(model: RGBDDual) -> float:
        b = {k: examples[k] for k in ("target_rgb", "target_depth", "ref_rgb", "ref_depth", "cond_rgb", "cond_depth",
                                      "cond_mask", "c_L", "c_L_mask")}  # fmt: skip
        with torch.no_grad():
            return sum(model.eval().loss(*b.values(), generator=torch.Generator().manual_seed(s))[0].item()
                       for s in range(16)) / 16  # fmt: skip

    assert l_gen(after) < 0.9 * l_gen(before)

    ev = EvaluateGenConfig(batch_size=2, fvd_clip_frames=3)
    up = {"diffusion": UpstreamOutput("diffusion", "u" * 64, dctx.out_dir), "lora": world_model, "distill": distill}
    ectx = _ctx("evaluate_gen", {"stage.evaluate_gen": asdict(ev)}, tmp_path / "evaluate", up, data, seed=0)
    em = world_evaluate_gen.fn(ectx)
    g = f"gen/{KIND}"
    scores = [f"{g}/{k}" for k in ("psnr", "ssim", "depth_absrel", "depth_rmse", "fd_daisy")]
    counts = ["count/heldout_views", "count/heldout_samples", "count/samples_without_gt_depth"]
    assert sorted(em) == sorted(scores + counts)
    assert (em["count/heldout_views"], em["count/heldout_samples"], em["count/samples_without_gt_depth"]) == (3, 1, 0)
    assert 0 < em[f"{g}/psnr"] < 60 and -1 <= em[f"{g}/ssim"] <= 1
    assert em[f"{g}/depth_absrel"] >= 0 and 0 <= em[f"{g}/depth_rmse"] <= MODEL.max_depth
    assert math.isfinite(em[f"{g}/fd_daisy"]) and em[f"{g}/fd_daisy"] >= 0
    assert json.loads((ectx.out_dir / "metrics.json").read_text()) == em
    protocol = json.loads((ectx.out_dir / "protocol.json").read_text())
    assert protocol["not_computed"] == {**NOT_COMPUTED, f"{g}/fd_video_daisy": "fewer than 2 clips of 3 frames "
                                        "(fvd_clip_frames)"}  # fmt: skip
    assert protocol["views"] == "approximate" and protocol["frechet"].startswith("fd_daisy: approximate")
    assert ectx.tracker.artifacts == [str(ectx.out_dir / "protocol.json")]
    for t in range(3):
        grid = cv2.imread(str(ectx.out_dir / "samples" / KIND / f"w1_{t:03d}.png"))
        assert grid.shape == (HW[0], 4 * HW[1], 3)


def test_a_dataset_without_world_samples_is_refused_naming_it(synth_small, distill, tmp_path):
    cfg = {"model.diffusion": asdict(MODEL), "stage.diffusion_vae": asdict(VaeStageConfig(steps=1))}
    with pytest.raises(DataError, match=re.escape(f"at {synth_small}: no world samples in split 'train'; it has no")):
        world_vae.fn(_ctx("diffusion_vae", cfg, tmp_path / "vae", {}, synth_small))
    cfg = {"model.diffusion": asdict(MODEL), "stage.diffusion": asdict(DiffusionStageConfig())}
    up = {"diffusion_vae": None, "lora": None, "distill": distill}
    with pytest.raises(DataError, match=re.escape("no world samples in split 'train'")):
        world_diffusion.fn(_ctx("diffusion", cfg, tmp_path / "diffusion", up, synth_small, seed=0))


def test_the_stages_stand_in_under_the_names_the_dag_uses():
    assert [(s.name, s.config, s.upstream) for s in (world_vae, world_diffusion, world_evaluate_gen)] == [
        ("diffusion_vae", ("model.diffusion", "stage.diffusion_vae"), ()),
        ("diffusion", ("model.diffusion", "stage.diffusion"), ("diffusion_vae", "lora", "distill")),
        ("evaluate_gen", ("stage.evaluate_gen",), ("diffusion", "lora", "distill")),
    ]
    assert world_evaluate_gen.evaluation and world_diffusion.seeded and world_evaluate_gen.seeded
    assert [sorted(s.needed({})) for s in (world_vae, world_diffusion, world_evaluate_gen)] == [["world"]] * 3
