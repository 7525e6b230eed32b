"""``gdwm ui --mlflow``: the dashboard and MLflow's own UI on the configured store, on 127.0.0.1, until stopped
(SIGTERM or Ctrl-C: exit 0, both servers gone). The dashboard itself: ``tests/gdwm/ui/``."""

import json
import signal
import socket
import subprocess
import sys
import time
import urllib.request

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


def test_ui_serves_the_store_and_stops_cleanly(tmp_path):
    backend = TrackingBackend(f"sqlite:///{tmp_path}/mlflow.db", "gdwm", str(tmp_path / "mlartifacts"))
    run_id = backend.create_run("run-x", {"gdwm.kind": "run"})
    backend.end_run(run_id)
    port, dash = _free_port(), _free_port()
    lines: list[str] = []
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gdwm",
            "ui",
            "--mlflow",
            f"workdir={tmp_path}",
            f"ui.mlflow_port={port}",
            "--port",
            str(dash),
        ],
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
        # gdwm ui names MLflow's URL once it has seen it answer (its own check, a moment after this test's)
        while not any(ln.startswith("MLflow UI: ") for ln in lines) and (ln := proc.stdout.readline()):
            lines.append(ln)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    out = "".join(lines) + out
    assert proc.returncode == 0, out
    assert f"MLflow UI: http://127.0.0.1:{port}" in out and f"gdwm ui: http://127.0.0.1:{dash}/" in out
    assert _refused(port) and _refused(dash)  # both servers and MLflow's workers are gone with it
