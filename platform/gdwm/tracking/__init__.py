"""MLflow tracking: one backend class talks to MLflow; with sqlite it lives in one Ray actor, the single
writer; the driver calls it through a ``TrackingClient``, stages log through a ``Tracker`` bound to their run;
``RunGuard`` and ``reconcile`` make sure no run is left RUNNING.

Names load on first use (PEP 562): a reader that needs only ``gdwm.tracking.owner`` (``gdwm ui``) imports neither Ray
nor MLflow through this package."""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "backend": (
        "DEFAULT_SYSTEM_METRICS_INTERVAL_S",
        "STAGE_TAG",
        "Sink",
        "TrackingActor",
        "TrackingBackend",
        "open_tracking",
    ),
    "client": ("TrackingClient",),
    "guard": ("RunGuard",),
    "owner": ("OWNER_TAG", "RECONCILED_TAG", "AliveExcept", "owner_is_alive", "parse_owner", "process_owner"),
    "params": ("batches", "flatten_params", "truncate"),
    "tracker": ("Tracker",),
    "writes": ("NewRun", "RunWrite", "WriteQueue"),
}
_MODULE = {name: module for module, names in _WHERE.items() for name in names}

__all__ = sorted(_MODULE)


def __getattr__(name: str) -> Any:
    module = _MODULE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
