"""The dashboard's read-only view of the tracking store: an MLflow server through MLflow's client (basic-auth
credentials from ``MLFLOW_TRACKING_USERNAME``/``PASSWORD``); a workdir's sqlite file through ``gdwm.ui.sqlite``'s
reads where they answer (MLflow's client for the rest).

It never writes: no experiment is created, no lock is taken (``TrackingBackend`` serialises writers; a reader needs
neither), and a sqlite file that is gone is reported instead of being recreated empty by SQLite. Every failure is a
``StoreError`` whose one line names the store (credentials masked), so a page can say so instead of a stack trace.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from gdwm.config import sqlite_path
from gdwm.redact import redact
from gdwm.ui.sqlite import SqliteRuns, inside, list_local

# A store that does not answer fails a page in seconds, not after MLflow's default 7 retries with backoff.
# No progress bar per artifact read on the dashboard's console.
HTTP_DEFAULTS = {
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "1",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "20",
    "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false",
}
TERMINAL = ("FINISHED", "FAILED", "KILLED")

_F = TypeVar("_F", bound=Callable[..., Any])


class StoreError(Exception):
    """The store cannot be read; the message is one line naming it (no secret)."""


def first_line(e: BaseException) -> str:
    """``Type: first line of the message``, credentials masked."""
    text = getattr(e, "message", None) or str(e)
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return redact(f"{type(e).__name__}: {lines[0]}" if lines else type(e).__name__)


def refused(shown: str, e: BaseException) -> str | None:
    """The line for a server's 401 / 403 (naming the user, never the password); None for other errors."""
    status = getattr(e, "get_http_status_code", lambda: None)()
    user = os.environ.get("MLFLOW_TRACKING_USERNAME")
    if status == 401:
        who = f"rejected the credentials of user '{user}'" if user else "needs credentials"
        return f"MLflow server {shown} {who} (401): set MLFLOW_TRACKING_USERNAME/MLFLOW_TRACKING_PASSWORD"
    if status == 403:
        return f"MLflow server {shown} denied user '{user}' access (403)"
    return None


def _reads(fn: _F) -> _F:
    """Any failure of a read as a ``StoreError`` naming the store."""

    @functools.wraps(fn)
    def wrapper(self: Store, *args, **kwargs):
        self.check_file()
        try:
            return fn(self, *args, **kwargs)
        except StoreError:
            raise
        except Exception as e:  # MLflow, SQLAlchemy, requests, OSError: the page says which store and why
            raise StoreError(refused(self.shown, e) or f"the store {self.shown} cannot be read: {first_line(e)}") from e

    return wrapper  # type: ignore[return-value]


def run_dict(run: Any) -> dict:
    """A run as plain data: id, name, status, times, experiment, artifact URI, tags, params, metrics."""
    info = run.info
    return {
        "run_id": info.run_id,
        "name": info.run_name or "",
        "status": info.status,
        "start_time": info.start_time,
        "end_time": info.end_time,
        "experiment_id": info.experiment_id,
        "artifact_uri": info.artifact_uri,
        "tags": dict(run.data.tags),
        "params": dict(run.data.params),
        "metrics": dict(run.data.metrics),
    }


