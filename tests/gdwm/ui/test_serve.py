"""``gdwm ui`` as a command: what it says when the port is busy or the store is missing, gone or refuses it, a run
left RUNNING by a dead driver, and a basic-auth MLflow server read with the right credentials (a screenshot of its
sweep page) and refused with wrong ones (exit 1 naming the URI, no secret)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import urllib.error
import urllib.request

import psutil
import pytest

from gdwm.events import Event
from gdwm.progress import Execution, LaunchProgress
from tests.gdwm.compare_runs import log_store
from tests.gdwm.servers import mlflow_auth_server
from tests.gdwm.ui.dash import browser, dashboard, env


def _ui(*args: str, **extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gdwm", "ui", *args], env=env(**extra), capture_output=True, text=True, timeout=300
    )


def _get(url: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=60) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    s = log_store(tmp_path_factory.mktemp("serve"))
    b = s.backend()
    dead = f"{socket.gethostname()}:999999:1.0"  # no such process on this host: its driver is gone
    s.left_running = b.create_run(
        "sweep-left", {"gdwm.kind": "sweep", "gdwm.sweep": "left_running", "gdwm.owner": dead}
    )
    return s


def test_a_busy_port_is_one_line_naming_it(store):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _ui(f"workdir={store.workdir}", "--port", str(port))
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        f"gdwm ui: port {port} on 127.0.0.1 is in use (pid {os.getpid()}, {psutil.Process().name()}) (ui.port={port}); "
        "pick another with --port N, or --port 0 for a free one"
    ]


def test_no_store_exits_1_naming_it(tmp_path):
    r = _ui(f"workdir={tmp_path}", "--port", "0")
    assert r.returncode == 1
    assert r.stderr.strip() == (
        f"gdwm ui: no MLflow store at {tmp_path}/mlflow.db (the workdir's mlflow.db is gone or was never made)"
    )
    assert not (tmp_path / "mlflow.db").exists()  # reading made nothing


def test_stale_run_and_a_store_that_goes_away(store):
    with dashboard(f"workdir={store.workdir}") as dash:
        assert dash.url.startswith("http://127.0.0.1:")  # loopback unless told
        assert dash.url.endswith(f"/sweeps/{store.left_running}")  # the newest sweep
        status, home = _get(dash.base + "/")
        assert status == 200
        assert '<span class="badge stale" title="its driver (pid 999999 on this host) is gone">stale</span>' in home
        assert home.count("badge failed") == 0 and "abl" in home
        db = store.workdir / "mlflow.db"
        db.rename(store.workdir / "moved.db")
        try:
            status, page = _get(dash.base + "/")
            api_status, api = _get(dash.base + f"/api/sweeps/{store.sweep_id}/live")
        finally:
            (store.workdir / "moved.db").rename(db)
        assert status == 503 and f"no MLflow store at {db}" in page and "Traceback" not in page
        assert api_status == 503 and json.loads(api)["error"].startswith(f"no MLflow store at {db}")
        assert _get(dash.base + "/")[0] == 200  # back once the store is


def _snapshot() -> dict:
    """A finished two-trial launch's snapshot, as the driver writes it."""
    lp = LaunchProgress(
        "sweep",
        "remote",
        "sweep-remote-x",
        {"a": [("train", "k1")], "b": [("train", "k2")]},
        [Execution("train", "k1", ["a"]), Execution("train", "k2", ["b"])],
    )
    for key, trial in (("k1", "a"), ("k2", "b")):
        lp.feed(Event("stage", "running", stage="train", key=key))
        lp.feed(Event("stage", "done", stage="train", key=key))
        lp.feed(Event("trial", "done", trials=[trial]))
    lp.feed(Event("launch", "done"))
    return lp.snapshot("logs/sweep-remote-x/events.jsonl")


def test_a_basic_auth_server_read_with_good_credentials_and_refused_with_bad(tmp_path, monkeypatch):
    from gdwm.tracking import TrackingBackend

    with mlflow_auth_server(tmp_path) as server:
        for k, v in server.creds().items():
            monkeypatch.setenv(k, v)
        b = TrackingBackend(server.uri, "gdwm")
        sweep = b.create_run("sweep-remote", {"gdwm.kind": "sweep", "gdwm.sweep": "remote"})
        snap = _snapshot()
        b.log_text(sweep, json.dumps(snap), "progress/snapshot.json")
        b.set_tags(sweep, {"gdwm.trials_done": "2", "gdwm.trials_failed": "0", "gdwm.trials_total": "2"})
        b.end_run(sweep)
        with dashboard("tracking=server", **server.creds()) as dash, browser() as page:
            page.goto(dash.url)
            assert page.inner_text("#sweep-name") == "remote"
            assert page.inner_text("#trials-done") == "2/2"
            states = page.eval_on_selector_all("#trial-grid td.cell", "tds => tds.map(t => t.dataset.state)")
            assert states == ["done", "done"]
            assert page.inner_text("header .store") == server.uri
            page.screenshot(path=tmp_path / "server-sweep.png", full_page=True)
            print(f"screenshot: {tmp_path / 'server-sweep.png'}")
        bad = _ui("tracking=server", "--port", "0", **server.creds(password="not-the-password"))
    assert bad.returncode == 1
    lines = bad.stderr.strip().splitlines()
    assert lines == [
        f"gdwm ui: MLflow server {server.uri} rejected the credentials of user 'trainer' (401): set "
        "MLFLOW_TRACKING_USERNAME/MLFLOW_TRACKING_PASSWORD"
    ]
    assert "not-the-password" not in bad.stderr + bad.stdout
