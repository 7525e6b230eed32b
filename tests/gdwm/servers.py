"""Real servers on loopback for the cluster-path tests: a moto S3 server (the cache), an MLflow tracking server with
basic-auth (tracking) and PostgreSQL (a team's store: MLflow on PostgreSQL with artifacts on S3). Test modules and
session fixtures start them; these are the shared parts."""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import boto3
from moto.server import ThreadedMotoServer

from gdwm.ui.serve import mlflow_server_env

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
        # moto serves through werkzeug, whose logger prints every request at INFO (verbose=False leaves it on)
        logging.getLogger("werkzeug").setLevel(logging.WARNING)
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
def mlflow_auth_server(
    root: Path,
    backend_store_uri: str | None = None,
    artifacts_destination: str | None = None,
    auth_db_uri: str | None = None,
    env: dict[str, str] | None = None,
    workers: int = 1,
) -> Iterator[MlflowServer]:
    """``mlflow server --app-name basic-auth`` on loopback, its stores under ``root`` (or the given ones: a
    PostgreSQL database, an S3 bucket), with a user ``trainer`` that may write (MLflow ships no admin password: it
    comes from ``MLFLOW_AUTH_ADMIN_PASSWORD``; default READ). ``env``: what the server needs besides (S3 keys)."""
    ini = root / "basic_auth.ini"
    ini.write_text(
        "[mlflow]\n"
        "default_permission = READ\n"
        f"database_uri = {auth_db_uri or f'sqlite:///{root}/auth.db'}\n"
        "admin_username = admin\n"
        "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n"
        # Without it every request pays a PBKDF2 hash of the password (1M rounds, seconds on a busy CPU).
        "auth_cache_ttl_seconds = 300\n"
    )
    admin_password = secrets.token_urlsafe(18)
    server_env = mlflow_server_env({k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")})
    server_env.update(
        MLFLOW_FLASK_SERVER_SECRET_KEY=secrets.token_hex(16),
        MLFLOW_AUTH_CONFIG_PATH=str(ini),
        MLFLOW_AUTH_ADMIN_PASSWORD=admin_password,
        **(env or {}),
    )
    port = free_port()
    cmd = [
        *(sys.executable, "-m", "mlflow", "server", "--app-name", "basic-auth"),
        *("--backend-store-uri", backend_store_uri or f"sqlite:///{root}/mlflow.db"),
        *("--artifacts-destination", artifacts_destination or str(root / "art"), "--serve-artifacts"),
        *("--host", "127.0.0.1", "--port", str(port), "--workers", str(workers)),
    ]
    log = root / "server.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, env=server_env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    uri = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while _health(uri) != 200:
            if proc.poll() is not None:
                raise RuntimeError(f"mlflow server exited {proc.returncode}:\n{log.read_text()[-3000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"mlflow server did not answer /health within 180 s:\n{log.read_text()[-3000:]}")
            time.sleep(0.5)
        # A user that may write: default READ lets it create an experiment, which it then manages.
        trainer_password = secrets.token_urlsafe(18)
        user = {"username": "trainer", "password": trainer_password}
        assert rest_call(uri, "POST", "/api/2.0/mlflow/users/create", user, ("admin", admin_password))[0] == 200
        yield MlflowServer(uri, admin_password, trainer_password, log)
    finally:
        _stop(proc)


# ---- PostgreSQL --------------------------------------------------------------------------------------------------
PG_USER = "postgres"
"""The unprivileged user Debian's package creates: PostgreSQL refuses to run as root (CI runs as root)."""


def pg_bindir() -> Path | None:
    """PostgreSQL's server programs (initdb, pg_ctl): on PATH, else Debian's ``/usr/lib/postgresql/<N>/bin`` (the
    newest); None where PostgreSQL is not installed."""
    if found := shutil.which("initdb"):
        return Path(found).resolve().parent
    dirs = [p.parent for p in Path("/usr/lib/postgresql").glob("*/bin/initdb")]
    dirs.sort(key=lambda d: int(d.parent.name) if d.parent.name.isdigit() else 0)
    return dirs[-1] if dirs else None


@dataclass
class Postgres:
    """A PostgreSQL cluster of its own on 127.0.0.1 (password login over TCP; its unix socket in its folder)."""

    bindir: Path
    root: Path
    port: int
    password: str
    """The superuser ``postgres``'s."""

    @property
    def data(self) -> Path:
        return self.root / "data"

    def url(self, user: str, password: str, db: str) -> str:
        return f"postgresql://{user}:{password}@127.0.0.1:{self.port}/{db}"

    def sql(self, *statements: str, db: str = "postgres") -> None:
        """Statements as the superuser, each in its own transaction (CREATE DATABASE can't run inside one)."""
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=PG_USER, password=self.password, dbname=db,
                             autocommit=True) as conn:  # fmt: skip
            for statement in statements:
                conn.execute(statement)

    def database(self, name: str) -> str:
        """A new database owned by a new login role of the same name; returns its URL (with the role's password)."""
        password = secrets.token_urlsafe(18)
        self.sql(f"CREATE ROLE {name} LOGIN PASSWORD '{password}'", f"CREATE DATABASE {name} OWNER {name}")
        return self.url(name, password, name)

    def ctl(self, *args: str) -> None:
        """``pg_ctl`` on this cluster (``start``, ``stop``), as the cluster's owner."""
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1"
        _as_owner([str(self.bindir / "pg_ctl"), "-D", str(self.data), "-l", str(self.root / "server.log"),
                   "-o", opts, "-w", "-t", "120", *args], self.root)  # fmt: skip

    def stop(self) -> None:
        self.ctl("stop", "-m", "fast")

    def start(self) -> None:
        self.ctl("start")


def _as_owner(cmd: list[str], cwd: Path) -> None:
    """Run ``cmd`` as ``postgres`` when this process is root (PostgreSQL refuses root), else as ourselves."""
    kw: dict = {}
    if os.getuid() == 0:
        pw = pwd.getpwnam(PG_USER)
        kw = {"user": pw.pw_uid, "group": pw.pw_gid, "extra_groups": []}
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "LC_ALL": "C.UTF-8", "HOME": str(cwd)}
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=180, **kw)
    if r.returncode != 0:
        log = cwd / "server.log"
        tail = log.read_text()[-2000:] if log.exists() else ""
        raise RuntimeError(f"{' '.join(cmd[:2])} exited {r.returncode}:\n{r.stdout}{r.stderr}\n{tail}")


