"""Pipeline validation fails before anything runs, naming the stage and what is wrong."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gdwm.dag import DagError, load_pipeline
from gdwm.stage import StageContext, stage


@stage("a", "1", config=["stage.a"])
def a(ctx: StageContext) -> None:
    return None


@stage("b", "1", config=["stage.b"], upstream=["a"])
def b(ctx: StageContext) -> None:
    return None


@stage("c", "1", upstream=["d"])
def c(ctx: StageContext) -> None:
    return None


@stage("d", "1", upstream=["c"])
def d(ctx: StageContext) -> None:
    return None


def not_a_stage() -> None:
    return None


M = __name__
REPO = Path(__file__).resolve().parents[2]


def _cfg(stages: dict, **extra) -> OmegaConf:
    return OmegaConf.create(
        {
            "pipeline": {"name": "p", "stages": {k: {"_target_": f"{M}.{v}"} for k, v in stages.items()}},
            "stage": {"a": {"x": 1}, "b": {"y": 2}},
            **extra,
        }
    )


def test_valid_pipeline_in_topological_order_and_ancestors():
    pipe = load_pipeline(_cfg({"b": "b", "a": "a"}))
    assert pipe.order == ["a", "b"]
    assert pipe.ancestors(["b"]) == ["a", "b"]
    assert pipe.ancestors(["a"]) == ["a"]
    with pytest.raises(DagError, match=r"targets \['z'\] are not stages of pipeline 'p' \(stages: \['a', 'b'\]\)"):
        pipe.ancestors(["z"])


def test_missing_upstream():
    with pytest.raises(DagError, match=r"stage 'b' needs upstream \['a'\], which pipeline 'p' does not define"):
        load_pipeline(_cfg({"b": "b"}))


def test_cycle():
    with pytest.raises(DagError, match=r"pipeline 'p' has a cycle: (c -> d -> c|d -> c -> d)"):
        load_pipeline(_cfg({"c": "c", "d": "d"}))


def test_unknown_stage_target_and_non_stage():
    with pytest.raises(DagError, match=r"pipeline.stages.a._target_: cannot import 'tests.gdwm.test_dag.nope'"):
        load_pipeline(_cfg({"a": "nope"}))
    with pytest.raises(DagError, match=r"pipeline.stages.a._target_: '.*not_a_stage' is not a gdwm stage"):
        load_pipeline(_cfg({"a": "not_a_stage"}))
    with pytest.raises(DagError, match=r"pipeline.stages.x._target_: '.*test_dag.a' declares stage name 'a', not 'x'"):
        load_pipeline(_cfg({"x": "a"}))


def test_config_subtree_absent():
    cfg = _cfg({"a": "a", "b": "b"})
    del cfg.stage["b"]
    with pytest.raises(DagError, match=r"stage 'b' depends on config \['stage.b'\], absent from the composed config"):
        load_pipeline(cfg)


def test_bad_resource_class():
    with pytest.raises(ValueError, match=r"stage 'e': resources must be one of \('cpu', 'gpu', 'train', 'eval'\)"):
        stage("e", "1", resources="tpu")(not_a_stage)


def test_dag_error_exits_2_before_launch(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "gdwm",
            "run",
            "experiment=toy",
            f"workdir={tmp_path}",
            "pipeline.stages.distill._target_=nowhere.distill",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO), "GDWM_CONF_PATH": str(REPO / "tests" / "conf")},
    )
    assert r.returncode == 2
    assert "gdwm run: pipeline error: pipeline.stages.distill._target_: cannot import 'nowhere.distill'" in r.stderr
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "cache").exists()


def test_targets_import_only_their_ancestors():
    cfg = _cfg({"a": "a", "b": "b", "z": "nope"})
    with pytest.raises(DagError, match=r"pipeline.stages.z._target_: cannot import"):
        load_pipeline(cfg)
    pipe = load_pipeline(cfg, ["b"])  # z is never needed, so never imported
    assert pipe.order == ["a", "b"]
    with pytest.raises(DagError, match=r"targets \['q'\] are not stages of pipeline 'p'"):
        load_pipeline(cfg, ["q"])
