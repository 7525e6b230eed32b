"""The dashboard's MLflow-free reads of a sqlite store (``gdwm.ui.sqlite``) equal MLflow's client on a real store.

The store is the compare tests' (a sweep, rows, trials with metrics, a failed trial, a stage run with a loss history,
a plain run with an artifact), written by ``TrackingBackend``, plus a NaN metric, nested artifacts and a deleted run.
Every read is made twice: by ``Store`` as the dashboard uses it, and by the same ``Store`` with the direct reader
switched off, which asks ``mlflow.MlflowClient``: the answers must be the same, value for value and in the same order.
"""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

import pytest

from gdwm.ui.sqlite import SqliteRuns, inside, parse_filter, parse_order
from gdwm.ui.store import Store, StoreError
from tests.gdwm.compare_runs import EXPERIMENT, log_store


def _same(a, b) -> bool:
    """Equal, NaN equal to NaN."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str)


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    s = log_store(tmp_path_factory.mktemp("sqlite"))
    b = s.backend()
    b.log_metrics(s.stage_run, {"diverged": math.nan})
    b.log_metrics(s.stage_run, {"diverged": 1.5}, step=1)
    b.log_metrics(s.stage_run, {"stuck": math.nan})
    b.log_text(s.stage_run, '{"a": 1}', "progress/snapshot.json")
    b.log_text(s.stage_run, "line\n", "logs/deep/stage.log")
    deleted = b.create_run("deleted", {"gdwm.kind": "trial", "gdwm.sweep": "abl"})
    b.end_run(deleted)
    b.close()
    from mlflow import MlflowClient

    MlflowClient(s.uri).delete_run(deleted)
    fast, reference = Store(s.uri, EXPERIMENT), Store(s.uri, EXPERIMENT)
    reference._direct = None  # every read through MLflow's client
    fast.connect(), reference.connect()
    assert fast.direct() is not None and reference.direct() is None
    return s, fast, reference


FILTERS = [
    ("", None),
    ("tags.`gdwm.kind` = 'trial'", None),
    ("tags.`gdwm.kind` = 'sweep'", ["attributes.start_time DESC"]),
    ("tags.`gdwm.kind` = 'sweep'", ["attributes.start_time ASC"]),
    ("tags.`gdwm.kind` = 'trial' and tags.`gdwm.sweep` = 'abl'", None),
    ("tags.`gdwm.kind` = 'trial' AND tags.`gdwm.row` = 'A'", ["attributes.end_time"]),
    ('params.model = \'{"selector": {"name": "driving_aware"}}\'', None),
    ("tags.`gdwm.kind` = 'nothing'", None),
]


@pytest.mark.parametrize(("filter_string", "order_by"), FILTERS)
@pytest.mark.parametrize("limit", [1, 3, 1000])
def test_search_equals_mlflows(stores, filter_string, order_by, limit):
    _, fast, reference = stores
    assert fast.direct().search(fast.experiment_id, filter_string, limit, order_by) is not None  # read directly
    got = fast.search(filter_string, limit, order_by)
    want = reference.search(filter_string, limit, order_by)
    assert [r["run_id"] for r in got] == [r["run_id"] for r in want]
    assert _same(got, want)


def test_the_parent_filter_the_sweep_page_uses(stores):
    s, fast, reference = stores
    f = f"tags.`mlflow.parentRunId` = '{s.sweep_id}'"
    got = fast.search(f, 10000)
    assert len(got) == len(s.rows) + 1  # the rows and the stage run
    assert _same(got, reference.search(f, 10000))


def test_each_run_its_history_and_artifacts_equal_mlflows(stores, tmp_path):
    s, fast, reference = stores
    ids = [r["run_id"] for r in reference.search("", 1000)]
    assert len(ids) == 1 + 1 + len(s.rows) * 4 + 1 + 1 + 1  # sweeps, old trial, rows and trials, stage, plain
    for rid in ids:
        assert _same(fast.run(rid), reference.run(rid))
    stage = fast.run(s.stage_run)
    assert math.isnan(stage["metrics"]["stuck"]) and stage["metrics"]["diverged"] == 1.5
    for key in ("loss", "diverged", "stuck", "absent"):
        assert _same(fast.history(s.stage_run, key, False), reference.history(s.stage_run, key, False))
    assert fast.history(s.stage_run, "loss", False) == [(0, 2.0), (1, 1.5), (2, 1.2), (3, 1.0)]
    for rid, path in [(s.stage_run, None), (s.stage_run, "logs"), (s.stage_run, "logs/deep"), (s.plain_run, None)]:
        assert fast.artifacts(rid, path) == reference.artifacts(rid, path)
    assert fast.artifacts(s.stage_run, "logs/deep") == [("logs/deep/stage.log", False, 5)]
    snapshot = "progress/snapshot.json"
    assert fast.json(s.stage_run, snapshot) == {"a": 1} == reference.json(s.stage_run, snapshot)
    assert fast.text(s.stage_run, "nothing.txt") is None is reference.text(s.stage_run, "nothing.txt")
    assert fast.exists(s.plain_run, "evaluate_qa/predictions.parquet")
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    got = Path(fast.download(s.plain_run, "evaluate_qa/predictions.parquet", str(a)))
    want = Path(reference.download(s.plain_run, "evaluate_qa/predictions.parquet", str(b)))
    assert got.name == want.name == "predictions.parquet" and got.read_bytes() == want.read_bytes()


def test_a_missing_run_and_a_path_out_of_the_run_are_errors_naming_them(stores):
    s, fast, _ = stores
    with pytest.raises(StoreError, match=r"^the store sqlite:///.*mlflow\.db has no run 0123abc$"):
        fast.run("0123abc")
    with pytest.raises(StoreError, match=r"artifact path '\.\./\.\./x' is not inside the run's artifacts"):
        fast.text(s.stage_run, "../../x")
    with pytest.raises(ValueError, match=r"^artifact path '/etc/passwd' is not inside"):
        inside("/etc/passwd")
    assert inside("./logs//deep/") == "logs/deep"


def test_what_the_reader_does_not_know_goes_to_mlflow(stores):
    _, fast, reference = stores
    for f, order in [
        ("metrics.`nuinteract/avg` > 30", None),
        ("tags.`gdwm.row` != 'A'", None),
        ("tags.`gdwm.row` = 'it\\'s'", None),
        ("tags.`gdwm.kind` = 'trial'", ["metrics.`nuinteract/avg` DESC"]),
        ("attributes.status = 'FAILED'", None),
    ]:
        assert fast.direct().search(fast.experiment_id, f, 1000, order) is None
        got = fast.search(f, 1000, order)  # answered by MLflow's client instead
        assert _same(got, reference.search(f, 1000, order))
    failed = [r["run_id"] for r in reference.search("", 1000) if r["status"] == "FAILED"]
    assert len(failed) > 1 and [r["run_id"] for r in fast.search("attributes.status = 'FAILED'", 1000)] == failed


def test_parsers():
    assert parse_filter("tags.`a.b` = 'x' and params.lr = '0.1'") == [("tags", "a.b", "x"), ("params", "lr", "0.1")]
    assert parse_filter("  ") == []
    assert parse_filter("tags.a = 'x' or tags.b = 'y'") is None
    assert parse_filter("tags.a = 'x' and") is None
    orders = ["attributes.start_time", "attributes.end_time desc"]
    assert parse_order(orders) == [("start_time", True), ("end_time", False)]
    assert parse_order(["attributes.start_time", "attributes.start_time DESC"]) is None  # MLflow refuses duplicates
    assert parse_order(["tags.x"]) is None


def test_a_schema_without_a_column_read_here_is_left_to_mlflow(tmp_path):
    db = tmp_path / "mlflow.db"
    with sqlite3.connect(db) as con:
        for table, cols in {"experiments": "experiment_id, name", "runs": "run_uuid"}.items():
            con.execute(f"CREATE TABLE {table} ({cols})")
    assert SqliteRuns(str(db)).usable() is False
    store = Store(f"sqlite:///{db}", EXPERIMENT)
    assert store.direct() is None
