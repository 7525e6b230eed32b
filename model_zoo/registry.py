"""Variants are data: ``(component, name) -> builder``, each with a ``tiny`` flavor that runs on CPU in seconds.

    @register("encoder", "daisy")
    def build_daisy(cfg: DaisyConfig) -> nn.Module: ...

    model = build("encoder", "daisy", cfg)

Adding a variant is one module that registers itself plus one YAML under ``conf/model/<component>/``: the registry
finds every module of ``model_zoo`` whose source registers a variant and imports those on the first lookup, so
importing ``model_zoo`` stays cheap and no list of modules is kept by hand.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

_BUILDERS: dict[tuple[str, str], Callable[..., Any]] = {}
_MARK = "@register("
"""What a registering module's source holds: modules without it are never imported by the lookup."""


class UnknownVariant(KeyError):
    def __str__(self) -> str:
        return str(self.args[0])


def register(component: str, name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    def wrap(builder: Callable[..., Any]) -> Callable[..., Any]:
        key = (component, name)
        if key in _BUILDERS and _BUILDERS[key] is not builder:
            raise ValueError(
                f"variant {component}/{name} is registered twice ({_BUILDERS[key].__module__}, {builder.__module__})"
            )
        _BUILDERS[key] = builder
        return builder

    return wrap


def shipped_modules() -> list[str]:
    """The modules of ``model_zoo`` that register variants (their source holds ``@register(``), sorted."""
    root = Path(__file__).parent
    out = []
    for path in sorted(root.rglob("*.py")):
        if path.name == Path(__file__).name or _MARK not in path.read_text(encoding="utf-8"):
            continue
        parts = path.relative_to(root).with_suffix("").parts
        out.append(".".join((__package__, *(parts[:-1] if parts[-1] == "__init__" else parts))))
    return out


@cache
def _load_shipped() -> None:
    for module in shipped_modules():
        importlib.import_module(module)


def variants(component: str | None = None) -> list[tuple[str, str]]:
    _load_shipped()
    return sorted(k for k in _BUILDERS if component is None or k[0] == component)


def get(component: str, name: str) -> Callable[..., Any]:
    _load_shipped()
    try:
        return _BUILDERS[(component, name)]
    except KeyError:
        known = [n for c, n in sorted(_BUILDERS) if c == component]
        raise UnknownVariant(f"no variant '{name}' of component '{component}' (registered: {known})") from None


def build(component: str, name: str, *args: Any, **kwargs: Any) -> Any:
    return get(component, name)(*args, **kwargs)
