"""What a stage sees: one run, logged to a backend directly or through the tracking actor."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any, Concatenate, ParamSpec

import ray
from ray.actor import ActorHandle

from gdwm.tracking.backend import Sink, TrackingBackend
from gdwm.tracking.params import flatten_params

# Waiting on the oldest calls beyond this many bounds memory and applies back-pressure on a slow store.
MAX_PENDING = 1000

P = ParamSpec("P")


class Tracker:
    """Bound to one run. With an actor sink calls are queued (``.remote()``) and ``flush()`` waits for them
    and raises the first error; with a backend sink calls are direct. Picklable (pending calls stay behind)."""

    def __init__(self, sink: Sink, run_id: str):
        self.sink = sink
        self.run_id = run_id
        self._pending: list[ray.ObjectRef] = []

    def __getstate__(self) -> dict[str, Any]:
        return {"sink": self.sink, "run_id": self.run_id}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["sink"], state["run_id"])

    def __repr__(self) -> str:
        return f"Tracker(run_id={self.run_id!r}, sink={type(self.sink).__name__})"

    @property
    def remote(self) -> bool:
        return isinstance(self.sink, ActorHandle)

    def _send(
        self, method: Callable[Concatenate[TrackingBackend, str, P], None], *args: P.args, **kwargs: P.kwargs
    ) -> None:
        if not self.remote:
            method(self.sink, self.run_id, *args, **kwargs)
            return
        self._pending.append(getattr(self.sink, method.__name__).remote(self.run_id, *args, **kwargs))
        if len(self._pending) >= MAX_PENDING:
            self.flush()

    def log_params(self, params: Mapping[str, Any]) -> None:
        self._send(TrackingBackend.log_params, flatten_params(params))

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        # Stamped here, not when the actor gets to it.
        self._send(
            TrackingBackend.log_metrics, {k: float(v) for k, v in metrics.items()}, step, int(time.time() * 1000)
        )

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self._send(TrackingBackend.set_tags, {k: str(v) for k, v in tags.items()})

    def log_artifact(self, path: str, artifact_path: str | None = None) -> None:
        """Copied before returning (the caller may delete ``path`` next). Through the actor, ``path`` must be
        readable on the driver's node (local Ray or a shared filesystem)."""
        self._send(TrackingBackend.log_artifact, str(path), artifact_path)
        self.flush()

    def log_text(self, text: str, artifact_file: str) -> None:
        self._send(TrackingBackend.log_text, text, artifact_file)

    def flush(self) -> None:
        """Wait until every queued call has been written; raises the first error the actor hit."""
        pending, self._pending = self._pending, []
        if pending:
            ray.get(pending)
