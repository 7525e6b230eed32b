"""``tracking=server`` against a real ``mlflow server --app-name basic-auth`` on loopback.

The server gets its admin password from ``MLFLOW_AUTH_ADMIN_PASSWORD`` (MLflow ships none) and gives every
user READ by default; gdwm takes the URI and credentials from ``MLFLOW_TRACKING_URI/USERNAME/PASSWORD``.
"""

from __future__ import annotations

import base64
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import mlflow
import pytest

from gdwm.tracking import TrackingBackend
from tests.gdwm.test_run import Toy, _ok

# One server start (25-50 s on a loaded 2-CPU box) plus two `gdwm run`s on local Ray: minutes, not seconds.
pytestmark = pytest.mark.slow


@dataclass
class Server:
    uri: str
    admin_password: str
    trainer_password: str


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _call(uri: str, method: str, path: str, body: dict | None = None, auth: tuple[str, str] | None = None):
    """``(HTTP status, parsed body)`` of one REST call, errors included."""
    req = urllib.request.Request(
        f"{uri}{path}", method=method, data=None if body is None else json.dumps(body).encode()
    )
    req.add_header("Content-Type", "application/json")
    if auth is not None:
        req.add_header("Authorization", "Basic " + base64.b64encode(":".join(auth).encode()).decode())
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            status, text = r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        status, text = e.code, e.read().decode()
    try:
        return status, json.loads(text)
    except json.JSONDecodeError:
        return status, text


