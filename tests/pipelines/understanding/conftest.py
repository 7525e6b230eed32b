"""Distilled scenes made in milliseconds: each frame's LiDAR points as Gaussians with random codes and a fresh D_F
(what the distill stage publishes, without running it)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder
from pipelines.data.layout import gaussians_table, write_arrow
from pipelines.data.reader import GSQADataset


def make_distilled(data: Path, out: Path, d_z: int, points: int = 300, seed: int = 0) -> dict[str, Path]:
    ds = GSQADataset(data)
    rng = np.random.default_rng(seed)
    dirs = {}
    for scene in ds.scenes():
        d = out / scene.id
        for frame in scene.frames():
            xyz = frame.lidar()[:, :3]
            xyz = xyz[rng.choice(len(xyz), size=min(points, len(xyz)), replace=False)]
            n = len(xyz)
            arrays = {
                "xyz": xyz.astype(np.float32),
                "scale": rng.uniform(0.05, 0.5, (n, 3)).astype(np.float32),
                "rotation": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)).astype(np.float32),
                "opacity": rng.uniform(0.1, 1.0, n).astype(np.float32),
                "color": rng.uniform(0, 1, (n, 3)).astype(np.float32),
                "feature": rng.normal(size=(n, d_z)).astype(np.float32),
            }
            write_arrow(gaussians_table(arrays, where=frame.where), d / "gaussians" / f"{frame.idx:05d}.arrow")
        cfg = FeatureAEConfig(d_f=16, d_z=d_z, hidden=16)
        torch.manual_seed(seed)
        torch.save(FeatureAutoencoder(cfg).state_dict(), d / "decoder.pt")
        (d / "autoencoder.json").write_text(json.dumps({"variant": "foundation", "config": asdict(cfg)}))
        dirs[scene.id] = d
    return dirs


@pytest.fixture(scope="session")
def distilled16(synth_small, tmp_path_factory) -> dict[str, Path]:
    return make_distilled(synth_small, tmp_path_factory.mktemp("distilled16"), d_z=16)


@pytest.fixture(scope="session")
def distilled3(synth_small, tmp_path_factory) -> dict[str, Path]:
    return make_distilled(synth_small, tmp_path_factory.mktemp("distilled3"), d_z=3)
