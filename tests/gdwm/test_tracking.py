"""MLflow tracking — one writer for sqlite, batches within MLflow's limits, no run left RUNNING."""

import contextlib
import dataclasses
import inspect
import os
import pickle
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import ray
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID
from omegaconf import OmegaConf

from gdwm.config import TrackingConfig
from gdwm.tracking import (
    OWNER_TAG,
    RECONCILED_TAG,
    NewRun,
    RunGuard,
    RunWrite,
    Tracker,
    TrackingBackend,
    TrackingClient,
    batches,
    flatten_params,
    open_tracking,
    process_owner,
)
from gdwm.tracking.backend import TrackingError

EXPERIMENT = "gdwm-test"


@pytest.fixture(scope="session")
def empty_store(tmp_path_factory) -> Path:
    """A migrated, empty sqlite store (creating one costs seconds; copying it, nothing)."""
    path = tmp_path_factory.mktemp("template") / "mlflow.db"
    TrackingBackend(f"sqlite:///{path}", "template", None)
    return path


@pytest.fixture
def cfg(tmp_path, empty_store) -> TrackingConfig:
    shutil.copy(empty_store, tmp_path / "mlflow.db")
    return TrackingConfig(
        uri=f"sqlite:///{tmp_path}/mlflow.db", artifact_location=str(tmp_path / "mlartifacts"), experiment=EXPERIMENT
    )


@pytest.fixture
def backend(cfg) -> TrackingBackend:
    backend = TrackingBackend(cfg.uri, cfg.experiment, cfg.artifact_location)
    yield backend
    backend.close()


def run_of(backend: TrackingBackend, run_id: str) -> dict:
    (run,) = backend.search_runs(f"attributes.run_id = '{run_id}'")
    return run


def read_artifact(backend: TrackingBackend, run_id: str, name: str) -> str:
    return Path(backend.client.download_artifacts(run_id, name)).read_text()


