"""Every numeric knob carries its range in its schema, checked when a config is composed (exit 2 naming the key);
a string may carry its length limits the same way (``Annotated[str, Len(1, 256)]``).

A field declares its range with ``typing.Annotated`` and ``annotated_types`` (what pydantic reads too; a dependency-free
library that ``model_zoo`` may import, as it imports no platform code)::

    steps: Annotated[int, Ge(1)] = 100
    lr: Annotated[float, Gt(0)] = 1e-3
    seeds: Annotated[list[int] | None, Interval(ge=0, le=MAX_SEED)] = None   # every element

OmegaConf reads ``Annotated`` as its inner type, so the YAML is validated as before; ``check_ranges`` then walks the
composed config and checks every value (every element of a list, every value of a dict) of every annotated field.
``unranged`` names the numeric fields of a schema that declare no range (a test holds that there are none).
"""

from __future__ import annotations

import dataclasses
import math
import typing
from functools import cache
from typing import Any

from annotated_types import Ge, Gt, Interval, Le, Len, Lt, MaxLen, MinLen

__all__ = [
    "MAX_SEED",
    "SEED",
    "Ge",
    "Gt",
    "Interval",
    "Le",
    "Len",
    "Lt",
    "bounds",
    "check_ranges",
    "describe",
    "unranged",
]

MAX_SEED = 2**32 - 1
"""Seeds take numpy's legacy range (``RandomState``), which every generator a stage seeds (torch, numpy) accepts."""

SEED = Interval(ge=0, le=MAX_SEED)
"""A seed's range, for ``seed: Annotated[int, SEED] = 0`` (``gdwm.api.SEED``)."""

_BOUNDS = (Ge, Gt, Le, Lt, MinLen, MaxLen)


def bounds(hint: Any) -> tuple[Any, ...]:
    """The ``Ge``/``Gt``/``Le``/``Lt`` (numbers) and ``MinLen``/``MaxLen`` (strings) constraints of an ``Annotated``
    type hint (an ``Interval`` or a ``Len`` split into them)."""
    out: list[Any] = []
    for m in getattr(hint, "__metadata__", ()):
        for b in m if isinstance(m, Interval | Len) else [m]:
            if isinstance(b, _BOUNDS):
                out.append(b)
    return tuple(out)


def describe(constraints: tuple[Any, ...]) -> str:
    """``>= 1``, ``> 0 and <= 1``, ``at most 256 characters``."""
    words = {Ge: ">= {}", Gt: "> {}", Le: "<= {}", Lt: "< {}", MinLen: "at least {} character(s)",
             MaxLen: "at most {} characters"}  # fmt: skip
    lengths = {type(b): b for b in constraints if isinstance(b, MinLen | MaxLen)}
    if len(lengths) == 2:
        return f"{lengths[MinLen].min_length} to {lengths[MaxLen].max_length} characters"
    return " and ".join(words[type(b)].format(_limit(b)) for b in constraints)


def _limit(b: Any) -> Any:
    return getattr(b, {Ge: "ge", Gt: "gt", Le: "le", Lt: "lt", MinLen: "min_length", MaxLen: "max_length"}[type(b)])


def _ok(value: Any, constraints: tuple[Any, ...]) -> bool:
    """Whether ``value`` meets every constraint that applies to its kind (lengths to strings, bounds to numbers)."""
    if isinstance(value, str):
        return all(
            len(value) >= b.min_length if isinstance(b, MinLen) else len(value) <= b.max_length
            for b in constraints
            if isinstance(b, MinLen | MaxLen)
        )
    if isinstance(value, bool) or not isinstance(value, int | float):
        return True
    numeric = [b for b in constraints if isinstance(b, Ge | Gt | Le | Lt)]
    for b in numeric:
        limit = _limit(b)
        if not (value >= limit if isinstance(b, Ge) else value > limit if isinstance(b, Gt) else
                value <= limit if isinstance(b, Le) else value < limit):  # fmt: skip
            return False
    return math.isfinite(value) or not numeric  # NaN fails every comparison above; inf only an upper bound


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _numbers(value: Any) -> list[tuple[str, Any]]:
    """``(suffix, number)`` of a scalar, of each element of a list and each value of a dict."""
    from omegaconf import DictConfig, ListConfig

    if isinstance(value, ListConfig | list | tuple):
        return [(f"[{i}]", v) for i, v in enumerate(value)]
    if isinstance(value, DictConfig | dict):
        return [(f".{k}", v) for k, v in value.items()]
    return [("", value)]


def check_ranges(cfg: Any, prefix: str = "") -> str | None:
    """The first value of the composed ``cfg`` outside its field's range, as ``invalid value for 'KEY': V (must be
    >= 1)``; None when every value is in range."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(cfg, ListConfig):
        for i, item in enumerate(cfg):
            if isinstance(item, DictConfig | ListConfig) and (bad := check_ranges(item, f"{prefix}[{i}].")):
                return bad
        return None
    if not isinstance(cfg, DictConfig):
        return None
    cls = OmegaConf.get_type(cfg)
    hints = _hints(cls) if isinstance(cls, type) and dataclasses.is_dataclass(cls) else {}
    for key in cfg:
        full = f"{prefix}{key}"
        value = cfg[key]
        constraints = bounds(hints.get(key))
        if constraints:
            for suffix, v in _numbers(value):
                if not _ok(v, constraints):
                    shown = (
                        repr(v) if not isinstance(v, str) or len(v) <= 40 else f"'{v[:20]}...' ({len(v)} characters)"
                    )
                    return f"invalid value for '{full}{suffix}': {shown} (must be {describe(constraints)})"
        if isinstance(value, DictConfig | ListConfig) and (bad := check_ranges(value, f"{full}.")):
            return bad
    return None


def _numeric(hint: Any) -> bool:
    def parts(h: Any) -> list[Any]:
        return [h, *(p for a in typing.get_args(h) for p in parts(a))]

    found = parts(hint)
    return bool({int, float} & set(found)) and bool not in found


def unranged(cls: type) -> list[str]:
    """The numeric fields of dataclass ``cls`` (scalars, lists and dicts of numbers) declaring no range."""
    hints = _hints(cls)
    return [f.name for f in dataclasses.fields(cls) if _numeric(hints[f.name]) and not bounds(hints[f.name])]
