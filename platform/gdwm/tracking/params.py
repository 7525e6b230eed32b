"""Flattening configs into MLflow params and splitting writes to MLflow's batch limits."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from gdwm.redact import redact

# MLflow's limits (mlflow.utils.validation), held here so that a Ray worker flattening a stage's params needn't import
# MLflow (1-2 s per process); tests/gdwm/test_seed.py checks they are MLflow's.
MAX_METRICS_PER_BATCH = 1000
MAX_PARAMS_TAGS_PER_BATCH = 100
MAX_PARAM_VAL_LENGTH = 6000
MAX_TAG_VAL_LENGTH = 8000

__all__ = [
    "MAX_METRICS_PER_BATCH",
    "MAX_PARAMS_TAGS_PER_BATCH",
    "MAX_PARAM_VAL_LENGTH",
    "MAX_TAG_VAL_LENGTH",
    "batches",
    "flatten_params",
    "full_params",
    "own_params",
    "relative_paths",
    "truncate",
]


def truncate(value: str, limit: int) -> str:
    """``value`` cut to ``limit`` chars, ending in a marker that gives the original length."""
    if len(value) <= limit:
        return value
    marker = f"...[truncated, {len(value)} chars]"
    return value[: limit - len(marker)] + marker


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, DictConfig | ListConfig) else value


_NAME = re.compile(r"[\w\-. :/]+")
"""What MLflow accepts in a param name (alphanumerics, underscores, dashes, periods, spaces, colons, slashes)."""


def flatten_params(cfg: Mapping | DictConfig, prefix: str = "") -> dict[str, str]:
    """``{"a": {"b": 1}, "l": [1, 2]}`` -> ``{"a.b": "1", "l": "[1, 2]"}``; a mapping with a key MLflow does not accept
    in a name (``{"Task_A&B": ...}``) is one param, its JSON. Values cut to MLflow's param limit, credentials
    in them masked (:func:`gdwm.redact.redact`: params are readable by every user of the store)."""
    out: dict[str, str] = {}
    for key, value in _plain(cfg).items():
        full = f"{prefix}{key}"
        value = _plain(value)
        if isinstance(value, Mapping) and value and all(_NAME.fullmatch(str(k)) for k in value):
            out.update(flatten_params(value, f"{full}."))
            continue
        if isinstance(value, Mapping | list | tuple):
            text = json.dumps(value, default=str)
        else:
            text = str(value)
        out[full] = truncate(redact(text), MAX_PARAM_VAL_LENGTH)
    return out


def relative_paths(params: Mapping[str, str], root: str | Path) -> dict[str, str]:
    """Flattened params with every absolute path (plain, ``file://`` or ``sqlite:///``) written relative to ``root``
    (the workdir): a run's params describe the experiment, not the machine or folder it ran in, and stay true for a
    copied workdir. A URI with a query or fragment (``file:///c?token=...``) is left whole: its path is not a file's
    alone, and no relative form of it is a URI."""
    root = os.path.abspath(root)
    out = {}
    for k, v in params.items():
        for scheme in ("sqlite:///", "file://", ""):
            path = v.removeprefix(scheme) if v.startswith(scheme) else None
            if scheme and path is not None and ("?" in path or "#" in path):
                break
            if path is not None and path.startswith("/") and "\n" not in path and " " not in path:
                v = scheme + os.path.relpath(path, root)
                break
        out[k] = v
    return out


PARAMS_BASE_TAG = "gdwm.params_base"
"""On a sweep's row run that records only what differs from its sweep's run: that run's id (:func:`full_params`)."""


def own_params(params: Mapping[str, str], inherited: Mapping[str, str], keep: Iterable[str] = ()) -> dict[str, str]:
    """What a run records of its config ``params`` under a run that holds ``inherited`` (a trial under its row's, a
    row under its sweep's): the values that differ (a seed and what it sets; a row's factors' keys) and the keys
    ``keep`` (its factors, which MLflow's views filter and plot by); :func:`full_params` puts the config back
    together. A 200-row sweep's trial runs repeated
    every row's ~270 params: three more requests a trial to a team's server, and every search returning them twice."""
    keep = set(keep)
    return {k: v for k, v in params.items() if k in keep or inherited.get(k) != v}


def full_params(own: Mapping[str, str], *inherited: Mapping[str, str]) -> dict[str, str]:
    """A run's config as params: what it inherits overlaid with its own (:func:`own_params`), nearest last: a trial's
    ``full_params(trial, row, sweep)``, where the row inherits from its sweep's run only if tagged
    ``PARAMS_BASE_TAG``. A run that recorded its whole config (gdwm before 2026-12-06) comes back as it is."""
    out: dict[str, str] = {}
    for level in reversed(inherited):
        out |= level
    return out | dict(own)


def inherited_params(tags: Mapping[str, str], runs: Mapping[str, Mapping]) -> Mapping[str, str]:
    """The params a run with ``tags`` inherits: those of the run its ``PARAMS_BASE_TAG`` names, looked up in
    ``runs`` (run id -> a run dict with ``params``); none when it names none, or one not in ``runs``."""
    base = runs.get(tags.get(PARAMS_BASE_TAG, ""))
    return base["params"] if base is not None else {}


def batches(items: Sequence, size: int) -> Iterator[list]:
    """Consecutive slices of at most ``size`` items (the last may be shorter; none when empty)."""
    if size < 1:
        raise ValueError(f"batch size must be >= 1, got {size}")
    items = list(items)
    for start in range(0, len(items), size):
        yield items[start : start + size]
