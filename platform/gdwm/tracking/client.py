"""The typed way to call the tracking store: the same methods whether the backend is in this process or is
the single-writer Ray actor, so a type checker follows every call to ``TrackingBackend``."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Concatenate, ParamSpec, TypeVar

import ray
from ray.actor import ActorHandle

from gdwm.errors import one_line
from gdwm.tracking.backend import Sink, TrackingBackend, TrackingError
from gdwm.tracking.writes import NewRun, RunWrite

P = ParamSpec("P")
R = TypeVar("R")


class TrackingClient:
    """Waits for each call's result. Through the actor, a dead actor or a refused write (a full disk...) raises
    ``TrackingError`` with one line naming it; in-process, the backend's own exception. Picklable: it holds only
    the sink (a backend reconnects on arrival, an actor handle names the same actor)."""

    def __init__(self, sink: Sink):
        self.sink = sink

    def __repr__(self) -> str:
        return f"TrackingClient({type(self.sink).__name__})"

    def _call(self, method: Callable[Concatenate[TrackingBackend, P], R], *args: P.args, **kwargs: P.kwargs) -> R:
        # The backend's function, not its name: renaming a backend method breaks here, where a checker sees it.
        if isinstance(self.sink, ActorHandle):
            try:
                return ray.get(getattr(self.sink, method.__name__).remote(*args, **kwargs))
            except ray.exceptions.RayError as e:
                raise TrackingError(f"tracking store write failed: {one_line(e)}") from e
        return method(self.sink, *args, **kwargs)

    def create_run(self, name: str, tags: Mapping[str, str], parent_run_id: str | None = None) -> str:
        return self._call(TrackingBackend.create_run, name, tags, parent_run_id)

    def create_runs(self, runs: list[NewRun]) -> list[str]:
        return self._call(TrackingBackend.create_runs, runs)

    def write(self, writes: list[RunWrite]) -> None:
        self._call(TrackingBackend.write, writes)

    def keyed_run(self, match: Mapping[str, str], new: NewRun, resumed: Mapping[str, str], recomputes_tag: str) -> str:
        return self._call(TrackingBackend.keyed_run, match, new, resumed, recomputes_tag)

    def reopen_run(self, run_id: str) -> None:
        self._call(TrackingBackend.reopen_run, run_id)

    def log_params(self, run_id: str, params: Mapping[str, Any]) -> None:
        self._call(TrackingBackend.log_params, run_id, params)

    def log_metrics(
        self, run_id: str, metrics: Mapping[str, float], step: int | None = None, timestamp_ms: int | None = None
    ) -> None:
        self._call(TrackingBackend.log_metrics, run_id, metrics, step, timestamp_ms)

    def set_tags(self, run_id: str, tags: Mapping[str, str]) -> None:
        self._call(TrackingBackend.set_tags, run_id, tags)

    def log_artifact(self, run_id: str, local_path: str, artifact_path: str | None = None) -> None:
        self._call(TrackingBackend.log_artifact, run_id, local_path, artifact_path)

    def log_text(self, run_id: str, text: str, artifact_file: str) -> None:
        self._call(TrackingBackend.log_text, run_id, text, artifact_file)

    def register_component(self, run_id: str, name: str, local_path: str, variant: str, tags: Mapping[str, str]) -> int:
        return self._call(TrackingBackend.register_component, run_id, name, local_path, variant, tags)

    def tag_versions(self, cache_keys: list[str], tags: Mapping[str, str]) -> list[tuple[str, int]]:
        return self._call(TrackingBackend.tag_versions, cache_keys, tags)

    def end_run(self, run_id: str, status: str = "FINISHED") -> None:
        self._call(TrackingBackend.end_run, run_id, status)

    def search_runs(
        self, filter_string: str = "", max_results: int = 1000, order_by: list[str] | None = None
    ) -> list[dict]:
        return self._call(TrackingBackend.search_runs, filter_string, max_results, order_by)

    def metric_history(self, run_id: str, key: str) -> list[tuple[int, float]]:
        return self._call(TrackingBackend.metric_history, run_id, key)

    def reconcile(self, is_alive: Callable[[str], bool] | None = None) -> list[str]:
        return self._call(TrackingBackend.reconcile, is_alive)
