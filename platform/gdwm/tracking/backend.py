"""The one object that talks to MLflow, its Ray actor (the single writer for sqlite) and the factory.

MLflow is imported where it is used, not with this module: every Ray worker that runs a stage imports the tracking
package (a stage's ``Tracker`` talks to the tracking actor) and would otherwise pay MLflow's import, 1-2 s of CPU per
worker process, for nothing; only the backend itself (the actor, or the process holding a server-mode backend) does.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import posixpath
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import ray
from ray.actor import ActorHandle
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from gdwm.config import sqlite_path
from gdwm.errors import one_line
from gdwm.redact import redact
from gdwm.tracking.errors import TrackingError
from gdwm.tracking.owner import OWNER_TAG, RECONCILED_TAG, owner_is_alive, process_owner
from gdwm.tracking.params import (
    MAX_METRICS_PER_BATCH,
    MAX_PARAMS_TAGS_PER_BATCH,
    MAX_TAG_VAL_LENGTH,
    batches,
    flatten_params,
    truncate,
)
from gdwm.tracking.reach import failure_line, probe, unreachable
from gdwm.tracking.relocate import relocate_store
from gdwm.tracking.seed import seed_store
from gdwm.tracking.storelock import DEFAULT_TIMEOUT_S, StoreLock, StoreLockTimeout
from gdwm.tracking.writes import NewRun, RunWrite
from gdwm.zoo import registry as zoo

if TYPE_CHECKING:
    from mlflow.exceptions import MlflowException
    from mlflow.store.artifact.artifact_repository import ArtifactRepository

# MLflow prints a link per run it ends on a server ("View run ... at: ...") after one more request: gdwm's output names
# its runs itself, in workers too (they import this module to unpickle a backend).
os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")

log = logging.getLogger(__name__)

TERMINAL = ("FINISHED", "FAILED", "KILLED")
EXPERIMENT_KIND, TRAINING = "mlflow.experimentKind", "custom_model_development"
"""MLflow 3's UI opens an experiment of this kind on its runs (not on its GenAI traces)."""
STAGE_TAG = "gdwm.stage"
DEFAULT_SYSTEM_METRICS_INTERVAL_S = 10.0
_PAGE = 1000


_C = TypeVar("_C", bound=type)


