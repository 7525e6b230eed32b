"""Variants are data: ``(component, name) -> builder``, each with a ``tiny`` flavor that runs on CPU in seconds.

    @register("encoder", "daisy")
    def build_daisy(cfg: DaisyConfig) -> nn.Module: ...

    model = build("encoder", "daisy", cfg)

Adding a variant is one module that registers itself plus one YAML under ``conf/model/<component>/``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

_BUILDERS: dict[tuple[str, str], Callable[..., Any]] = {}
# Modules that register the shipped variants; imported on first lookup so importing model_zoo stays cheap.
_SHIPPED: tuple[str, ...] = (
    "model_zoo.encoders.daisy",
    "model_zoo.encoders.qwen3_vl_vision",
    "model_zoo.feature_ae",
    "model_zoo.llm.qwen3_vl",
    "model_zoo.adapter",
    "model_zoo.alignment",
    "model_zoo.selectors",
    "model_zoo.diffusion.rgbd_dual",
)


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


def _load_shipped() -> None:
    for module in _SHIPPED:
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
