"""Per-scene stages' actor pools on local Ray with 2 CPUs: a pool makes progress with whatever part of the cluster it
got, so concurrent per-scene stages never wait on each other (scenes used to be pinned to every actor of a pool up
front: pools that each got one of the two CPUs sat idle, each waiting for its unplaced second actor)."""

from __future__ import annotations

from pathlib import Path

import pytest
import ray

from gdwm.config import TrackingConfig
from gdwm.executor import RunEnv, run_scene_stage
from gdwm.tracking import open_tracking
from tests.gdwm.stages import scene_pid

SCENES = ("scene-0000", "scene-0001", "scene-0002")
POOL = {"cpu": {"num_cpus": 1, "num_gpus": 0, "num_workers": 2}}
WAIT_S = 300
"""A pool that cannot progress never returns: the test fails after this instead of hanging."""


@pytest.fixture
def env(ray_local, tmp_path) -> RunEnv:
    store = TrackingConfig(uri=f"sqlite:///{tmp_path}/mlflow.db", artifact_location=str(tmp_path / "art"))
    sink, close = open_tracking(store)
    yield RunEnv(cache_uri=str(tmp_path / "cache"), data_root=str(tmp_path), data_fingerprint="toy", scenes=SCENES,
                 checkpoint_root=str(tmp_path / "ckpt"), sink=sink, parent_run_id=None, progress=None,
                 resources=POOL)  # fmt: skip
    close()


def _pids(result) -> dict[str, int]:
    return {s: int((Path(path) / "pid.txt").read_text()) for s, (_, path) in result.scenes.items()}


@ray.remote(num_cpus=1)
class _Holder:
    """Holds one of the cluster's CPUs, as another stage's placed actor does."""

    def ready(self) -> bool:
        return True


def test_a_pool_with_one_placed_actor_runs_every_scene_on_it(env):
    holder = _Holder.remote()
    try:
        assert ray.get(holder.ready.remote(), timeout=WAIT_S)
        # one CPU left for a pool of two: its second actor stays unplaced while the test holds the other
        result = ray.get(run_scene_stage.remote(scene_pid, {"stage.scene_pid": {"n": 1}}, env), timeout=WAIT_S)
    finally:
        ray.kill(holder)
    pids = _pids(result)
    assert sorted(pids) == list(SCENES) and result.failed == {} and not result.cached
    assert len(set(pids.values())) == 1, pids  # the placed actor took every scene


def test_three_per_scene_stages_at_once_all_finish(env):
    # three datasets (different keys), each a pool of two actors: six actors asking for two CPUs
    refs = [run_scene_stage.remote(scene_pid, {"stage.scene_pid": {"n": n}}, env) for n in range(3)]
    results = ray.get(refs, timeout=WAIT_S)
    assert [sorted(r.scenes) for r in results] == [list(SCENES)] * 3
    assert len({r.key for r in results}) == 3 and all(not r.cached and r.failed == {} for r in results)
