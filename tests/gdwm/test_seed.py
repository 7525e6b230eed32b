"""A new sqlite store is a copy of an empty one MLflow made (gdwm.tracking.seed): the same schema as a store MLflow
creates itself, never a replaced store, and the backend works on it as on any other."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from mlflow import MlflowClient
from mlflow.utils import validation

from gdwm.tracking import params
from gdwm.tracking.backend import TrackingBackend
from gdwm.tracking.seed import seed_store, template_dir


@pytest.fixture
def local_cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("GDWM_LOCAL_CACHE", str(tmp_path / "local"))
    return tmp_path / "local"


def _schema(db: Path) -> tuple[list[tuple], list[tuple]]:
    """Every table and index with its definition, the definition's lines sorted: a migration that recreates a table
    (alembic's batch mode) writes its constraints in an order that varies with the process' hash seed."""
    with sqlite3.connect(db) as c:
        rows = c.execute("select type, name, sql from sqlite_master order by type, name").fetchall()
        tables = [(kind, name, sorted(line.strip().rstrip(",") for line in (sql or "").splitlines()))
                  for kind, name, sql in rows]  # fmt: skip
        return tables, c.execute("select version_num from alembic_version").fetchall()


def test_a_seeded_store_has_the_schema_mlflow_makes(tmp_path, local_cache):
    mine, theirs = tmp_path / "a" / "mlflow.db", tmp_path / "b" / "mlflow.db"
    assert seed_store(f"sqlite:///{mine}") is True
    (template,) = template_dir().glob("mlflow-*.db")
    MlflowClient(f"sqlite:///{theirs}").search_experiments()  # MLflow creating a store itself
    MlflowClient(f"sqlite:///{mine}").search_experiments()  # and opening the copy (its default experiment)
    assert _schema(mine) == _schema(theirs)
    assert _schema(mine)[1] != []  # a migrated schema: alembic's head revision
    assert (mine.stat().st_mode & 0o777) == (theirs.stat().st_mode & 0o777)  # the umask's mode, not mkstemp's 0600
    assert template.parent == local_cache / "mlflow-schema"


def test_an_existing_store_is_never_replaced(tmp_path, local_cache):
    db = tmp_path / "mlflow.db"
    db.write_bytes(b"not mine")
    assert seed_store(f"sqlite:///{db}") is False
    assert db.read_bytes() == b"not mine"
    assert seed_store("postgresql://u@host/db") is False  # only sqlite files are seeded
    assert not local_cache.exists()  # nor was a template made for nothing


def test_the_backend_creates_its_experiment_and_runs_in_a_seeded_store(tmp_path, local_cache):
    uri = f"sqlite:///{tmp_path / 'w' / 'mlflow.db'}"
    first = TrackingBackend(uri, "gdwm", (tmp_path / "w" / "mlartifacts").as_uri())
    second = TrackingBackend(f"sqlite:///{tmp_path / 'v' / 'mlflow.db'}", "gdwm", None)  # seeded from the template
    assert len(list(local_cache.joinpath("mlflow-schema").glob("*.db"))) == 1
    run = second.create_run("r", {"k": "v"})
    second.end_run(run)
    assert first.experiment_id == second.experiment_id == "1"  # MLflow's default experiment is 0, as ever
    assert MlflowClient(uri).get_experiment("1").artifact_location == (tmp_path / "w" / "mlartifacts").as_uri()
    assert MlflowClient(second.uri).get_run(run).info.status == "FINISHED"


def test_the_batch_limits_are_mlflows():
    assert params.MAX_METRICS_PER_BATCH == validation.MAX_METRICS_PER_BATCH
    assert params.MAX_PARAMS_TAGS_PER_BATCH == validation.MAX_PARAMS_TAGS_PER_BATCH
    assert params.MAX_PARAM_VAL_LENGTH == validation.MAX_PARAM_VAL_LENGTH
    assert params.MAX_TAG_VAL_LENGTH == validation.MAX_TAG_VAL_LENGTH
