"""The driving-aware prior's path (``model.selector.path``): the planned route by default, and never a recorded future
pose (issue 17): perturbing the dataset's future ego poses leaves the selector's input and output unchanged."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from model_zoo import registry
from model_zoo.config import SelectorConfig
from model_zoo.selectors import SelectorInputs
from pipelines.data.layout import EGO_POSES_SCHEMA, DataError
from pipelines.data.reader import GSQADataset
from pipelines.data.synth.route import planned_route
from pipelines.data.synth.scenarios import generate_scene
from pipelines.understanding.data import FrameStore

FRAME = 4  # 4 frames of history, 5 of recorded future in the 10-frame fixture scenes


@pytest.fixture(scope="module")
def perturbed(synth_small, tmp_path_factory) -> Path:
    """A copy of the dataset whose ego poses after FRAME swerve 4 m left and turn 0.5 rad, the rest identical."""
    dst = tmp_path_factory.mktemp("perturbed") / "data"
    shutil.copytree(synth_small, dst)
    rows = pq.read_table(dst / "ego_poses.parquet").to_pylist()
    for r in rows:
        if r["frame_idx"] > FRAME:
            m = np.asarray(r["ego2world"], dtype=np.float64).reshape(4, 4)
            c, s = np.cos(0.5), np.sin(0.5)
            m[:2, :2] = np.array([[c, -s], [s, c]]) @ m[:2, :2]
            m[1, 3] += 4.0
            r["ego2world"] = m.reshape(-1).tolist()
    pq.write_table(pa.Table.from_pylist(rows, schema=EGO_POSES_SCHEMA), dst / "ego_poses.parquet")
    return dst


def _gaussians(n: int = 400) -> SelectorInputs:
    rng = np.random.default_rng(0)
    xyz = np.stack([rng.uniform(-30, 50, n), rng.uniform(-20, 20, n), rng.uniform(0, 3, n)], 1)
    return SelectorInputs(
        torch.tensor(xyz, dtype=torch.float32),
        torch.tensor(rng.uniform(0.05, 0.5, (n, 3)), dtype=torch.float32),
        torch.tensor(np.tile([1.0, 0, 0, 0], (n, 1)), dtype=torch.float32),
        torch.tensor(rng.uniform(0.1, 1.0, n), dtype=torch.float32),
    )


def _future_xy(ds: GSQADataset, scene: str) -> np.ndarray:
    """The recorded future ego positions in the FRAME ego frame: what the selector must never see."""
    poses = ds.scene(scene).ego_poses
    rel = np.einsum("ij,fj->fi", np.linalg.inv(poses[FRAME]), poses[FRAME + 1 :, :, 3])
    return rel[:, :2].astype(np.float32)


@pytest.mark.parametrize("path", ["route", "extrapolated"])
def test_no_recorded_future_pose_reaches_the_selector(path, synth_small, perturbed):
    cfg = SelectorConfig(name="driving_aware", k_c=32, path=path, sigma_traj=3.0)
    selector = registry.build("selector", "driving_aware", cfg)
    original, changed = GSQADataset(synth_small), GSQADataset(perturbed)
    for scene in original.scene_ids:
        assert not np.allclose(_future_xy(original, scene), _future_xy(changed, scene))  # the future did change
        a = FrameStore(original, {}, "clear", 4).selector_path(scene, FRAME, cfg)
        b = FrameStore(changed, {}, "clear", 4).selector_path(scene, FRAME, cfg)
        assert torch.equal(a, b) and len(a) > 0
        g = _gaussians()
        picked = {}
        for name, traj in {"a": a, "b": b}.items():
            picked[name] = selector(dataclasses.replace(g, trajectory=traj)).index
        assert torch.equal(picked["a"], picked["b"])
        # the same check has teeth: a path made of the recorded future would change the selection
        leaky = [selector(dataclasses.replace(g, trajectory=torch.from_numpy(_future_xy(d, scene)))).index
                 for d in (original, changed)]  # fmt: skip
        assert not torch.equal(*leaky)


def test_the_route_is_the_path_ahead_in_the_egos_lane(synth_small):
    """In the fixture's bend and stop scenes the ego keeps its lane: every recorded future position lies on the route
    ahead (within 5 cm of the polyline), though the route was built from none of them."""
    ds = GSQADataset(synth_small)
    cfg = SelectorConfig(path="route", route_ahead_m=40.0)
    for scene in ds.scene_ids:
        path = FrameStore(ds, {}, "clear", 4).selector_path(scene, FRAME, cfg).numpy()
        assert np.allclose(path[0], 0.0, atol=1e-3) and np.all(np.diff(path[:, 0]) > 0)  # from the ego, forward
        future = _future_xy(ds, scene)
        a, d = path[:-1], np.diff(path, axis=0)  # the polyline's segments
        t = np.clip(((future[:, None] - a[None]) * d[None]).sum(-1) / (d * d).sum(-1)[None], 0, 1)
        gap = np.linalg.norm(future[:, None] - (a[None] + t[..., None] * d[None]), axis=-1).min(1)
        assert gap.max() < 0.05, (scene, gap)


def test_the_synthetic_route_is_the_map_not_the_egos_manoeuvres(synth_small_cfg):
    """A lane change, a different speed or a stop leave the planned route as it was: it comes from road and lane."""
    scene = generate_scene(synth_small_cfg, 0)
    route = planned_route(scene)
    other = dataclasses.replace(scene.ego, v0=2.0, accel=-1.0, v_end=0.0, lc_offset=3.5, lc_start=1.0)
    np.testing.assert_array_equal(planned_route(dataclasses.replace(scene, ego=other)), route)


def test_the_dataset_records_routes_and_a_missing_one_is_named(synth_small, tmp_path):
    ds = GSQADataset(synth_small)
    routes = json.loads((synth_small / "routes.json").read_text())
    assert sorted(routes) == ds.scene_ids and min(len(r) for r in routes.values()) >= 60
    assert "routes.json" in ds.meta["files"]  # in the dataset fingerprint, so in every stage key
    dst = tmp_path / "data"
    shutil.copytree(synth_small, dst)
    (dst / "routes.json").unlink()
    store = FrameStore(GSQADataset(dst), {}, "clear", 4)
    with pytest.raises(DataError) as e:
        store.selector_path("scene-0000", FRAME, SelectorConfig())
    assert str(e.value) == (
        f"{dst}: no planned route for scene-0000 (routes.json), which model.selector.path=route follows; rebuild "
        "the dataset with a builder that records routes (synthetic_mini does), or set model.selector.path=extrapolated"
    )
    assert len(store.selector_path("scene-0000", FRAME, SelectorConfig(path="extrapolated"))) == 4 + 1 + 4
