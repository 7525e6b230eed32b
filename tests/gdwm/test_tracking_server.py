"""``tracking=server`` against a real ``mlflow server --app-name basic-auth`` on loopback.

The server gets its admin password from ``MLFLOW_AUTH_ADMIN_PASSWORD`` (MLflow ships none) and gives every
user READ by default; gdwm takes the URI and credentials from ``MLFLOW_TRACKING_URI/USERNAME/PASSWORD``.
"""

from __future__ import annotations

import secrets
from pathlib import Path

import mlflow
import pytest

from gdwm.tracking import TrackingBackend
from tests.gdwm.servers import MlflowServer, mlflow_auth_server, rest_call
from tests.gdwm.test_run import Toy, _ok
from tests.gdwm.test_tracking import wait_for

pytestmark = pytest.mark.heavy(1.5)

# One server start (25-50 s on a loaded 2-CPU box) plus two `gdwm run`s on local Ray: minutes, not seconds.


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> MlflowServer:
    with mlflow_auth_server(tmp_path_factory.mktemp("mlflow-server")) as server:
        yield server
    assert server.admin_password not in server.log.read_text()


def test_unauthenticated_write_is_rejected_401(server):
    probe = "/api/2.0/mlflow/experiments/get-by-name?experiment_name=anonymous"
    status, body = rest_call(server.uri, "POST", "/api/2.0/mlflow/experiments/create", {"name": "anonymous"})
    assert status == 401 and "You are not authenticated" in body
    assert rest_call(server.uri, "GET", probe)[0] == 401  # reads need a login too
    assert rest_call(server.uri, "GET", probe, auth=("admin", server.admin_password))[0] == 404  # nothing was created


def test_read_only_user_cannot_write_403(server):
    admin = ("admin", server.admin_password)
    reader = {"username": "reader", "password": secrets.token_urlsafe(18)}
    status, body = rest_call(server.uri, "POST", "/api/2.0/mlflow/users/create", reader, admin)
    assert status == 200 and body["user"]["username"] == "reader" and body["user"]["is_admin"] is False
    status, body = rest_call(
        server.uri, "POST", "/api/2.0/mlflow/experiments/create", {"name": "read-only-probe"}, admin
    )
    assert status == 200
    exp_id = body["experiment_id"]
    as_reader = (reader["username"], reader["password"])

    status, body = rest_call(server.uri, "POST", "/api/2.0/mlflow/runs/create", {"experiment_id": exp_id}, as_reader)
    assert (status, body) == (403, "Permission denied")
    status, body = rest_call(
        server.uri, "GET", f"/api/2.0/mlflow/experiments/get?experiment_id={exp_id}", auth=as_reader
    )
    assert status == 200 and body["experiment"]["name"] == "read-only-probe"
    status, body = rest_call(server.uri, "POST", "/api/2.0/mlflow/runs/search", {"experiment_ids": [exp_id]}, as_reader)
    assert status == 200 and body.get("runs", []) == []  # the refused write created nothing
    # a wrong password is a 401, not a 403
    status, _ = rest_call(
        server.uri, "POST", "/api/2.0/mlflow/runs/create", {"experiment_id": exp_id}, ("reader", "x" * 12)
    )
    assert status == 401


def test_backend_names_missing_credentials_and_refused_access(server, monkeypatch):
    admin = ("admin", server.admin_password)
    reader = {"username": "reader2", "password": secrets.token_urlsafe(18)}
    assert rest_call(server.uri, "POST", "/api/2.0/mlflow/users/create", reader, admin)[0] == 200
    status, body = rest_call(server.uri, "POST", "/api/2.0/mlflow/experiments/create", {"name": "deleted-probe"}, admin)
    assert status == 200
    assert rest_call(server.uri, "POST", "/api/2.0/mlflow/experiments/delete", body, admin)[0] == 200
    for k in ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD", "MLFLOW_TRACKING_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HOME", "/nonexistent")  # no ~/.mlflow/credentials either
    with pytest.raises(PermissionError) as e:
        TrackingBackend(server.uri, "gdwm")
    assert str(e.value) == (
        f"MLflow server {server.uri} needs credentials (401): set MLFLOW_TRACKING_USERNAME/MLFLOW_TRACKING_PASSWORD"
    )
    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", reader["username"])
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", reader["password"])
    with pytest.raises(PermissionError) as e:
        TrackingBackend(server.uri, "deleted-probe")  # reopening a deleted experiment is a write
    assert (
        str(e.value) == f"MLflow server {server.uri} denied user 'reader2' access to experiment 'deleted-probe' (403)"
    )


