"""``gdwm ui``: serve the dashboard until Ctrl-C or SIGTERM (exit 0).

Order matters for what a user sees: the port is bound first (a busy one fails at once, naming it), then the store is
reached (unreachable or credentials refused: exit 1 naming its URI, no secret), then uvicorn serves on the bound
socket, and the URL, a deep link to the newest sweep, is printed only once that page has answered 200.
``--mlflow`` also starts MLflow's own UI on the store (``ui.mlflow_port``) and every page links to it.
"""

from __future__ import annotations

import base64
import contextlib
import errno
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Mapping
from pathlib import Path

from omegaconf import DictConfig

from gdwm.config import sqlite_path, ui_url
from gdwm.errors import CommandError
from gdwm.ports import holder
from gdwm.term import console, err_console
from gdwm.ui.store import Store, StoreError


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (0: a free port); a busy port is one line naming it."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a port left in TIME_WAIT is free; one in use is not
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        if e.errno == errno.EADDRINUSE:
            raise CommandError(
                f"port {port} on {host} is in use{holder(port)} (ui.port={port}); pick another with --port N, or "
                "--port 0 for a free one"
            ) from None
        raise CommandError(f"cannot listen on {host}:{port} (ui.host, ui.port): {e.strerror or e}") from None
    sock.listen(128)
    sock.set_inheritable(False)
    return sock


def _shown_host(host: str) -> str:
    return "127.0.0.1" if host in ("0.0.0.0", "", "::") else host


def _option(args: list[str], name: str) -> str | None:
    return next((a.split("=", 1)[1] for a in args if a.startswith(f"{name}=")), None)


