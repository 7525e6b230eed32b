"""gdwm's API for pipelines: the one module of gdwm that ``pipelines`` (and any plugin) imports; the rest of gdwm
is private to it and may change without notice.

- Stages: ``stage`` (the decorator), ``StageContext`` (what a stage function receives), ``StageDef``.
- Training on Ray Train: ``TrainSession`` (what a loop gets on every worker), ``warmup_cosine_lr``.
- Commands (entry-point group ``gdwm.commands``): ``Command``, ``CommandError`` (one line, exit 1),
  ``build_data`` (a dataset-building command's ``run``), ``run_pipeline`` (a sub-pipeline up to some targets),
  ``TrackingBackend`` (MLflow, for a command's own runs), ``console`` / ``err_console`` (terminal output).
- Reporting: ``mean_of_printed`` (the average of numbers as a table prints them).
- Plugins: ``register_callables`` (the functions a config may name, e.g. a dataset's ``data.builder``; anything
  else is refused, exit 2).
- Config schemas: ``SEED``, a seed's range for ``typing.Annotated`` fields (``gdwm.knobs``: every numeric knob
  declares its range with ``annotated_types``).

Names load on first use (``EXPORTS``: name -> defining module), so a light plugin module (a command list read at
every start) does not pay for Ray Train or MLflow. A stage's code fingerprint follows each imported name to its
defining module (``gdwm.fingerprint``), so importing from here adds no other platform code to its cache key.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what checkers and IDEs see (`as` marks a re-export); EXPORTS names the same, tested
    from gdwm.callables import register_callables as register_callables
    from gdwm.cli import Command as Command
    from gdwm.cli import build_data as build_data
    from gdwm.compare.rounding import mean_of_printed as mean_of_printed
    from gdwm.errors import CommandError as CommandError
    from gdwm.knobs import SEED as SEED
    from gdwm.runner import run_pipeline as run_pipeline
    from gdwm.stage import StageContext as StageContext
    from gdwm.stage import StageDef as StageDef
    from gdwm.stage import stage as stage
    from gdwm.term import console as console
    from gdwm.term import err_console as err_console
    from gdwm.tracking import TrackingBackend as TrackingBackend
    from gdwm.training import TrainSession as TrainSession
    from gdwm.training import warmup_cosine_lr as warmup_cosine_lr

EXPORTS = {
    "stage": "gdwm.stage",
    "StageContext": "gdwm.stage",
    "StageDef": "gdwm.stage",
    "TrainSession": "gdwm.training",
    "warmup_cosine_lr": "gdwm.training",
    "Command": "gdwm.cli",
    "build_data": "gdwm.cli",
    "CommandError": "gdwm.errors",
    "run_pipeline": "gdwm.runner",
    "TrackingBackend": "gdwm.tracking",
    "console": "gdwm.term",
    "err_console": "gdwm.term",
    "mean_of_printed": "gdwm.compare.rounding",
    "SEED": "gdwm.knobs",
    "register_callables": "gdwm.callables",
}
"""Name -> the module that defines it (a literal: the fingerprint reads it without importing this module)."""

__all__ = sorted(EXPORTS)


def __getattr__(name: str) -> Any:
    module = EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'gdwm.api' has no attribute {name!r} (the API: {', '.join(__all__)})")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *EXPORTS})
