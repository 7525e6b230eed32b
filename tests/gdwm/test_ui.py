"""``gdwm ui``: the MLflow UI on the configured store, on 127.0.0.1, until stopped (SIGTERM or Ctrl-C: exit 0)."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import psutil
import pytest

from gdwm.tracking import TrackingBackend


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=5) as r:
        return r.read()


def _refused(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


@pytest.mark.slow  # make test-all: a real MLflow UI server (~30 s)
def test_ui_serves_the_store_and_stops_cleanly(tmp_path):
    backend = TrackingBackend(f"sqlite:///{tmp_path}/mlflow.db", "gdwm", str(tmp_path / "mlartifacts"))
    run_id = backend.create_run("run-x", {"gdwm.kind": "run"})
    backend.end_run(run_id)
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "gdwm", "ui", f"workdir={tmp_path}", f"ui.port={port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                pytest.fail(f"gdwm ui exited {proc.returncode}: {proc.stdout.read()}")
            try:
                assert _get(f"http://127.0.0.1:{port}/health") == b"OK"
                break
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail("gdwm ui did not answer /health within 120 s")
                time.sleep(0.5)
        found = json.loads(_get(f"http://127.0.0.1:{port}/api/2.0/mlflow/experiments/search?max_results=10"))
        exp = next(e for e in found["experiments"] if e["name"] == "gdwm")
        assert exp["experiment_id"] == backend.experiment_id
        run = json.loads(_get(f"http://127.0.0.1:{port}/api/2.0/mlflow/runs/get?run_id={run_id}"))["run"]
        assert run["info"]["run_name"] == "run-x" and run["info"]["status"] == "FINISHED"
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert f"MLflow UI for sqlite:///{tmp_path}/mlflow.db: http://127.0.0.1:{port}" in out
    assert _refused(port)  # the server and its workers are gone with it


def test_another_server_on_the_port_exits_1_naming_it(tmp_path):
    """Something else listens on ui.port: gdwm never prints that server's URL as its own, and says who holds it."""
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "gdwm", "ui", f"workdir={tmp_path}", f"ui.port={port}"],
                           capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip() == (
        f"gdwm ui: CommandError: ui.port={port}: 127.0.0.1:{port} is already in use by another process (pid "
        f"{os.getpid()}, {psutil.Process().name()}); stop it or choose another ui.port"
    )
