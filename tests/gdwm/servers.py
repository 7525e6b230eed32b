"""Real servers on loopback for the cluster-path tests: a moto S3 server (the cache) and an MLflow tracking server
with basic-auth (tracking). Each test module starts its own from a fixture; these are the shared parts."""

from __future__ import annotations

import base64
import contextlib
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
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import boto3
from moto.server import ThreadedMotoServer

BUCKET = "gdwm"
SECRET = "wJalrXUtnFEMI-not-a-real-secret-K7MDENG"
"""The S3 secret the tests' environment carries: no output may ever show it."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Moto:
    """A moto S3 server on 127.0.0.1 that can go down and come back on the same port (its buckets live in the
    process, so they survive a restart)."""

    def __init__(self):
        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        self.server.start()
        self.port = self.server.get_host_and_port()[1]
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self.up = True

    def stop(self) -> None:
        self.server.stop()
        self.up = False

    def start(self) -> None:
        self.server = ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
        self.server.start()
        self.up = True

    def uri(self, prefix: str) -> str:
        return f"s3://{BUCKET}/{prefix}?endpoint_override=127.0.0.1:{self.port}&scheme=http"

    def client(self):
        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            region_name="us-east-1",
            aws_access_key_id="testing",
            aws_secret_access_key=SECRET,
        )

    def objects(self, prefix: str) -> dict[str, bytes]:
        """Every object under ``prefix/`` (directory markers, keys ending in '/', left out) with its bytes."""
        c = self.client()
        listed = c.list_objects_v2(Bucket=BUCKET, Prefix=f"{prefix}/").get("Contents", [])
        return {
            o["Key"]: c.get_object(Bucket=BUCKET, Key=o["Key"])["Body"].read()
            for o in listed
            if not o["Key"].endswith("/")
        }

    def env(self) -> dict[str, str]:
        """What a gdwm process needs in its environment to reach this server (never on its command line)."""
        return {
            "AWS_ACCESS_KEY_ID": "testing",
            "AWS_SECRET_ACCESS_KEY": SECRET,
            "AWS_REGION": "us-east-1",
            "AWS_ENDPOINT_URL": self.endpoint,
        }


@dataclass
class MlflowServer:
    uri: str
    admin_password: str
    trainer_password: str
    log: Path

    def creds(self, user: str = "trainer", password: str | None = None) -> dict[str, str]:
        """``MLFLOW_TRACKING_URI/USERNAME/PASSWORD`` of a user (the trainer's password by default)."""
        if password is None:
            password = self.admin_password if user == "admin" else self.trainer_password
        return {"MLFLOW_TRACKING_URI": self.uri, "MLFLOW_TRACKING_USERNAME": user, "MLFLOW_TRACKING_PASSWORD": password}


def rest_call(uri: str, method: str, path: str, body: dict | None = None, auth: tuple[str, str] | None = None):
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


def _health(uri: str) -> int:
    try:
        return rest_call(uri, "GET", "/health")[0]
    except OSError:
        return 0


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


@contextlib.contextmanager
def mlflow_auth_server(root: Path) -> Iterator[MlflowServer]:
    """``mlflow server --app-name basic-auth`` on loopback, its stores under ``root``, with a user ``trainer`` that
    may write (MLflow ships no admin password: it comes from ``MLFLOW_AUTH_ADMIN_PASSWORD``; default READ)."""
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
    port = free_port()
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
                raise RuntimeError(f"mlflow server exited {proc.returncode}:\n{log.read_text()[-3000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"mlflow server did not answer /health within 120 s:\n{log.read_text()[-3000:]}")
            time.sleep(0.5)
        # A user that may write: default READ lets it create an experiment, which it then manages.
        trainer_password = secrets.token_urlsafe(18)
        user = {"username": "trainer", "password": trainer_password}
        assert rest_call(uri, "POST", "/api/2.0/mlflow/users/create", user, ("admin", admin_password))[0] == 200
        yield MlflowServer(uri, admin_password, trainer_password, log)
    finally:
        _stop(proc)
