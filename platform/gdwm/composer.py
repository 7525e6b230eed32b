"""The configs of many trials of one launch, composed at the cost of a few: a sweep's trials differ from its base in a
row's overrides, a grid point and a seed, and most of those are plain values (``stage.lora.rank=8``, ``seed=2``).

Hydra composes a config from scratch on every call (its defaults tree, every YAML file, the merge): a large part of
a trial's orchestration cost. ``Composer`` composes once per distinct set of config-group choices
(``model/selector=voxel_topk``, ``experiment=...``) and applies each trial's plain value overrides to a copy with
Hydra's own override parser and applier, which is what Hydra's composition does with them after the merge: the
same config and the same errors as ``load_config(base + extra)``. Anything it does not recognise as a plain value
override (a group choice, a ``hydra.`` key, a package override) goes into the composed part.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from functools import cache

from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig

from gdwm.config import compose_raw, group_options, load_config, validated


@cache
def _is_group(key: str) -> bool:
    return "/" in key or bool(group_options(key))


def split_overrides(overrides: Sequence[str]) -> tuple[list[str], list] | None:
    """(config-group choices, parsed plain value overrides) of ``overrides``, in their order; None when one does not
    parse (the full composition reports it)."""
    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except HydraException:
        return None
    groups, values = [], []
    for text, o in zip(overrides, parsed, strict=True):
        if o.is_hydra_override() or o.is_sweep_override() or o.package is not None or _is_group(o.key_or_group):
            groups.append(text)
        else:
            values.append(o)
    return groups, values


class Composer:
    """``load(extra)`` is ``load_config([*base, *extra])``, composing with Hydra once per distinct set of group
    choices in ``extra``."""

    def __init__(self, base: Sequence[str], config_name: str = "config"):
        self.base = list(base)
        self.config_name = config_name
        self._composed: dict[tuple[str, ...], DictConfig] = {}
        self.compositions = 0
        """How many times Hydra composed (what the cache saved is the number of loads minus this)."""

    def _raw(self, groups: tuple[str, ...]) -> DictConfig:
        if groups not in self._composed:
            self._composed[groups] = compose_raw([*self.base, *groups], self.config_name)
            self.compositions += 1
        return self._composed[groups]

    def load(self, extra: Sequence[str]) -> DictConfig:
        overrides = [*self.base, *extra]
        split = split_overrides(extra)
        if split is None:
            return load_config(overrides, self.config_name)
        groups, values = split

        def make() -> DictConfig:
            cfg = copy.deepcopy(self._raw(tuple(groups)))
            ConfigLoaderImpl._apply_overrides_to_config(values, cfg)  # what Hydra's compose does with them
            return cfg

        return validated(make, overrides)