class Store:
    """One experiment of one tracking store, read through ``mlflow.MlflowClient``; a sqlite store's runs, metrics and
    local artifacts are read without MLflow (``gdwm.ui.sqlite``: the same answers, without MLflow's 4-5 s import)."""

    def __init__(self, uri: str, experiment: str):
        for k, v in HTTP_DEFAULTS.items():
            os.environ.setdefault(k, v)
        self.uri = uri
        self.shown = redact(uri)
        self.experiment = experiment
        self.db = sqlite_path(uri)
        self.experiment_id: str | None = None
        self._client = None
        self._direct = SqliteRuns(self.db) if self.db else None
        self._histories: dict[tuple[str, str], list[tuple[int, float]]] = {}
        self._lock = threading.Lock()

    @property
    def workdir(self) -> Path | None:
        """The workdir of a sqlite store (the folder of its file): events and tracebacks live there."""
        return Path(self.db).parent if self.db else None

    def check_file(self) -> None:
        if self.db is not None and not Path(self.db).is_file():
            # SQLite would create an empty file and MLflow a new schema: a reader must not
            raise StoreError(f"no MLflow store at {self.db} (the workdir's mlflow.db is gone or was never made)")

    def direct(self) -> SqliteRuns | None:
        """The sqlite reader where it can read this store's schema."""
        return self._direct if self._direct is not None and self._direct.usable() else None

    def _local(self, run_id: str) -> Path | None:
        direct = self.direct()
        return direct.artifact_root(run_id) if direct is not None else None

    @property
    def client(self):
        if self._client is None:
            with self._lock:
                if self._client is None:
                    from mlflow import MlflowClient  # the one heavy import of the dashboard

                    self._client = MlflowClient(self.uri, registry_uri=self.uri)
        return self._client

    @_reads
    def connect(self) -> None:
        """Reach the store and find the experiment (absent: nothing has been logged yet; pages say so)."""
        if (direct := self.direct()) is not None:
            self.experiment_id = direct.experiment_id(self.experiment)
            return
        exp = self.client.get_experiment_by_name(self.experiment)
        self.experiment_id = exp.experiment_id if exp is not None and exp.lifecycle_stage == "active" else None

    @_reads
    def search(self, filter_string: str = "", max_results: int = 1000, order_by: list[str] | None = None) -> list[dict]:
        """Runs of the experiment matching an MLflow filter, every page of them up to ``max_results``."""
        if self.experiment_id is None:
            self.connect()
            if self.experiment_id is None:
                return []
        if (direct := self.direct()) is not None:
            found = direct.search(self.experiment_id, filter_string, max_results, order_by)
            if found is not None:  # None: a filter or order the reader does not know; MLflow answers it
                return found
        from mlflow.entities import ViewType

        out: list[dict] = []
        token = None
        while len(out) < max_results:
            page = self.client.search_runs(
                [self.experiment_id],
                filter_string,
                ViewType.ACTIVE_ONLY,
                max_results=min(1000, max_results - len(out)),
                order_by=order_by,
                page_token=token,
            )
            out += [run_dict(r) for r in page]
            token = page.token
            if not token:
                break
        return out

    @_reads
    def run(self, run_id: str) -> dict:
        if (direct := self.direct()) is not None:
            if (found := direct.run(run_id)) is None:
                raise StoreError(f"the store {self.shown} has no run {run_id}")
            return found
        return run_dict(self.client.get_run(run_id))

    @_reads
    def history(self, run_id: str, key: str, finished: bool) -> list[tuple[int, float]]:
        """(step, value) of a metric, by step; kept for runs that ended (their history no longer changes)."""
        if (run_id, key) in self._histories:
            return self._histories[run_id, key]
        if (direct := self.direct()) is not None:
            out = direct.history(run_id, key)
        else:
            ms = sorted(self.client.get_metric_history(run_id, key), key=lambda m: (m.step, m.timestamp))
            out = [(m.step, m.value) for m in ms]
        if finished:
            self._histories[run_id, key] = out
        return out

    @_reads
    def artifacts(self, run_id: str, path: str | None = None) -> list[tuple[str, bool, int | None]]:
        """(path, is_dir, size) of a run's artifacts under ``path``."""
        if (root := self._local(run_id)) is not None:
            return list_local(root, path)
        return [(f.path, f.is_dir, f.file_size) for f in self.client.list_artifacts(run_id, path)]

    @_reads
    def download(self, run_id: str, path: str, dst: str) -> str:
        if (root := self._local(run_id)) is not None:
            out = Path(dst) / Path(inside(path)).name
            shutil.copy2(root / inside(path), out)
            return str(out)
        return self.client.download_artifacts(run_id, path, dst)

    def exists(self, run_id: str, path: str) -> bool:
        parent = path.rpartition("/")[0] or None
        return any(p == path and not is_dir for p, is_dir, _ in self.artifacts(run_id, parent))

    @_reads
    def text(self, run_id: str, path: str) -> str | None:
        """An artifact's text; None where the run has no such artifact."""
        if (root := self._local(run_id)) is not None:
            file = root / inside(path)
            return file.read_text(encoding="utf-8", errors="replace") if file.is_file() else None
        if not self.exists(run_id, path):
            return None
        with tempfile.TemporaryDirectory(prefix="gdwm-ui-") as tmp:
            return Path(self.download(run_id, path, tmp)).read_text(encoding="utf-8", errors="replace")

    def json(self, run_id: str, path: str) -> Any:
        text = self.text(run_id, path)
        try:
            return None if text is None else json.loads(text)
        except json.JSONDecodeError:
            return None

    @_reads
    def model_versions(self) -> list[dict]:
        """Every registered version (name, version, aliases, tags, run, created), newest model first."""
        out = []
        for model in self.client.search_registered_models(max_results=1000):
            aliases: dict[str, list[str]] = {}
            for alias, version in (model.aliases or {}).items():
                aliases.setdefault(str(version), []).append(alias)
            for mv in self.client.search_model_versions(f"name = '{model.name}'", max_results=1000):
                out.append(
                    {
                        "name": mv.name,
                        "version": int(mv.version),
                        "aliases": sorted(aliases.get(str(mv.version), [])),
                        "tags": dict(mv.tags),
                        "run_id": mv.run_id,
                        "created": mv.creation_timestamp,
                        "source": mv.source,
                    }
                )
        return sorted(out, key=lambda v: (v["name"], -v["version"]))
