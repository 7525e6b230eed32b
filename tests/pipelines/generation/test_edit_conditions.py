"""Edits as the paper means them: the instruction rides in C_L for every edit kind, the Gaussian-level edit is the
low-level condition."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from model_zoo import registry
from model_zoo.adapter import FineAdapterConfig, ProjectionConfig
from model_zoo.alignment import AlignmentConfig
from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder
from model_zoo.llm.qwen3_vl import LLMConfig
from model_zoo.selectors import SelectorConfig
from pipelines.data.layout import gaussians_table, write_arrow
from pipelines.data.reader import GSQADataset
from pipelines.generation.edits import (
    InsertVehicle,
    RemoveVehicle,
    Weather,
    gaussians_in_box,
    remove_vehicle,
)
from pipelines.generation.examples import conditions_of
from pipelines.generation.samples import GenTarget, build_example, edited_example, enumerate_targets
from pipelines.understanding.config import WorldConfig
from pipelines.understanding.data import load_samples, training_corpus
from pipelines.understanding.model import Components, build_world_model

SCENE, HW = "scene-0000", (24, 40)


def lidar_gaussians(frame, rng, d_z: int = 0, every: int = 4) -> dict[str, np.ndarray]:
    """Every ``every``-th LiDAR point as a Gaussian (random colours; random codes of width ``d_z`` if > 0)."""
    xyz = frame.lidar()[::every, :3].astype(np.float32)
    n = len(xyz)
    g = {
        "xyz": xyz,
        "scale": np.full((n, 3), 0.3, np.float32),
        "rotation": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)).astype(np.float32),
        "opacity": np.full(n, 0.9, np.float32),
        "color": rng.uniform(0, 1, (n, 3)).astype(np.float32),
    }
    return g | ({"feature": rng.normal(size=(n, d_z)).astype(np.float32)} if d_z else {})


@pytest.fixture(scope="module")
def world(synth_small, tmp_path_factory):
    """A tiny world model over scene-0000's frames distilled as LiDAR Gaussians with random codes (what the
    distill stage publishes, without running it), and the directories its frame store reads."""
    ds = GSQADataset(synth_small)
    out = tmp_path_factory.mktemp("edit_world") / SCENE
    rng = np.random.default_rng(0)
    for frame in ds.scene(SCENE).frames():
        g = lidar_gaussians(frame, rng, d_z=16, every=30)
        write_arrow(gaussians_table(g, where=frame.where), out / "gaussians" / f"{frame.idx:05d}.arrow")
    cfg = FeatureAEConfig(d_f=16, d_z=16, hidden=16)
    torch.manual_seed(0)
    torch.save(FeatureAutoencoder(cfg).state_dict(), out / "decoder.pt")
    (out / "autoencoder.json").write_text(json.dumps({"variant": "foundation", "config": asdict(cfg)}))
    dirs = {SCENE: Path(out)}
    samples, _ = load_samples(ds, "train", {}, need_gaussians=False)
    llm_cfg = LLMConfig(tiny=True, hidden_size=32, intermediate_size=64)
    llm = registry.build("llm", "qwen3_vl", llm_cfg, corpus=training_corpus(samples))
    comp = Components(
        WorldConfig(),
        SelectorConfig(name="driving_aware", k_c=32, voxel_size=4.0),
        ProjectionConfig(fourier_features=4),
        FineAdapterConfig(name="query_xattn", k_f=8, heads=2),
        AlignmentConfig(name="none"),
        llm_cfg,
    )
    return build_world_model(comp, llm, dirs, seed=0).eval(), dirs


def _removal(ds):
    """scene-0000 frame 0's LiDAR Gaussians, the plain front view and the vehicle whose removal that view sees
    (most Gaussians inside among the vehicles that change its conditions)."""
    frame = ds.scene(SCENE).frame(0)
    g = lidar_gaussians(frame, np.random.default_rng(1))
    t = GenTarget(SCENE, 0, "CAM_FRONT", "shift", lateral_m=0.0)
    plain = build_example(ds, t, g, HW, edited=True)
    cars = [b for b in frame.boxes3d() if b["instance_id"].split("-")[2] in ("car", "truck", "bus")
            and b["center"][0] > abs(b["center"][1]) / 2]  # fmt: skip  # ahead of the front camera
    cars.sort(key=lambda b: -int(gaussians_in_box(g["xyz"], b).sum()))
    car = next(
        b for b in cars if not torch.equal(build_example(ds, t, remove_vehicle(g, b), HW, edited=True).cond_mask,
                                           plain.cond_mask)
    )  # fmt: skip
    return frame.boxes3d(), g, t, plain, car


def test_a_removal_conditions_on_the_edited_gaussians_and_prompts_with_the_instruction(synth_small):
    ds = GSQADataset(synth_small)
    boxes, g, t, plain, car = _removal(ds)
    ex, qa = edited_example(ds, t, RemoveVehicle(car["instance_id"]), g, boxes, HW)
    # low level: exactly the conditions projected from the Gaussians without the car
    by_hand = build_example(ds, t, remove_vehicle(g, car), HW, edited=True)
    for k in ("cond_rgb", "cond_depth", "cond_mask"):
        assert torch.equal(getattr(ex, k), getattr(by_hand, k)), k
    assert not torch.equal(ex.cond_mask, plain.cond_mask)
    # high level: the instruction is in the prompt C_L is computed from
    view = "Based on <gauss>, generate the CAM_FRONT view."
    assert qa.instruction == f"{view} Remove vehicle {car['instance_id']} from the scene."
    assert t.qa().instruction == view


def test_the_instruction_changes_c_l(synth_small, world):
    model, dirs = world
    ds = GSQADataset(synth_small)
    boxes, g, t, _, car = _removal(ds)
    _, qa_remove = edited_example(ds, t, RemoveVehicle(car["instance_id"]), g, boxes, HW)
    _, qa_insert = edited_example(ds, t, InsertVehicle(car["instance_id"], (12.0, -3.0), 0.5), g, boxes, HW)
    with torch.no_grad():
        c_remove, c_none, c_insert = conditions_of(model, ds, dirs, [qa_remove, t.qa(), qa_insert], 3)
    assert c_remove.shape[0] > c_none.shape[0]  # the instruction's tokens
    assert not torch.allclose(c_remove[-1], c_none[-1], atol=1e-4)
    assert not torch.allclose(c_remove[-1], c_insert[-1], atol=1e-4)


def test_a_weather_edit_asks_what_the_weather_targets_were_trained_with(synth_small):
    ds = GSQADataset(synth_small)
    frame = ds.scene(SCENE).frame(0)
    g = lidar_gaussians(frame, np.random.default_rng(1))
    t = GenTarget(SCENE, 0, "CAM_FRONT", "shift", lateral_m=0.0)
    ex, qa = edited_example(ds, t, Weather("rain"), g, frame.boxes3d(), HW)
    trained = next(x for x in enumerate_targets(ds, [SCENE], ["CAM_FRONT"], [], [], ["rain"]) if x.frame == 0)
    assert (
        qa.instruction
        == trained.qa().instruction
        == ("Based on <gauss>, generate the CAM_FRONT view. Change the weather to rain.")
    )
    plain = build_example(ds, t, g, HW, edited=True)
    assert torch.equal(ex.cond_rgb, plain.cond_rgb) and torch.equal(ex.cond_depth, plain.cond_depth)  # no geometry