def wait_for(condition, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"condition not met within {timeout_s} s"
        time.sleep(0.05)


def start_child(cfg: TrackingConfig, body: str, cwd: Path) -> tuple[subprocess.Popen, str]:
    """A python process that opens ``cfg``'s store, creates a run, prints its id and runs ``body``."""
    script = textwrap.dedent(
        f"""
        import sys, time
        from gdwm.tracking import RunGuard, TrackingBackend
        b = TrackingBackend({cfg.uri!r}, {cfg.experiment!r}, None)
        run_id = b.create_run("child", {{}})
        """
    ) + textwrap.dedent(body)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=cwd, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline().strip()
    assert len(line) == 32, f"child printed {line!r} instead of a run id (exit code {proc.poll()})"
    return proc, line


# -- params and batches ---------------------------------------------------------------------------------------------


def test_flatten_params_nests_keys_lists_as_json_and_truncates():
    cfg = OmegaConf.create(
        {"model": {"lora": {"rank": 8, "alpha": 16.0, "targets": ["q", "v"]}, "name": None}, "empty": {}, "flag": True}
    )
    cfg.long = "x" * 7000
    flat = flatten_params(cfg, prefix="trial.")
    assert {k: v for k, v in flat.items() if k != "trial.long"} == {
        "trial.model.lora.rank": "8",
        "trial.model.lora.alpha": "16.0",
        "trial.model.lora.targets": '["q", "v"]',
        "trial.model.name": "None",
        "trial.empty": "{}",
        "trial.flag": "True",
    }
    assert len(flat["trial.long"]) == 6000
    assert flat["trial.long"] == "x" * (6000 - len("...[truncated, 7000 chars]")) + "...[truncated, 7000 chars]"
    assert flatten_params({"l": [{"a": 1}, [2, 3]]}) == {"l": '[{"a": 1}, [2, 3]]'}


def test_a_mapping_whose_keys_mlflow_refuses_in_names_is_one_json_param():
    # the release importer's task_map: "NuInteract_RD&P" is no MLflow param name, so the map is logged whole
    flat = flatten_params({"data": {"task_map": {"NuInteract_RD&P": "rdp", "NuInteract_2DVG": "vg2d"}, "n": 1}})
    assert flat == {"data.task_map": '{"NuInteract_RD&P": "rdp", "NuInteract_2DVG": "vg2d"}', "data.n": "1"}


def test_batches_split_at_size():
    assert [len(b) for b in batches(range(250), 100)] == [100, 100, 50]
    assert list(batches([], 100)) == []
    assert list(batches("abc", 2)) == [["a", "b"], ["c"]]
    with pytest.raises(ValueError, match="batch size must be >= 1, got 0"):
        list(batches([1], 0))


def test_log_params_and_metrics_split_into_mlflow_batches(backend, monkeypatch):
    params = {"stage": {f"s{i}": {"lr": i / 10, "layers": [i, i + 1]} for i in range(120)}, "note": "y" * 7000}
    calls = []
    real = backend.client.log_batch
    monkeypatch.setattr(
        backend.client,
        "log_batch",
        lambda run_id, **kw: calls.append({k: len(v) for k, v in kw.items()}) or real(run_id, **kw),
    )
    run_id = backend.create_run("params", {})
    backend.log_params(run_id, params)
    backend.log_metrics(run_id, {f"m{i}": float(i) for i in range(2500)}, step=7)

    assert calls == [
        {"params": 100},
        {"params": 100},
        {"params": 41},
        {"metrics": 1000},
        {"metrics": 1000},
        {"metrics": 500},
    ]
    run = run_of(backend, run_id)
    assert run["params"] == flatten_params(params)
    assert len(run["params"]) == 241
    assert run["params"]["stage.s17.lr"] == "1.7"
    assert run["params"]["stage.s17.layers"] == "[17, 18]"
    assert run["params"]["note"].endswith("...[truncated, 7000 chars]")
    assert len(run["params"]["note"]) == 6000
    assert len(run["metrics"]) == 2500
    assert run["metrics"]["m1234"] == 1234.0
    assert backend.metric_history(run_id, "m1234") == [(7, 1234.0)]


# -- runs -----------------------------------------------------------------------------------------------------------


def test_child_run_is_nested_under_its_parent_and_owned_by_this_process(backend):
    parent = backend.create_run("sweep", {"gdwm.sweep": "ablation"})
    child = backend.create_run("trial-0", {"gdwm.stage": "lora"}, parent_run_id=parent)
    tags = run_of(backend, child)["tags"]
    assert tags[MLFLOW_PARENT_RUN_ID] == parent
    assert tags["gdwm.stage"] == "lora"
    assert tags[OWNER_TAG] == process_owner()
    assert MLFLOW_PARENT_RUN_ID not in run_of(backend, parent)["tags"]
    host, pid, _ = tags[OWNER_TAG].split(":")
    assert (host, int(pid)) == (socket.gethostname(), os.getpid())


def test_server_mode_backend_is_used_directly(cfg, tmp_path):
    cfg.single_writer = False
    sink, close = open_tracking(cfg, {OWNER_TAG: "driver-host:1:2.00"})
    assert type(sink) is TrackingBackend
    run_id = sink.create_run("stage", {"gdwm.stage": "reconstruct"})
    # Workers get the backend itself: it must survive pickling and reconnect to the same experiment.
    tracker = pickle.loads(pickle.dumps(Tracker(sink, run_id)))
    assert type(tracker.sink) is TrackingBackend
    assert tracker.sink.experiment_id == sink.experiment_id
    tracker.log_params({"scene": {"count": 3}})
    for step in range(5):
        tracker.log_metrics({"loss": 1.0 / (step + 1)}, step=step)
    tracker.set_tags({"gdwm.cache_key": "abc123"})
    (tmp_path / "manifest.json").write_text('{"key": "abc123"}')
    tracker.log_artifact(str(tmp_path / "manifest.json"), "out")
    tracker.log_text("hello", "notes/readme.txt")
    tracker.flush()
    sink.end_run(run_id)
    close()

    run = run_of(sink, run_id)
    assert run["status"] == "FINISHED"
    assert run["end_time"] >= run["start_time"]
    assert run["params"] == {"scene.count": "3"}
    assert run["tags"]["gdwm.cache_key"] == "abc123"
    assert run["tags"][OWNER_TAG] == "driver-host:1:2.00"
    assert sink.metric_history(run_id, "loss") == [(s, 1.0 / (s + 1)) for s in range(5)]
    assert read_artifact(sink, run_id, "out/manifest.json") == '{"key": "abc123"}'
    assert read_artifact(sink, run_id, "notes/readme.txt") == "hello"
    assert run["artifact_uri"].startswith(str(tmp_path / "mlartifacts"))
    with pytest.raises(ValueError, match="end status must be one of"):
        sink.end_run(run_id, "DONE")


def test_stage_runs_sample_system_metrics_until_they_end(cfg):
    backend = TrackingBackend(cfg.uri, cfg.experiment, None, system_metrics_interval_s=0.1)
    stage = backend.create_run("stage", {"gdwm.stage": "lora"})
    plain = backend.create_run("trial", {})
    key = "system/system_memory_usage_megabytes"
    wait_for(lambda: len(backend.metric_history(stage, key)) >= 2)
    backend.end_run(stage)
    backend.end_run(plain)
    samples = len(backend.metric_history(stage, key))
    assert [k for k in run_of(backend, plain)["metrics"] if k.startswith("system/")] == []
    time.sleep(0.3)
    assert len(backend.metric_history(stage, key)) == samples
    # A resumed stage run continues the step count instead of starting over at 0.
    backend.reopen_run(stage)
    wait_for(lambda: len(backend.metric_history(stage, key)) > samples)
    backend.end_run(stage)
    steps = [step for step, _ in backend.metric_history(stage, key)]
    assert len(steps) > samples
    assert steps == list(range(len(steps)))


def test_open_tracking_single_writer_needs_ray(cfg, monkeypatch):
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    with pytest.raises(RuntimeError, match=r"tracking.single_writer=true .*call ray.init\(\) first"):
        open_tracking(cfg)


# -- many writes in one call ----------------------------------------------------------------------------------------


def test_write_packs_each_runs_writes_into_few_store_calls(backend, monkeypatch, tmp_path):
    table = tmp_path / "predictions.parquet"
    table.write_bytes(b"PAR1")
    a, b = backend.create_run("a", {}), backend.create_run("b", {})
    backend.end_run(b, "KILLED")
    store = backend.client._tracking_client.store
    calls = []
    real = store.log_batch
    monkeypatch.setattr(store, "log_batch", lambda run_id, **kw: calls.append(
        (run_id, {k: len(v) for k, v in kw.items() if v})) or real(run_id, **kw))  # fmt: skip
    backend.write([
        RunWrite(a, tags={f"gdwm.t{i}": str(i) for i in range(30)}, params={f"p{i}": str(i) for i in range(150)},
                 metrics={"acc": 0.5, "loss": 2.0}, step=3, texts={"notes/a.txt": "hello"},
                 files=[(str(table), "evaluate")], end="FINISHED"),
        RunWrite(b, tags={"gdwm.x": "1"}, reopen=True),
    ])  # fmt: skip
    # a's 150 params, 30 tags and 2 metrics in two transactions (MLflow's limit: 100 params a call); b's in one
    assert calls == [(a, {"metrics": 2, "params": 100, "tags": 30}), (a, {"params": 50}), (b, {"tags": 2})]
    ra, rb = run_of(backend, a), run_of(backend, b)
    assert ra["status"] == "FINISHED" and len(ra["params"]) == 150 and ra["tags"]["gdwm.t29"] == "29"
    assert backend.metric_history(a, "acc") == [(3, 0.5)]
    arts = {f.path for f in backend.client.list_artifacts(a, "evaluate")} | {
        f.path for f in backend.client.list_artifacts(a, "notes")}  # fmt: skip
    assert arts == {"evaluate/predictions.parquet", "notes/a.txt"}
    assert rb["status"] == "RUNNING" and rb["tags"][OWNER_TAG] == process_owner() and rb["tags"]["gdwm.x"] == "1"


def test_create_runs_creates_each_with_its_params_and_texts(backend):
    parent = backend.create_run("sweep", {})
    ids = backend.create_runs([NewRun(f"row-{i}", {"gdwm.row": str(i)}, parent, {"x": str(i)}, {"c.json": "{}"})
                               for i in range(3)])  # fmt: skip
    runs = [run_of(backend, i) for i in ids]
    assert [(r["name"], r["params"], r["tags"]["gdwm.row"]) for r in runs] == [
        (f"row-{i}", {"x": str(i)}, str(i)) for i in range(3)]  # fmt: skip
    assert {r["tags"][MLFLOW_PARENT_RUN_ID] for r in runs} == {parent}
    assert [a.path for a in backend.client.list_artifacts(ids[1])] == ["c.json"]


def test_keyed_run_reopens_an_abandoned_attempt_never_a_live_drivers(backend):
    match = {"gdwm.cache_key": "k1", "gdwm.stage": "lora"}
    new = NewRun("lora-k1", {**match, "gdwm.kind": "stage"}, None, {"lr": "0.1"})

    def keyed() -> str:
        return backend.keyed_run(match, new, {"gdwm.resumed": "true"}, "gdwm.recomputes")

    first = keyed()
    assert run_of(backend, first)["params"] == {"lr": "0.1"} and "gdwm.resumed" not in run_of(backend, first)["tags"]
    assert keyed() == first  # RUNNING and ours (a retried task): reopened, no duplicate
    backend.end_run(first, "KILLED")
    assert keyed() == first and run_of(backend, first)["tags"]["gdwm.resumed"] == "true"  # a killed attempt
    backend.end_run(first)
    again = keyed()  # a recompute after a finished run: a new run that says which it recomputes
    assert again != first and run_of(backend, again)["tags"]["gdwm.recomputes"] == first
    # a live other driver's RUNNING run (this test's parent process) is left to it: that driver computes the key too
    backend.set_tags(again, {OWNER_TAG: process_owner(os.getppid())})
    third = keyed()
    assert third not in (first, again) and run_of(backend, again)["status"] == "RUNNING"


def test_an_experiment_another_driver_made_first_is_used(tmp_path, monkeypatch):
    """Drivers starting at once on a shared server all find no experiment; all but one are refused creating it
    (RESOURCE_ALREADY_EXISTS) and must use the one that was made."""
    import mlflow

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    first = TrackingBackend(uri, "team", str(tmp_path / "mlartifacts"))
    real = mlflow.MlflowClient.get_experiment_by_name
    calls = []

    def late(self, name):  # the first look happened before the other driver created it
        calls.append(name)
        return None if len(calls) == 1 else real(self, name)

    monkeypatch.setattr(mlflow.MlflowClient, "get_experiment_by_name", late)
    second = TrackingBackend(uri, "team", str(tmp_path / "mlartifacts"))
    assert calls == ["team", "team"] and second.experiment_id == first.experiment_id


def test_a_server_that_does_not_answer_is_one_line_at_connection(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    with pytest.raises(TrackingError) as e:
        TrackingBackend(f"http://127.0.0.1:{port}", "gdwm")
    assert str(e.value) == f"no MLflow server answers at http://127.0.0.1:{port} (connection refused)"


def test_a_store_failure_is_told_from_a_refused_request():
    from mlflow.exceptions import MlflowException
    from mlflow.protos.databricks_pb2 import RESOURCE_DOES_NOT_EXIST

    from gdwm.tracking.reach import failure_line, unreachable

    down = MlflowException(
        "API request to http://u:pw@127.0.0.1:5/api/2.0/mlflow/runs/create failed with exception HTTPConnectionPool("
        "host='127.0.0.1', port=5): Max retries exceeded (Caused by ResponseError('too many 500 error responses'))"
    )
    assert unreachable(down) and not unreachable(MlflowException("no run x", error_code=RESOURCE_DOES_NOT_EXIST))
    assert failure_line("http://u:pw@127.0.0.1:5", "write", down) == (
        "tracking store http://u:***@127.0.0.1:5 failed write: server errors (HTTP 5xx) on every retry"
    )


# -- single writer --------------------------------------------------------------------------------------------------


def test_two_tasks_log_through_one_tracking_actor(ray_local, cfg):
    sqlite_cfg = OmegaConf.create({**dataclasses.asdict(cfg), "system_metrics_interval_s": 0.2})
    sink, close = open_tracking(sqlite_cfg)
    client = TrackingClient(sink)
    run_id = client.create_run("stage", {"gdwm.stage": "distill"})
    tracker = Tracker(sink, run_id)

    @ray.remote(num_cpus=1)
    def log_300(tracker: Tracker, name: str) -> list[str]:
        errors = []
        try:
            for step in range(300):
                tracker.log_metrics({f"{name}/loss": step * 0.5}, step=step)
            tracker.flush()
        except Exception as e:  # reported back so the test can name the error
            errors.append(repr(e))
        return errors

    assert ray.get([log_300.remote(tracker, "a"), log_300.remote(tracker, "b")]) == [[], []]
    # its sampler starts one interval after the run (gdwm.tracking.backend._LateMonitor): its first sample, then end
    wait_for(lambda: len(client.metric_history(run_id, "system/cpu_utilization_percentage")) >= 1)
    client.end_run(run_id)
    assert client.metric_history(run_id, "a/loss") == [(s, s * 0.5) for s in range(300)]
    assert len(client.metric_history(run_id, "b/loss")) == 300
    run = client.search_runs(f"attributes.run_id = '{run_id}'")[0]
    assert run["status"] == "FINISHED"
    assert run["tags"][OWNER_TAG] == process_owner()  # the driver's, not the actor's
    # A stage run: system metrics were sampled in the actor, the only writer, while the tasks ran.
    assert len(client.metric_history(run_id, "system/cpu_utilization_percentage")) >= 1
    close()
    close()  # idempotent
    with pytest.raises(ray.exceptions.RayActorError):
        ray.get(sink.ready.remote())
    # The actor is gone, so this process may open the store now.
    assert len(TrackingBackend(cfg.uri, cfg.experiment, None).metric_history(run_id, "b/loss")) == 300


def test_tracker_flush_raises_the_actors_error(ray_local, cfg):
    sink, close = open_tracking(cfg)
    try:
        tracker = Tracker(sink, "0" * 32)
        tracker.log_metrics({"loss": 1.0}, step=0)
        copy = pickle.loads(pickle.dumps(tracker))
        assert copy._pending == [] and copy.run_id == "0" * 32
        with pytest.raises(ray.exceptions.RayTaskError, match=f"Run with id={'0' * 32} not found"):
            tracker.flush()
        tracker.flush()  # the failed calls are not re-raised
    finally:
        close()


# -- the typed client -----------------------------------------------------------------------------------------------

# Called by open_tracking and by the backend itself, never through a client.
BACKEND_ONLY = {"ready", "close", "start_system_metrics", "stop_system_metrics"}


def test_tracking_client_has_every_backend_method_with_its_signature():
    backend_methods = {n for n, f in vars(TrackingBackend).items() if callable(f) and not n.startswith("_")}
    client_methods = {n for n, f in vars(TrackingClient).items() if callable(f) and not n.startswith("_")}
    assert client_methods == backend_methods - BACKEND_ONLY
    for name in sorted(client_methods):
        expected = inspect.signature(getattr(TrackingBackend, name))
        # ray.remote(TrackingBackend) gives the class's methods a keyword-only _ray_trace_ctx.
        expected = expected.replace(parameters=[p for p in expected.parameters.values() if p.name != "_ray_trace_ctx"])
        assert inspect.signature(getattr(TrackingClient, name)) == expected, name


@ray.remote(num_cpus=0)
def _log_from_a_task(client: TrackingClient, run_id: str) -> None:
    client.log_metrics(run_id, {"from_task": 2.0}, step=7)


def exercise(client: TrackingClient, artifact: Path) -> dict:
    """Every client method a driver uses on runs, and what the store holds afterwards."""
    parent = client.create_run("sweep", {"gdwm.sweep": "ablation"})
    run_id = client.create_run("trial", {"gdwm.row": "0"}, parent)
    client.log_params(run_id, {"lr": 0.1, "model": {"depth": 2}})
    for step in range(3):
        client.log_metrics(run_id, {"loss": 1.0 / (step + 1)}, step=step, timestamp_ms=1000 + step)
    client.set_tags(run_id, {"gdwm.cache_key": "abc123"})
    client.log_text(run_id, "hello", "notes/readme.txt")
    client.log_artifact(run_id, str(artifact), "out")
    client.end_run(run_id, "FAILED")
    client.reopen_run(run_id)
    # The client pickles: a task gets a working copy (the actor's handle, or a backend that reconnects).
    ray.get(_log_from_a_task.remote(pickle.loads(pickle.dumps(client)), run_id))
    client.end_run(run_id)
    killed = client.reconcile(lambda owner: False)
    run = client.search_runs(f"attributes.run_id = '{run_id}'")[0]
    return {
        "status": run["status"],
        "params": run["params"],
        "metrics": run["metrics"],
        "tags": {k: v for k, v in run["tags"].items() if k.startswith("gdwm.")},
        "nested": run["tags"][MLFLOW_PARENT_RUN_ID] == parent,
        "loss": client.metric_history(run_id, "loss"),
        "from_task": client.metric_history(run_id, "from_task"),
        "killed_parent": killed == [parent],
        "runs": sorted((r["name"], r["status"]) for r in client.search_runs()),
    }


def test_tracking_client_gives_the_same_results_in_process_and_through_the_actor(ray_local, cfg, tmp_path):
    artifact = tmp_path / "manifest.json"
    artifact.write_text('{"key": "abc123"}')
    local_cfg = dataclasses.replace(cfg, uri=f"sqlite:///{tmp_path}/local.db")
    shutil.copy(tmp_path / "mlflow.db", tmp_path / "local.db")
    local = TrackingClient(TrackingBackend(local_cfg.uri, local_cfg.experiment, local_cfg.artifact_location))
    actor, close = open_tracking(cfg)
    remote = TrackingClient(actor)
    try:
        in_process = exercise(local, artifact)
        assert exercise(remote, artifact) == in_process
        with pytest.raises(ValueError, match="end status must be one of"):
            local.end_run(local.create_run("x", {}), "DONE")
        with pytest.raises(TrackingError, match=r"^tracking store write failed: .*end status must be one of"):
            remote.end_run(remote.create_run("x", {}), "DONE")
    finally:
        close()
        local.sink.close()
    assert in_process == {
        "status": "FINISHED",
        "params": {"lr": "0.1", "model.depth": "2"},
        "metrics": {"loss": 1.0 / 3, "from_task": 2.0},
        "tags": {"gdwm.row": "0", "gdwm.owner": process_owner(), "gdwm.cache_key": "abc123"},
        "nested": True,
        "loss": [(0, 1.0), (1, 0.5), (2, 1.0 / 3)],
        "from_task": [(7, 2.0)],
        "killed_parent": True,
        "runs": [("sweep", "KILLED"), ("trial", "FINISHED")],
    }


# -- no run left RUNNING --------------------------------------------------------------------------------------------


def test_run_guard_logs_exception_as_error_txt_and_fails(backend):
    run_id = backend.create_run("stage", {})
    with pytest.raises(ValueError, match="scene-0003"), RunGuard(backend, run_id) as tracker:
        tracker.log_metrics({"loss": 0.25}, step=1)
        raise ValueError("scene-0003/frame_007 CAM_FRONT: image unreadable")
    run = run_of(backend, run_id)
    assert run["status"] == "FAILED"
    assert run["metrics"] == {"loss": 0.25}
    error = read_artifact(backend, run_id, "error.txt")
    assert "Traceback" in error
    assert error.rstrip().endswith("ValueError: scene-0003/frame_007 CAM_FRONT: image unreadable")


@pytest.mark.parametrize(
    ("exc", "status"),
    [(None, "FINISHED"), (KeyboardInterrupt(), "KILLED"), (SystemExit(0), "FINISHED"), (SystemExit(3), "FAILED")],
)
def test_run_guard_end_status(backend, exc, status):
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    parent = backend.create_run("sweep", {})
    child = backend.create_run("trial", {}, parent_run_id=parent)
    with (
        pytest.raises(type(exc)) if exc else contextlib.nullcontext(),
        RunGuard(backend, parent),
        RunGuard(backend, child),
    ):
        assert signal.getsignal(signal.SIGTERM) is not before[0]
        if exc:
            raise exc
    assert [run_of(backend, r)["status"] for r in (parent, child)] == [status, status]
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_sigterm_ends_guarded_run_killed(cfg, tmp_path):
    TrackingBackend(cfg.uri, cfg.experiment, cfg.artifact_location)  # the experiment exists before the child writes
    body = """
        with RunGuard(b, run_id):
            print(run_id, flush=True)
            time.sleep(120)
        """
    proc, run_id = start_child(cfg, body, tmp_path)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM
    run = run_of(TrackingBackend(cfg.uri, cfg.experiment, None), run_id)
    assert run["status"] == "KILLED"
    assert run["end_time"] is not None


def test_reconcile_kills_runs_of_dead_owners_only(cfg, tmp_path):
    backend = TrackingBackend(cfg.uri, cfg.experiment, cfg.artifact_location)
    proc, dead = start_child(cfg, "print(run_id, flush=True)\ntime.sleep(120)\n", tmp_path)
    proc.kill()
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    # Only now (the child is gone) does this process write again: one writer at a time.
    mine = backend.create_run("live", {})
    elsewhere = backend.create_run("remote", {OWNER_TAG: "some-other-host:1:1.00"})
    orphan = backend.create_run("no-owner", {})
    backend.client.delete_tag(orphan, OWNER_TAG)
    finished = backend.create_run("done", {OWNER_TAG: "some-other-host:1:1.00"})
    backend.end_run(finished)
    assert run_of(backend, dead)["tags"][OWNER_TAG].split(":")[1] == str(proc.pid)

    assert sorted(backend.reconcile()) == sorted([dead, orphan])
    status = {r["run_id"]: r["status"] for r in backend.search_runs()}
    assert status == {dead: "KILLED", orphan: "KILLED", mine: "RUNNING", elsewhere: "RUNNING", finished: "FINISHED"}
    assert RECONCILED_TAG in run_of(backend, dead)["tags"]
    assert RECONCILED_TAG not in run_of(backend, mine)["tags"]
    assert backend.reconcile() == []

    # Resuming the killed run makes this process its owner, so reconcile leaves it alone.
    backend.reopen_run(dead)
    assert run_of(backend, dead)["status"] == "RUNNING"
    assert run_of(backend, dead)["tags"][OWNER_TAG] == process_owner()
    assert backend.reconcile() == []
    assert sorted(backend.reconcile(is_alive=lambda owner: owner != process_owner())) == sorted([dead, mine])


def test_a_store_deleted_while_in_use_is_named_in_one_line(tmp_path):
    """mlflow.db removed under a running command: sqlite says "attempt to write a readonly database"; gdwm says the
    store was deleted."""
    db = tmp_path / "mlflow.db"
    backend = TrackingBackend(f"sqlite:///{db}", EXPERIMENT, str(tmp_path / "mlartifacts"), system_metrics_interval_s=0)
    run_id = backend.create_run("r", {})
    db.unlink()
    with pytest.raises(TrackingError) as e:
        backend.log_params(run_id, {"a": 1})
    assert str(e.value) == (
        f"tracking store {db} was deleted while gdwm was using it (MlflowException: (sqlite3.OperationalError) attempt "
        "to write a readonly database); the runs of this command went with it: run it again to start a new store"
    )
