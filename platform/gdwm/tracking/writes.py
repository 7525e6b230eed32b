"""Writes to many runs in one call: what a launch records per trial, sent as one message instead of one round trip
(and one store transaction) per tag, param set, metric set, text and status change.

A store's cost is per call: a sqlite commit, an HTTP request to a server. A trial's row and trial runs, a stage run's
params and tags, the outcome of a trial (links, metrics, tables, its end) are each a handful of writes to one run, so
``RunWrite`` gathers them and the backend packs their tags, params and metrics into as few ``log_batch`` calls as
MLflow's per-call limits allow. ``WriteQueue`` sends them without waiting where the store is behind the tracking actor
(the driver keeps scheduling while the actor writes) and waits for all of them in ``flush``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import ray
from ray.actor import ActorHandle

MAX_PENDING = 200
"""Queued writes beyond this many wait for the oldest: memory stays bounded and a slow store applies back-pressure."""


@dataclass
class RunWrite:
    """What one call writes to one run, in this order: reopened (RUNNING again, owned by the writer), tags, params and
    metrics (packed into ``log_batch`` calls), texts and files (artifacts), the zoo versions' tags, then its end."""

    run_id: str
    tags: Mapping[str, str] = field(default_factory=dict)
    params: Mapping[str, str] = field(default_factory=dict)
    """Flattened already (``gdwm.tracking.flatten_params``)."""
    metrics: Mapping[str, float] = field(default_factory=dict)
    step: int = 0
    timestamp_ms: int | None = None
    """Of the metrics (None: when written)."""
    texts: Mapping[str, str] = field(default_factory=dict)
    """Artifact path -> text."""
    files: Sequence[tuple[str, str | None]] = ()
    """(local file, artifact directory) to copy as artifacts; the file must stay where it is until written."""
    versions_of: Sequence[str] = ()
    """Runs whose registered zoo versions get ``version_tags`` (a trial's stage runs: its lineage)."""
    version_tags: Mapping[str, str] = field(default_factory=dict)
    end: str | None = None
    """FINISHED, FAILED or KILLED: ends the run after everything else."""
    reopen: bool = False


@dataclass
class NewRun:
    """A run to create (RUNNING) with its tags, params and texts."""

    name: str
    tags: Mapping[str, str]
    parent_run_id: str | None = None
    params: Mapping[str, str] = field(default_factory=dict)
    texts: Mapping[str, str] = field(default_factory=dict)


class WriteQueue:
    """Writes on their way to a sink. Through the tracking actor ``put`` returns at once and ``flush`` waits for every
    queued write and raises the first error; with a backend in this process each write happens in ``put``."""

    def __init__(self, sink: Any):
        self.sink = sink
        self._pending: list[ray.ObjectRef] = []

    def put(self, *writes: RunWrite) -> None:
        if not writes:
            return
        if not isinstance(self.sink, ActorHandle):
            self.sink.write(list(writes))
            return
        self._pending.append(self.sink.write.remote(list(writes)))
        if len(self._pending) >= MAX_PENDING:
            _wait([self._pending.pop(0)])

    def flush(self) -> None:
        pending, self._pending = self._pending, []
        _wait(pending)


def _wait(refs: list[ray.ObjectRef]) -> None:
    """Every write done; the first error as a ``TrackingError`` naming it (the client's words for a refused write)."""
    from gdwm.errors import one_line
    from gdwm.tracking.errors import TrackingError

    try:
        ray.get(refs)
    except ray.exceptions.RayError as e:
        raise TrackingError(f"tracking store write failed: {one_line(e)}") from e
