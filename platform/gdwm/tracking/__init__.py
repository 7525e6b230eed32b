"""MLflow tracking: one backend class talks to MLflow; with sqlite it lives in one Ray actor, the single
writer; the driver calls it through a ``TrackingClient``, stages log through a ``Tracker`` bound to their run;
``RunGuard`` and ``reconcile`` make sure no run is left RUNNING."""

from gdwm.tracking.backend import (
    DEFAULT_SYSTEM_METRICS_INTERVAL_S,
    STAGE_TAG,
    Sink,
    TrackingActor,
    TrackingBackend,
    open_tracking,
)
from gdwm.tracking.client import TrackingClient
from gdwm.tracking.guard import RunGuard
from gdwm.tracking.owner import (
    OWNER_TAG,
    RECONCILED_TAG,
    AliveExcept,
    owner_is_alive,
    parse_owner,
    process_owner,
)
from gdwm.tracking.params import batches, flatten_params, truncate
from gdwm.tracking.tracker import Tracker

__all__ = [
    "DEFAULT_SYSTEM_METRICS_INTERVAL_S",
    "OWNER_TAG",
    "RECONCILED_TAG",
    "STAGE_TAG",
    "AliveExcept",
    "RunGuard",
    "Sink",
    "Tracker",
    "TrackingActor",
    "TrackingBackend",
    "TrackingClient",
    "batches",
    "flatten_params",
    "open_tracking",
    "owner_is_alive",
    "parse_owner",
    "process_owner",
    "truncate",
]