@contextlib.contextmanager
def postgres_server(durable: bool = False) -> Iterator[Postgres]:
    """A fresh PostgreSQL cluster (initdb into a temp dir its owner holds), started with ``pg_ctl`` on a free port and
    removed afterwards. ``durable=False`` turns fsync off (a test's data need not survive a power cut)."""
    bindir = pg_bindir()
    if bindir is None:
        raise FileNotFoundError("PostgreSQL is not installed (no initdb): make setup installs Debian's postgresql")
    # under /tmp, not pytest's tmp_path: that is root's and mode 0700, which the postgres user can't enter
    root = Path(tempfile.mkdtemp(prefix="gdwm-pg-"))
    password = secrets.token_urlsafe(18)
    (root / "pwfile").write_text(password + "\n")
    if os.getuid() == 0:
        pw = pwd.getpwnam(PG_USER)
        for path in (root, root / "pwfile"):
            os.chown(path, pw.pw_uid, pw.pw_gid)
    pg = Postgres(bindir, root, free_port(), password)
    try:
        initdb = [str(bindir / "initdb"), "-D", str(pg.data), "-U", PG_USER, "--pwfile", str(root / "pwfile")]
        _as_owner([*initdb, "--auth-local=trust", "--auth-host=scram-sha-256", "-E", "UTF8", "--locale=C.UTF-8"], root)
        (root / "pwfile").unlink()
        if not durable:
            with (pg.data / "postgresql.conf").open("a") as f:
                f.write("fsync = off\nsynchronous_commit = off\nfull_page_writes = off\n")
        pg.start()
        yield pg
    finally:
        with contextlib.suppress(Exception):
            pg.ctl("stop", "-m", "immediate")
        shutil.rmtree(root, ignore_errors=True)


@dataclass
class TeamStore:
    """MLflow with basic-auth on PostgreSQL, artifacts on S3 (moto), as a lab runs it (k8s/): what a driver needs to
    reach it is ``server.creds()``; the S3 keys stay with the server."""

    pg: Postgres
    s3: Moto
    server: MlflowServer
    backend_url: str
    """The tracking database's URL (with its role's password)."""


@contextlib.contextmanager
def team_store(root: Path, workers: int = 1, durable: bool = False) -> Iterator[TeamStore]:
    """PostgreSQL, moto and the server, started in that order and stopped in reverse. One uvicorn worker: with more,
    uvicorn's supervisor kills a worker that answers its health check late (a loaded 2-core box: a restart loop)."""
    with postgres_server(durable) as pg:
        s3 = Moto()
        try:
            s3.client().create_bucket(Bucket=BUCKET)
            backend, auth = pg.database("mlflow"), pg.database("mlflow_auth")
            env = {**s3.env(), "MLFLOW_S3_ENDPOINT_URL": s3.endpoint}
            with mlflow_auth_server(root, backend, f"s3://{BUCKET}/mlartifacts", auth, env, workers) as server:
                yield TeamStore(pg, s3, server, backend)
        finally:
            if s3.up:
                s3.stop()