def _one_writer(cls: _C) -> _C:
    """Every public method (and the connection, which creates or migrates the schema) runs holding the store's
    file lock when the store is a sqlite file: two drivers on one workdir never write it at once, and the second
    to start finds the schema complete instead of racing the first one's migration."""

    def locked(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(self, *args, **kwargs):
            try:
                with self._store_lock():
                    return fn(self, *args, **kwargs)
            except StoreLockTimeout as e:  # one line naming the lock and its holder
                raise TrackingError(str(e)) from None
            except Exception as e:
                if isinstance(e, TrackingError):
                    raise
                db = sqlite_path(self.uri)
                if fn.__name__ != "_connect" and db is not None and not Path(db).exists():
                    # sqlite's own words are "attempt to write a readonly database"
                    raise TrackingError(
                        f"tracking store {db} was deleted while gdwm was using it ({one_line(e).splitlines()[0]}); "
                        "the runs of this command went with it: run it again to start a new store"
                    ) from e
                if unreachable(e):  # a server or database gone: one line
                    raise TrackingError(failure_line(self.uri, fn.__name__.strip("_"), e)) from e
                raise

        return wrapper

    for name, fn in list(vars(cls).items()):
        if callable(fn) and (name == "_connect" or not name.startswith("_")):
            setattr(cls, name, locked(fn))
    return cls


@_one_writer
class TrackingBackend:
    """Wraps ``MlflowClient(uri)`` for one experiment; every MLflow write of gdwm goes through one of these."""

    def __init__(
        self,
        uri: str,
        experiment: str,
        artifact_location: str | None = None,
        default_tags: Mapping[str, str] | None = None,
        system_metrics_interval_s: float = DEFAULT_SYSTEM_METRICS_INTERVAL_S,
        lock_timeout_s: float = DEFAULT_TIMEOUT_S,
    ):
        self.uri = uri
        self.experiment = experiment
        self.artifact_location = artifact_location
        self.default_tags = dict(default_tags or {})
        self.system_metrics_interval_s = system_metrics_interval_s
        self.lock_timeout_s = lock_timeout_s
        self._connect()

    def _connect(self) -> None:
        from mlflow.exceptions import MlflowException

        if (why := probe(self.uri)) is not None:  # down, or the password is wrong: now, not after minutes of retries
            raise TrackingError(why)
        if self.artifact_location:  # a workdir copied or moved since: its store points at itself first
            relocate_store(self.uri, self.artifact_location)
        seed_store(self.uri)  # a new sqlite store: a copy of an empty one, not fifty migrations
        self._attach()
        try:
            exp = self.client.get_experiment_by_name(self.experiment)
            if exp is None:
                try:
                    self.experiment_id = self.client.create_experiment(
                        self.experiment, self.artifact_location, tags={EXPERIMENT_KIND: TRAINING}
                    )
                    return
                except MlflowException as e:  # another driver on a shared server made it first: use that one
                    if e.error_code != "RESOURCE_ALREADY_EXISTS":
                        raise
                    exp = self.client.get_experiment_by_name(self.experiment)
                    if exp is None:
                        raise
            if exp.lifecycle_stage == "deleted":
                self.client.restore_experiment(exp.experiment_id)
            if EXPERIMENT_KIND not in exp.tags:
                self.client.set_experiment_tag(exp.experiment_id, EXPERIMENT_KIND, TRAINING)
        except MlflowException as e:
            refused = _refused(self.uri, self.experiment, e)
            if refused is None:
                raise
            raise refused from e
        self.experiment_id = exp.experiment_id

    def _attach(self) -> None:
        from mlflow import MlflowClient

        self.client = MlflowClient(self.uri)
        self._monitors: dict[str, _LateMonitor] = {}
        self._artifact_uris: dict[str, str] = {}
        """Run id -> artifact URI of the runs this backend created: their artifacts need no request to find it."""

    # Shipped to workers in server mode: a new client there instead of a pickled one and its threads. The experiment
    # was found (or made) where the backend was built: a stage task pays no request for it.
    def __getstate__(self) -> dict[str, Any]:
        keys = ("uri", "experiment", "artifact_location", "default_tags", "system_metrics_interval_s",
                "lock_timeout_s", "experiment_id")  # fmt: skip
        return {k: self.__dict__[k] for k in keys}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._attach()

    def _store_lock(self) -> contextlib.AbstractContextManager:
        if (db := sqlite_path(self.uri)) is None:
            return contextlib.nullcontext()
        if getattr(self, "_filelock", None) is None:  # reentrant: a method may call another
            self._filelock = StoreLock(db, getattr(self, "lock_timeout_s", DEFAULT_TIMEOUT_S))
        return self._filelock

    def ready(self) -> str:
        """The experiment id (a cheap round trip that proves an actor started)."""
        return self.experiment_id

    def _owner(self) -> str:
        return self.default_tags.get(OWNER_TAG) or process_owner()

    def create_run(self, name: str, tags: Mapping[str, str], parent_run_id: str | None = None) -> str:
        """A RUNNING run; stage runs (tagged ``gdwm.stage``) also get system metrics."""
        from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID

        all_tags = {OWNER_TAG: self._owner(), **self.default_tags, **tags}
        if parent_run_id:
            all_tags[MLFLOW_PARENT_RUN_ID] = parent_run_id
        all_tags = {k: truncate(redact(str(v)), MAX_TAG_VAL_LENGTH) for k, v in all_tags.items()}
        info = self.client.create_run(self.experiment_id, tags=all_tags, run_name=name).info
        run_id = info.run_id
        self._artifact_uris[run_id] = info.artifact_uri
        if STAGE_TAG in all_tags:
            self.start_system_metrics(run_id)
        return run_id

    def create_runs(self, runs: list[NewRun]) -> list[str]:
        """Create every run (tags, params, texts; ``create_run``'s owner and parent), in order; returns their ids."""
        ids = []
        for r in runs:
            run_id = self.create_run(r.name, r.tags, r.parent_run_id)
            self.write([RunWrite(run_id, params=r.params, texts=r.texts)])
            ids.append(run_id)
        return ids

    def write(self, writes: list[RunWrite]) -> None:
        """Each run's writes (``RunWrite``): its tags, params and metrics packed into as few ``log_batch`` calls as
        MLflow's limits allow (MLflow's client splits them), then its artifacts, its zoo versions' tags, its end."""
        from mlflow.entities import Metric, Param, RunTag

        now = int(time.time() * 1000)
        for w in writes:
            tags = dict(w.tags)
            if w.reopen:
                self.client.update_run(w.run_id, status="RUNNING")
                tags[OWNER_TAG] = self._owner()
            ts = now if w.timestamp_ms is None else w.timestamp_ms
            self.client.log_batch(
                w.run_id,
                metrics=[Metric(k, float(v), ts, w.step or 0) for k, v in w.metrics.items()],
                params=[Param(k, str(v)) for k, v in w.params.items()],
                tags=[RunTag(k, truncate(redact(str(v)), MAX_TAG_VAL_LENGTH)) for k, v in tags.items()],
            )
            for path, text in w.texts.items():
                self.log_text(w.run_id, text, path)
            for local, artifact_dir in w.files:
                self.log_artifact(w.run_id, local, artifact_dir)
            if w.version_tags and w.versions_of:
                zoo.tag_run_versions(self.client, w.versions_of, w.version_tags)
            if w.end is not None:
                self.end_run(w.run_id, w.end)

    def keyed_run(self, match: Mapping[str, str], new: NewRun, resumed: Mapping[str, str], recomputes_tag: str) -> str:
        """The one run of a unit of work (a stage's cache key), found by its ``match`` tags: the newest unfinished one
        (FAILED, KILLED, or RUNNING with its owner gone or this writer's owner) is reopened, ``resumed`` tags added: a
        killed or retried attempt leaves no duplicate. Else ``new`` is created, tagged ``recomputes_tag`` with the
        newest finished one's id where there is one (whose history stays as it was). A live other driver's RUNNING run
        is not taken over: that driver computes the same work, into another cache."""
        where = " and ".join(f"tags.`{k}` = '{v}'" for k, v in match.items())
        found = self.search_runs(where, order_by=["attributes.start_time DESC"])
        mine = self._owner()
        for r in found:
            owner = r["tags"].get(OWNER_TAG)
            if r["status"] in ("FAILED", "KILLED") or (
                r["status"] == "RUNNING" and (owner is None or owner == mine or not owner_is_alive(owner))
            ):
                self.reopen_run(r["run_id"])
                self.set_tags(r["run_id"], resumed)
                return r["run_id"]
        tags = dict(new.tags)
        finished = [r for r in found if r["status"] == "FINISHED"]
        if finished:
            tags[recomputes_tag] = finished[0]["run_id"]
        return self.create_runs([NewRun(new.name, tags, new.parent_run_id, new.params, new.texts)])[0]

    def reopen_run(self, run_id: str) -> None:
        """RUNNING again (resuming a KILLED/FAILED run), owned by this backend's owner from now on."""
        self.client.update_run(run_id, status="RUNNING")
        self.set_tags(run_id, {OWNER_TAG: self._owner()})
        if STAGE_TAG in self.client.get_run(run_id).data.tags:
            self.start_system_metrics(run_id, resume=True)

    def log_params(self, run_id: str, params: Mapping[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(k, v) for k, v in flatten_params(params).items()]
        for chunk in batches(items, MAX_PARAMS_TAGS_PER_BATCH):
            self.client.log_batch(run_id, params=chunk)

    def log_metrics(
        self, run_id: str, metrics: Mapping[str, float], step: int | None = None, timestamp_ms: int | None = None
    ) -> None:
        from mlflow.entities import Metric

        ts = int(time.time() * 1000) if timestamp_ms is None else timestamp_ms
        items = [Metric(k, float(v), ts, step or 0) for k, v in metrics.items()]
        for chunk in batches(items, MAX_METRICS_PER_BATCH):
            self.client.log_batch(run_id, metrics=chunk)

    def set_tags(self, run_id: str, tags: Mapping[str, str]) -> None:
        from mlflow.entities import RunTag

        items = [RunTag(k, truncate(redact(str(v)), MAX_TAG_VAL_LENGTH)) for k, v in tags.items()]
        for chunk in batches(items, MAX_PARAMS_TAGS_PER_BATCH):
            self.client.log_batch(run_id, tags=chunk)

    def log_artifact(self, run_id: str, local_path: str, artifact_path: str | None = None) -> None:
        if (repo := self._artifact_repo(run_id)) is None or os.path.isdir(local_path):
            self.client.log_artifact(run_id, local_path, artifact_path)
        else:
            repo.log_artifact(local_path, artifact_path)

    def log_text(self, run_id: str, text: str, artifact_file: str) -> None:
        text = redact(text)  # error.txt may quote a URI
        if run_id not in self._artifact_uris:
            self.client.log_text(run_id, text, artifact_file)
            return
        folder, name = posixpath.split(artifact_file)
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / name).write_text(text, encoding="utf-8")
            self.log_artifact(run_id, str(Path(d) / name), folder or None)

    def _artifact_repo(self, run_id: str) -> ArtifactRepository | None:
        """The artifact store of a run this backend created, from the URI its creation returned: MLflow's client asks
        the store for the run first, one request per run a process logs a file to (3 a no-op trial, when it sent ~30
        requests to a team server). None for other runs (MLflow's client finds theirs)."""
        if (uri := self._artifact_uris.get(run_id)) is None:
            return None
        from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

        return get_artifact_repository(uri, tracking_uri=self.uri)

    def register_component(self, run_id: str, name: str, local_path: str, variant: str, tags: Mapping[str, str]) -> int:
        """Log ``local_path`` as the MLflow model ``zoo/<name>`` of the run and register it as a new version of
        ``name`` (alias ``candidate``); returns the version."""
        from gdwm.zoo import registry as zoo

        return zoo.register(self.client, run_id, name, local_path, variant, tags)

    def tag_versions(self, cache_keys: list[str], tags: Mapping[str, str]) -> list[tuple[str, int]]:
        """Add ``tags`` to the zoo versions registered by the stage runs with these cache keys."""
        from gdwm.zoo import registry as zoo

        return zoo.tag_versions(self.client, cache_keys, tags)

    def end_run(self, run_id: str, status: str = "FINISHED") -> None:
        if status not in TERMINAL:
            raise ValueError(f"run {run_id}: end status must be one of {TERMINAL}, got {status!r}")
        self.stop_system_metrics(run_id)
        self.client.set_terminated(run_id, status)

    def start_system_metrics(self, run_id: str, resume: bool = False) -> None:
        """Sample CPU/memory/disk/network (and GPU) of *this* process's host into ``system/*`` every
        ``system_metrics_interval_s`` (<= 0: off) until the run ends, from one interval after it starts
        (``_LateMonitor``). In single-writer mode this runs in the tracking actor (the only sqlite writer, on the
        driver's node); in server mode in the process that created the run (the stage's task)."""
        if run_id in self._monitors or self.system_metrics_interval_s <= 0:
            return
        self._monitors[run_id] = _LateMonitor(run_id, self.system_metrics_interval_s, resume, self.uri)

    def stop_system_metrics(self, run_id: str) -> None:
        monitor = self._monitors.pop(run_id, None)
        if monitor is not None:
            monitor.finish()

    def close(self) -> None:
        """Stop every system-metrics monitor (flushing their last samples)."""
        for run_id in list(self._monitors):
            self.stop_system_metrics(run_id)

    def search_runs(
        self, filter_string: str = "", max_results: int = 1000, order_by: list[str] | None = None
    ) -> list[dict]:
        from mlflow.entities import ViewType

        out: list[dict] = []
        token = None
        while len(out) < max_results:
            page = self.client.search_runs(
                [self.experiment_id],
                filter_string,
                ViewType.ACTIVE_ONLY,
                max_results=min(_PAGE, max_results - len(out)),
                order_by=order_by,
                page_token=token,
            )
            out += [run_dict(r) for r in page]
            token = page.token
            if not token:
                break
        return out

    def metric_history(self, run_id: str, key: str) -> list[tuple[int, float]]:
        history = sorted(self.client.get_metric_history(run_id, key), key=lambda m: (m.step, m.timestamp))
        return [(m.step, m.value) for m in history]

    def reconcile(self, is_alive: Callable[[str], bool] | None = None) -> list[str]:
        """End KILLED every RUNNING run whose owner is gone (or unknown); returns their ids."""
        from mlflow.entities import RunStatus

        is_alive = is_alive or owner_is_alive
        now = datetime.now(UTC).isoformat(timespec="seconds")
        killed = []
        for run in self.search_runs(f"attributes.status = '{RunStatus.to_string(RunStatus.RUNNING)}'", 10**9):
            owner = run["tags"].get(OWNER_TAG)
            if owner is not None and is_alive(owner):
                continue
            self.set_tags(run["run_id"], {RECONCILED_TAG: now})
            self.end_run(run["run_id"], "KILLED")
            killed.append(run["run_id"])
        if killed:
            log.warning("reconciled %d run(s) left RUNNING by dead owners: %s", len(killed), ", ".join(killed))
        return killed


class _LateMonitor:
    """MLflow's ``SystemMetricsMonitor`` of one run, started one sampling interval after the run. MLflow's monitor
    samples at once, publishes after an interval, and asks the store for the run (a request to a server) each
    interval and once more as it stops; a run that ends within the first interval records nothing either way. So
    starting late costs a stage run none of its samples, only the first one (taken at the start, before the stage
    did anything), and a stage shorter than the interval (a cached lookup, a sweep's evaluation of a few seconds)
    no request and no sampling thread."""

    def __init__(self, run_id: str, interval_s: float, resume: bool, uri: str):
        self._args = (run_id, interval_s, resume, uri)
        self._lock = threading.Lock()
        self._monitor: Any = None
        self._ended = False
        self._timer = threading.Timer(interval_s, self._start)
        self._timer.daemon = True
        self._timer.start()

    def _start(self) -> None:
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        run_id, interval_s, resume, uri = self._args
        with self._lock:
            if self._ended:
                return
            self._monitor = SystemMetricsMonitor(
                run_id, sampling_interval=interval_s, resume_logging=resume, tracking_uri=uri
            )
            self._monitor.start()

    @property
    def started(self) -> bool:
        """Whether MLflow's monitor was ever started (it stays set once the run ended)."""
        return self._monitor is not None

    def finish(self) -> None:
        """Stop sampling (the samples so far flushed); a monitor not started yet never starts. Once only."""
        self._timer.cancel()
        with self._lock:
            if self._ended:
                return
            self._ended = True
        if self._monitor is not None:
            self._monitor.finish()


def _refused(uri: str, experiment: str, e: MlflowException) -> PermissionError | None:
    """A server's 401/403 as an error that says what to set (the CLI prints it, exit 1); None for others."""
    from mlflow.utils.credentials import read_mlflow_creds

    user = read_mlflow_creds().username  # the name only, never the password
    uri = redact(uri)
    status = e.get_http_status_code()
    if status == 401:
        who = f"rejected the credentials of user '{user}'" if user else "needs credentials"
        return PermissionError(
            f"MLflow server {uri} {who} (401): set MLFLOW_TRACKING_USERNAME/MLFLOW_TRACKING_PASSWORD"
        )
    if status == 403:
        return PermissionError(f"MLflow server {uri} denied user '{user}' access to experiment '{experiment}' (403)")
    return None


def run_dict(run) -> dict:
    info = run.info
    return {
        "run_id": info.run_id,
        "name": info.run_name,
        "status": info.status,
        "start_time": info.start_time,
        "end_time": info.end_time,
        "artifact_uri": info.artifact_uri,
        "tags": dict(run.data.tags),
        "params": dict(run.data.params),
        "metrics": dict(run.data.metrics),
    }


# One call at a time: the actor is the only process writing a sqlite store.
TrackingActor = ray.remote(num_cpus=0, max_concurrency=1)(TrackingBackend)

Sink = TrackingBackend | ActorHandle


def _field(cfg: Any, name: str, default: Any) -> Any:
    try:
        value = getattr(cfg, name)
    except (AttributeError, KeyError):
        return default
    return default if value is None else value


def open_tracking(cfg_tracking: Any, owner_tags: Mapping[str, str] | None = None) -> tuple[Sink, Callable[[], None]]:
    """``(sink, close)`` for a ``TrackingConfig``: the single-writer actor (needs Ray initialised, pinned to
    this node where the sqlite file lives) or a local backend. ``owner_tags`` (default: this process as
    ``gdwm.owner``) go on every run the sink creates; ``close()`` stops monitors and kills the actor."""
    tags = dict(owner_tags) if owner_tags is not None else {OWNER_TAG: process_owner()}
    interval = float(_field(cfg_tracking, "system_metrics_interval_s", DEFAULT_SYSTEM_METRICS_INTERVAL_S))
    timeout = float(_field(cfg_tracking, "lock_timeout_s", DEFAULT_TIMEOUT_S))
    args = (cfg_tracking.uri, cfg_tracking.experiment, cfg_tracking.artifact_location, tags, interval, timeout)
    if not cfg_tracking.single_writer:
        backend = TrackingBackend(*args)
        return backend, backend.close
    if not ray.is_initialized():
        raise RuntimeError(
            f"tracking.single_writer=true ({cfg_tracking.uri}): the tracking actor needs Ray; call ray.init() first"
        )
    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
    actor = TrackingActor.options(name=f"gdwm-tracking-{uuid.uuid4().hex[:12]}", scheduling_strategy=here).remote(*args)
    try:
        ray.get(actor.ready.remote())
    except ray.exceptions.RayActorError as e:
        raise TrackingError(f"tracking.uri={redact(cfg_tracking.uri)}: {one_line(e)}") from e
    closed = []

    def close() -> None:
        if closed:
            return
        closed.append(True)
        try:
            ray.get(actor.close.remote())
        finally:
            ray.kill(actor, no_restart=True)
            _wait_until_dead(actor)

    return actor, close


def _wait_until_dead(actor: Any, timeout_s: float = 60.0) -> None:
    """``ray.kill`` only asks for the kill; the sqlite store is free for another writer once the actor is gone."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            ray.get(actor.__ray_ready__.remote(), timeout=5.0)
        except ray.exceptions.RayActorError:
            return
        except ray.exceptions.GetTimeoutError:
            continue
        time.sleep(0.05)
    raise RuntimeError(f"tracking actor {actor} still answers {timeout_s:.0f} s after ray.kill")
