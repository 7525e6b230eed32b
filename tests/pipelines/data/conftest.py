"""Fixtures the benchmark importers' tests share."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipelines.data.nuscenes import NuScenesConfig
from pipelines.data.nuscenes import build as convert
from tests.pipelines.data.fixtures_nuscenes import write_nuscenes


@pytest.fixture(scope="session")
def converted(tmp_path_factory) -> Path:
    """The nuScenes fixture converted once per session; the importers only read it (they link its images)."""
    nus = write_nuscenes(tmp_path_factory.mktemp("nus"))
    return convert(NuScenesConfig(width=32, height=18), tmp_path_factory.mktemp("conv") / "nuscenes", str(nus.root))