def _own_auth() -> dict[str, str]:
    """The dashboard's own credentials (for its readiness check when it asks for a login)."""
    user, password = os.environ.get("MLFLOW_TRACKING_USERNAME"), os.environ.get("MLFLOW_TRACKING_PASSWORD")
    if not user or password is None:
        return {}
    return {"Authorization": "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()}


def mlflow_command(cfg: DictConfig, host: str, port: int) -> tuple[list[str], str]:
    """``mlflow server`` on the store and its URL (port 0: a free one, picked now)."""
    if port == 0:
        with socket.socket() as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
    cmd = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", cfg.tracking.uri, "--workers", "1"]
    cmd += ["--host", host, "--port", str(port)]
    if cfg.tracking.artifact_location:
        cmd += ["--artifacts-destination", cfg.tracking.artifact_location]
    return cmd, f"http://{_shown_host(host)}:{port}"


JOBS_ENV = "MLFLOW_SERVER_ENABLE_JOB_EXECUTION"


def mlflow_server_env(environ: Mapping[str, str]) -> dict[str, str]:
    """An MLflow server's environment: without MLflow's job execution unless asked for. gdwm runs no MLflow jobs
    (GenAI judges, trace rollups), and with it on the server starts 8 job consumers, each a whole MLflow process:
    28 s of CPU before it answers instead of 7 s on 2 cores, and their memory for as long as it runs."""
    return {**environ, JOBS_ENV: environ.get(JOBS_ENV, "false")}


def _stop(proc: subprocess.Popen | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def _announce(
    server,
    base: str,
    deep: str,
    what: str,
    mlflow: tuple[list[str], str] | None,
    answered: threading.Event,
    started: list[subprocess.Popen],
) -> None:
    """Print the URL once the deep-linked page answers; with ``--mlflow``, then start MLflow's UI (in its own process
    group: stopping it stops its workers; after the first page, whose start it would slow down) and print its URL once
    it answers."""
    while not server.started and not server.should_exit:
        time.sleep(0.01)
    if server.should_exit:
        return
    try:
        _first_page(base, deep, what)
    finally:
        answered.set()
    if mlflow is not None and not server.should_exit:
        cmd, url = mlflow
        proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                env=mlflow_server_env(os.environ))  # fmt: skip
        started.append(proc)
        _mlflow_ready(server, (proc, url))


def _first_page(base: str, deep: str, what: str) -> None:
    url = base + deep
    try:
        req = urllib.request.Request(url, headers=_own_auth())
        with urllib.request.urlopen(req, timeout=120) as r:
            ok = r.status == 200
    except urllib.error.HTTPError as e:
        ok = False
        err_console.print(f"gdwm ui: {url} answered {e.code}; every launch: {base}/", markup=False)
    except OSError as e:
        ok = False
        err_console.print(f"gdwm ui: {url} did not answer ({e}); every launch: {base}/", markup=False)
    if ok:
        console.print(f"gdwm ui: {url}  ({what}; every launch: {base}/; Ctrl-C stops it)", markup=False, soft_wrap=True)


def _mlflow_ready(server, mlflow: tuple[subprocess.Popen, str]) -> None:
    """MLflow's URL once its UI answers (it starts in tens of seconds), or why it exited."""
    proc, murl = mlflow
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not server.should_exit:
        try:
            with urllib.request.urlopen(f"{murl}/health", timeout=5) as r:
                if r.status == 200:
                    console.print(f"MLflow UI: {murl}", markup=False)
                    return
        except OSError:
            time.sleep(0.5)
    if proc.poll() is not None:
        tail = (proc.stderr.read().decode(errors="replace") if proc.stderr else "").strip().splitlines()
        err_console.print(f"gdwm ui: MLflow's UI exited {proc.returncode}: {tail[-1] if tail else ''}", markup=False)


def serve(cfg: DictConfig, args: list[str]) -> int:
    import uvicorn

    from gdwm.ui.app import MlflowAuth, create_app
    from gdwm.ui.pages import Context, newest_sweep
    from gdwm.ui.tables import Tables, Whys

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame) -> None:  # stop serving; gdwm ui then exits 0 (not re-raised)
            if self.should_exit and sig == signal.SIGINT:
                self.force_exit = True
            else:
                self.should_exit = True

    host = _option(args, "--host") or cfg.ui.host
    port_text = _option(args, "--port") or str(cfg.ui.port)
    if not port_text.isdigit() or int(port_text) > 65535:
        raise CommandError(f"--port {port_text}: a port number 0-65535 (0 picks a free one)")
    uri = cfg.tracking.uri
    auth = None
    if str(cfg.ui.auth) == "mlflow":
        if not uri.startswith(("http://", "https://")):
            raise CommandError(f"ui.auth=mlflow checks logins against an MLflow server; tracking.uri is {uri}")
        auth = MlflowAuth(uri, cfg.tracking.experiment)
    sock = bind(host, int(port_text))
    port = sock.getsockname()[1]
    store = Store(uri, cfg.tracking.experiment)
    try:
        store.connect()
        newest = newest_sweep(store)
    except StoreError as e:
        sock.close()
        raise CommandError(str(e)) from None
    mlflow = None
    mlflow_url = cfg.ui.url or (ui_url(cfg) if uri.startswith(("http://", "https://")) else None)
    if "--mlflow" in args and not uri.startswith(("http://", "https://")):
        mlflow = mlflow_command(cfg, host, int(cfg.ui.mlflow_port))
        mlflow_url = cfg.ui.url or mlflow[1]
    started: list[subprocess.Popen] = []
    workdirs = [p for p in {store.workdir, Path(cfg.workdir).resolve()} if p is not None and p.is_dir()]
    overrides = [
        a
        for a in args
        if "=" in a
        and not a.startswith("--")
        and a.split("=", 1)[0].lstrip("+~").split(".")[0] in ("workdir", "tracking")
    ]
    if sqlite_path(uri) is None:
        overrides.append(f"tracking.uri={uri}")  # the worker reads the same store
    answered = threading.Event()
    ctx = Context(
        store, workdirs, mlflow_url, Tables(hold=answered), Whys(str(cfg.cache.uri)), float(cfg.ui.poll_s), overrides
    )
    app = create_app(ctx, auth)
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off", timeout_graceful_shutdown=3)
    server = Server(config)
    base = f"http://{_shown_host(host)}:{port}"
    deep = f"/sweeps/{newest['run_id']}" if newest else "/"
    what = f"sweep {newest['tags'].get('gdwm.sweep', newest['name'])}, the newest" if newest else "no sweep yet"
    threading.Thread(target=_announce, args=(server, base, deep, what, mlflow, answered, started), daemon=True).start()
    try:
        server.run(sockets=[sock])
    finally:
        ctx.tables.close()
        for proc in started:
            _stop(proc)
        sock.close()
    return 0
