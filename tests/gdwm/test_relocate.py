"""A copied workdir's store follows the copy: artifacts read from and written to the copy, the original untouched
byte for byte; a sibling folder sharing the name's prefix is not rewritten; params carry paths relative to the
workdir. In process, no Ray."""

from __future__ import annotations

import hashlib
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

from gdwm.cli import main
from gdwm.tracking import TrackingBackend
from gdwm.tracking.params import relative_paths
from gdwm.tracking.relocate import relocate_store


def _store(work: Path) -> TrackingBackend:
    return TrackingBackend(f"sqlite:///{work}/mlflow.db", "gdwm", str(work / "mlartifacts"))


def _digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def test_a_copied_store_reads_and_writes_the_copy_only(tmp_path):
    a, b = tmp_path / "a" / "w", tmp_path / "b" / "w"
    backend = _store(a)
    run = backend.create_run("r", {"gdwm.kind": "run"})
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "weights.bin").write_bytes(b"\x01\x02")
    backend.log_text(run, "first", "notes/first.txt")
    version = backend.register_component(run, "gdwm-toy", str(tmp_path / "model"), "toy-v1", {})
    backend.end_run(run)
    shutil.copytree(a, b)
    before = _digest(a)

    copy = _store(b)  # the copy re-roots its store on connecting
    assert copy.client.get_run(run).info.artifact_uri == f"{b}/mlartifacts/{run}/artifacts"
    assert Path(copy.client.download_artifacts(run, "notes/first.txt", str(tmp_path))).read_text() == "first"
    copy.log_text(run, "second", "notes/second.txt")
    assert (b / "mlartifacts" / run / "artifacts" / "notes" / "second.txt").read_text() == "second"
    # the CLI on the copy: zoo show lists the copy's files
    assert main(["zoo", "show", f"workdir={b}", "args.name=gdwm-toy", f"args.version={version}"]) == 0
    assert _digest(a) == before
    assert relocate_store(f"sqlite:///{b}/mlflow.db", str(b / "mlartifacts")) == 0  # done once


def test_only_paths_under_the_old_root_move(tmp_path):
    a = tmp_path / "w"
    _store(a)
    db = a / "mlflow.db"
    with sqlite3.connect(db) as c:  # a run of another folder whose name starts with the workdir's
        c.execute("update runs set artifact_uri = 'x'")
        c.execute(f"insert into experiments (name, artifact_location, lifecycle_stage) values "
                  f"('other', '{a}/mlartifacts-other', 'active')")  # fmt: skip
    b = tmp_path / "moved"
    shutil.move(a, b)
    assert relocate_store(f"sqlite:///{b}/mlflow.db", str(b / "mlartifacts")) == 1
    with sqlite3.connect(b / "mlflow.db") as c:
        assert sorted(r[0] for r in c.execute("select artifact_location from experiments where name != 'Default'")) \
            == sorted([f"{a}/mlartifacts-other", f"{b}/mlartifacts"])  # fmt: skip


def test_a_server_store_keeps_its_uris():
    assert relocate_store("http://mlflow:5000", "s3://bucket/artifacts") == 0


def test_params_carry_paths_relative_to_the_workdir():
    params = {"workdir": "/data/w", "cache.uri": "/data/w/cache", "tracking.uri": "sqlite:////data/w/mlflow.db",
              "data.root": "/data/ds", "note": "a /slash inside text", "lr": "0.1",
              "other.uri": "file:///data/c?token=***"}  # fmt: skip
    assert relative_paths(params, "/data/w") == {
        "workdir": ".", "cache.uri": "cache", "tracking.uri": "sqlite:///mlflow.db", "data.root": "../ds",
        "note": "a /slash inside text", "lr": "0.1", "other.uri": "file:///data/c?token=***"}  # fmt: skip


def test_a_store_configured_with_a_quoted_file_uri_follows_the_copy(tmp_path):
    # tracking.artifact_location is a file URI (`${file_uri:...}`), percent-quoted where the path needs it
    a, b = tmp_path / "a" / "w #1", tmp_path / "b" / "w #1"
    backend = TrackingBackend(f"sqlite:///{a}/mlflow.db", "gdwm", (a / "mlartifacts").as_uri())
    run = backend.create_run("r", {"gdwm.kind": "run"})
    backend.log_text(run, "first", "notes/first.txt")
    backend.end_run(run)
    shutil.copytree(a, b)
    before = _digest(a)
    assert relocate_store(f"sqlite:///{b}/mlflow.db", (b / "mlartifacts").as_uri()) >= 2  # the experiment and the run
    copy = TrackingBackend(f"sqlite:///{b}/mlflow.db", "gdwm", (b / "mlartifacts").as_uri())
    assert Path(copy.client.download_artifacts(run, "notes/first.txt", str(tmp_path))).read_text() == "first"
    copy.log_text(run, "second", "notes/second.txt")
    assert (b / "mlartifacts" / run / "artifacts" / "notes" / "second.txt").read_text() == "second"
    assert _digest(a) == before


def test_a_moved_workdir_is_followed_without_importing_mlflow(tmp_path):
    """gdwm ui on a copied demo workdir starts in about 2 s; importing MLflow only to clear its (empty) per-process
    artifact repository cache cost 2.5 s of it."""
    a = tmp_path / "w"
    run = _store(a).create_run("r", {"gdwm.kind": "run"})
    b = tmp_path / "moved"
    shutil.move(a, b)
    code = (
        "import sys; from gdwm.tracking.relocate import relocate_store; "
        f"n = relocate_store('sqlite:///{b}/mlflow.db', '{b}/mlartifacts'); print(n, 'mlflow' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["2", "False"]  # the experiment's root and the run's artifact URI, MLflow never imported
    with sqlite3.connect(b / "mlflow.db") as c:
        assert c.execute("select artifact_uri from runs where run_uuid = ?", (run,)).fetchone()[0].startswith(str(b))