def test_gdwm_run_logs_with_credentials_from_env(server, tmp_path, monkeypatch):
    toy = Toy(tmp_path)
    creds = server.creds("trainer")
    r = toy.run("tracking=server", "targets=[tokenizer]", "cluster.resources.train.num_workers=1", **creds)
    _ok(r)
    assert server.trainer_password not in r.stdout + r.stderr

    for k, v in server.creds("admin").items():
        monkeypatch.setenv(k, v)
    client = mlflow.MlflowClient(server.uri)
    exp = client.get_experiment_by_name("gdwm")
    assert exp.artifact_location.startswith("mlflow-artifacts:")  # tracking=server leaves artifacts to the server
    runs = client.search_runs([exp.experiment_id], max_results=100)
    assert {r.info.status for r in runs} == {"FINISHED"}
    stages = {r.data.tags["gdwm.stage"]: r for r in runs if "gdwm.stage" in r.data.tags}
    assert sorted(stages) == ["distill", "reconstruct", "tokenizer"]
    parent = [r for r in runs if r.data.tags.get("gdwm.kind") == "run"]
    assert len(parent) == 1 and {r.data.tags["mlflow.parentRunId"] for r in stages.values()} == {parent[0].info.run_id}
    # Stage tasks, scene actors and the Ray Train worker logged directly with the driver's environment.
    assert {"scene-0000/psnr", "scene-0001/psnr", "scene-0002/psnr"} <= set(stages["reconstruct"].data.metrics)
    tok = stages["tokenizer"].info.run_id
    assert [m.step for m in client.get_metric_history(tok, "loss")] == [0, 1, 2, 3]
    world = client.download_artifacts(tok, "train/world.txt", str(tmp_path))  # through the server's artifact proxy
    assert Path(world).read_text() == "world_size=1"


def test_gdwm_run_with_a_wrong_password_names_the_credentials(server, tmp_path):
    r = Toy(tmp_path).run("tracking=server", "targets=[reconstruct]", **server.creds("trainer", "wrong-password-1"))
    assert r.returncode == 1, f"exit {r.returncode}\n{r.stderr[-3000:]}"
    assert (
        f"gdwm run: PermissionError: MLflow server {server.uri} rejected the credentials of user 'trainer' (401): "
        "set MLFLOW_TRACKING_USERNAME/MLFLOW_TRACKING_PASSWORD"
    ) in " ".join(r.stderr.split())  # rich may wrap the line
    assert "Traceback" not in r.stderr and "wrong-password-1" not in r.stdout + r.stderr


def test_texts_and_files_of_a_run_the_backend_created_cost_no_request_for_the_run(server, tmp_path, monkeypatch):
    for k, v in server.creds("trainer").items():
        monkeypatch.setenv(k, v)
    backend = TrackingBackend(server.uri, "artifact-requests", system_metrics_interval_s=0)
    ours = backend.create_run("ours", {})
    theirs = mlflow.MlflowClient(server.uri).create_run(backend.experiment_id).info.run_id  # made by another process
    (tmp_path / "table.csv").write_text("a,b\n1,2\n")
    gets = lambda: server.log.read_text().count("GET /api/2.0/mlflow/runs/get?")  # noqa: E731
    before = gets()
    backend.log_text(ours, "hello", "notes/readme.txt")
    backend.log_artifact(ours, str(tmp_path / "table.csv"), "eval")
    backend.log_text(ours, "top", "top.txt")
    assert gets() == before  # the artifact URI came back when the run was created
    backend.log_text(theirs, "hi", "notes/readme.txt")
    assert gets() == before + 1  # a run made elsewhere: MLflow's client asks for it, once per process
    client = mlflow.MlflowClient(server.uri)
    assert Path(client.download_artifacts(ours, "notes/readme.txt", str(tmp_path / "d1"))).read_text() == "hello"
    assert Path(client.download_artifacts(ours, "eval/table.csv", str(tmp_path / "d2"))).read_text() == "a,b\n1,2\n"
    assert Path(client.download_artifacts(ours, "top.txt", str(tmp_path / "d3"))).read_text() == "top"
    assert Path(client.download_artifacts(theirs, "notes/readme.txt", str(tmp_path / "d4"))).read_text() == "hi"


def test_a_stage_run_shorter_than_the_sampling_interval_costs_no_request_for_system_metrics(server, monkeypatch):
    """MLflow's monitor asks the server for the run each interval and again as it stops: a stage run that ends
    within its first interval (it would record no sample either) asks nothing; a longer one samples as before."""
    for k, v in server.creds("trainer").items():
        monkeypatch.setenv(k, v)
    backend = TrackingBackend(server.uri, "system-metrics-requests", system_metrics_interval_s=1.0)
    gets = lambda: server.log.read_text().count("GET /api/2.0/mlflow/runs/get?")  # noqa: E731
    before = gets()
    short = backend.create_run("short", {"gdwm.stage": "score"})
    monitor = backend._monitors[short]
    backend.end_run(short)
    assert (monitor.started, gets()) == (False, before)
    key = "system/system_memory_usage_megabytes"
    long = backend.create_run("long", {"gdwm.stage": "lora"})
    wait_for(lambda: len(backend.metric_history(long, key)) >= 1, timeout_s=60)
    long_monitor = backend._monitors[long]
    backend.end_run(long)
    assert long_monitor.started and gets() > before  # it asked, interval by interval
    short_run = mlflow.MlflowClient(server.uri).get_run(short)
    assert (short_run.info.status, [k for k in short_run.data.metrics if k.startswith("system/")]) == ("FINISHED", [])
