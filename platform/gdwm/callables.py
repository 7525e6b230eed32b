"""Callables named in config resolve only to what gdwm or a plugin registered.

A dataset's ``data.builder``, ``data.planner``, ``data.summarizer`` and ``data.checker`` are dotted paths that gdwm
calls; a sweep row, a benchmark suite or a command line can carry them, so ``data.summarizer=shutil.rmtree`` must not
be called with the dataset's root. A plugin registers the functions it provides (``gdwm.api.register_callables``,
from its ``gdwm.plugins`` entry point, which runs whenever a config is composed); anything else is a ``ConfigError``
naming the key and what is registered (exit 2), raised before any of them runs. Stages
(``pipeline.stages.*._target_``) are checked the same way by what they are: a ``StageDef`` (``gdwm.dag``).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["DATA_FUNCTIONS", "register_callables", "resolve_callable"]

DATA_FUNCTIONS = ("data.builder", "data.planner", "data.summarizer", "data.checker")
"""The config keys naming a dataset's functions."""

_REGISTERED: dict[str, set[str]] = defaultdict(set)


def register_callables(key: str, *targets: str | None) -> None:
    """Allow ``targets`` (dotted paths, ``module.function``) as values of config key ``key`` (e.g. ``data.builder``);
    None is skipped (a dataset without a planner)."""
    _REGISTERED[key].update(t for t in targets if t)


def check_callables(cfg: Any, keys: Iterable[str] = DATA_FUNCTIONS) -> None:
    """``ConfigError`` for the first of ``keys`` whose value (when set) is not registered: checked all at once,
    before any of them is called."""
    from omegaconf import OmegaConf

    for key in keys:
        target = OmegaConf.select(cfg, key)
        if target is not None and str(target) not in _REGISTERED[key]:
            from gdwm.config import ConfigError, _register_all

            _register_all()  # the plugins register theirs when configs are composed
            if str(target) in _REGISTERED[key]:
                continue
            known = ", ".join(sorted(_REGISTERED[key])) or "none"
            raise ConfigError(
                f"{key}={target}: not a registered function (registered: {known}); a plugin registers its own with "
                "gdwm.api.register_callables"
            )


def resolve_callable(cfg: Any, key: str) -> Callable:
    """The function config key ``key`` names, once ``check_callables`` accepts it."""
    from hydra.utils import get_method
    from omegaconf import OmegaConf

    check_callables(cfg, [key])
    return get_method(str(OmegaConf.select(cfg, key)))
