"""The GaussianDWM release fixture imported once, and distilled scenes made from its Gaussians (what the release
pipeline's per-scene Gaussian stage publishes: ``gaussians/<frame>.arrow``, ``decoder.pt``, ``autoencoder.json``)."""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import pytest
import torch

from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder
from pipelines.data.gaussiandwm import ReleaseConfig, build
from pipelines.data.reader import GSQADataset
from tests.pipelines.data.fixtures_release import Release, write_release


@dataclass(frozen=True)
class ImportedRelease:
    release: Release
    """What the fixture wrote (images, depths, pack as written)."""
    root: Path
    """The imported dataset."""
    distilled: dict[str, Path]
    """Scene id -> distilled scene directory."""

    @property
    def ds(self) -> GSQADataset:
        return GSQADataset(self.root)


def distill_release(root: Path, out: Path, seed: int = 0) -> dict[str, Path]:
    """Every imported scene's Gaussians as they are (their language features are the codes) with a fresh D_F."""
    ds = GSQADataset(root)
    dirs = {}
    for sid in ds.scene_ids:
        d = out / sid
        shutil.copytree(root / "scenes" / sid / "gaussians", d / "gaussians")
        cfg = FeatureAEConfig(d_f=16, d_z=int(ds.meta["gaussians"]["feature_dim"]), hidden=16)
        torch.manual_seed(seed)
        torch.save(FeatureAutoencoder(cfg).state_dict(), d / "decoder.pt")
        (d / "autoencoder.json").write_text(json.dumps({"variant": "foundation", "config": asdict(cfg)}))
        dirs[sid] = d
    return dirs


def import_release(tmp: Path, edit=None) -> ImportedRelease:
    """The release fixture written under ``tmp``, changed by ``edit(release)`` if given, imported and distilled."""
    release = write_release(tmp / "release")
    if edit is not None:
        edit(release)
    root = build(ReleaseConfig(), tmp / "data", str(release.root))
    return ImportedRelease(release, root, distill_release(root, tmp / "distilled"))


@pytest.fixture(scope="session")
def release_world(tmp_path_factory) -> ImportedRelease:
    """w1 (3 frames with ground truth, train and val), w2 (2 frames, no ground truth, train)."""
    return import_release(tmp_path_factory.mktemp("release_world"))