def _stop(proc: subprocess.Popen) -> None:
    # start_new_session made the server the leader of its own group: its uvicorn workers go with it.
    for sig, wait_s in ((signal.SIGTERM, 30), (signal.SIGKILL, 30)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Server:
    root = tmp_path_factory.mktemp("mlflow-server")
    ini = root / "basic_auth.ini"
    ini.write_text(
        "[mlflow]\n"
        "default_permission = READ\n"
        f"database_uri = sqlite:///{root}/auth.db\n"
        "admin_username = admin\n"
        "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n"
        # Without it every request pays a PBKDF2 hash of the password (1M rounds, seconds on a busy CPU).
        "auth_cache_ttl_seconds = 300\n"
    )
    admin_password = secrets.token_urlsafe(18)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env.update(
        MLFLOW_FLASK_SERVER_SECRET_KEY=secrets.token_hex(16),
        MLFLOW_AUTH_CONFIG_PATH=str(ini),
        MLFLOW_AUTH_ADMIN_PASSWORD=admin_password,
    )
    port = _free_port()
    cmd = [
        *(sys.executable, "-m", "mlflow", "server", "--app-name", "basic-auth"),
        *("--backend-store-uri", f"sqlite:///{root}/mlflow.db"),
        *("--artifacts-destination", str(root / "art"), "--serve-artifacts"),
        *("--host", "127.0.0.1", "--port", str(port), "--workers", "1"),
    ]
    log = root / "server.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    uri = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while _health(uri) != 200:
            if proc.poll() is not None:
                pytest.fail(f"mlflow server exited {proc.returncode}:\n{log.read_text()[-3000:]}")
            if time.monotonic() > deadline:
                pytest.fail(f"mlflow server did not answer /health within 120 s:\n{log.read_text()[-3000:]}")
            time.sleep(0.5)
        # A user that may write: default READ lets it create an experiment, which it then manages.
        trainer_password = secrets.token_urlsafe(18)
        user = {"username": "trainer", "password": trainer_password}
        assert _call(uri, "POST", "/api/2.0/mlflow/users/create", user, ("admin", admin_password))[0] == 200
        yield Server(uri, admin_password, trainer_password)
    finally:
        _stop(proc)
    assert admin_password not in log.read_text()


def _health(uri: str) -> int:
    try:
        return _call(uri, "GET", "/health")[0]
    except OSError:
        return 0


def test_unauthenticated_write_is_rejected_401(server):
    probe = "/api/2.0/mlflow/experiments/get-by-name?experiment_name=anonymous"
    status, body = _call(server.uri, "POST", "/api/2.0/mlflow/experiments/create", {"name": "anonymous"})
    assert status == 401 and "You are not authenticated" in body
    assert _call(server.uri, "GET", probe)[0] == 401  # reads need a login too
    assert _call(server.uri, "GET", probe, auth=("admin", server.admin_password))[0] == 404  # nothing was created


def test_read_only_user_cannot_write_403(server):
    admin = ("admin", server.admin_password)
    reader = {"username": "reader", "password": secrets.token_urlsafe(18)}
    status, body = _call(server.uri, "POST", "/api/2.0/mlflow/users/create", reader, admin)
    assert status == 200 and body["user"]["username"] == "reader" and body["user"]["is_admin"] is False
    status, body = _call(server.uri, "POST", "/api/2.0/mlflow/experiments/create", {"name": "read-only-probe"}, admin)
    assert status == 200
    exp_id = body["experiment_id"]
    as_reader = (reader["username"], reader["password"])

    status, body = _call(server.uri, "POST", "/api/2.0/mlflow/runs/create", {"experiment_id": exp_id}, as_reader)
    assert (status, body) == (403, "Permission denied")
    status, body = _call(server.uri, "GET", f"/api/2.0/mlflow/experiments/get?experiment_id={exp_id}", auth=as_reader)
    assert status == 200 and body["experiment"]["name"] == "read-only-probe"
    status, body = _call(server.uri, "POST", "/api/2.0/mlflow/runs/search", {"experiment_ids": [exp_id]}, as_reader)
    assert status == 200 and body.get("runs", []) == []  # the refused write created nothing
    # a wrong password is a 401, not a 403
    status, _ = _call(
        server.uri, "POST", "/api/2.0/mlflow/runs/create", {"experiment_id": exp_id}, ("reader", "x" * 12)
    )
    assert status == 401


def test_backend_names_missing_credentials_and_refused_access(server, monkeypatch):
    admin = ("admin", server.admin_password)
    reader = {"username": "reader2", "password": secrets.token_urlsafe(18)}
    assert _call(server.uri, "POST", "/api/2.0/mlflow/users/create", reader, admin)[0] == 200
    status, body = _call(server.uri, "POST", "/api/2.0/mlflow/experiments/create", {"name": "deleted-probe"}, admin)
    assert status == 200
    assert _call(server.uri, "POST", "/api/2.0/mlflow/experiments/delete", body, admin)[0] == 200
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


def _creds(server: Server, user: str, password: str) -> dict[str, str]:
    return {"MLFLOW_TRACKING_URI": server.uri, "MLFLOW_TRACKING_USERNAME": user, "MLFLOW_TRACKING_PASSWORD": password}


def test_gdwm_run_logs_with_credentials_from_env(server, tmp_path, monkeypatch):
    toy = Toy(tmp_path)
    creds = _creds(server, "trainer", server.trainer_password)
    r = toy.run("tracking=server", "targets=[tokenizer]", "cluster.resources.train.num_workers=1", **creds)
    _ok(r)
    assert server.trainer_password not in r.stdout + r.stderr

    for k, v in _creds(server, "admin", server.admin_password).items():
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
    r = Toy(tmp_path).run("tracking=server", "targets=[reconstruct]", **_creds(server, "trainer", "wrong-password-1"))
    assert r.returncode == 1, f"exit {r.returncode}\n{r.stderr[-3000:]}"
    assert (
        f"gdwm run: PermissionError: MLflow server {server.uri} rejected the credentials of user 'trainer' (401): "
        "set MLFLOW_TRACKING_USERNAME/MLFLOW_TRACKING_PASSWORD"
    ) in " ".join(r.stderr.split())  # rich may wrap the line
    assert "Traceback" not in r.stderr and "wrong-password-1" not in r.stdout + r.stderr
