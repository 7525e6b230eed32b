"""Values a config takes from the environment (``${oc.env:HF_TOKEN}``) are treated as secrets: gdwm records the
interpolation, never the value.

``load_config`` finds every key whose value comes from ``oc.env`` (directly, inside a string, or through other keys
that do) and keeps it in ``from_env`` as the text it was written as, interpolations shown as ``<env:NAME>``
(``Bearer ${oc.env:HF_TOKEN}`` -> ``Bearer <env:HF_TOKEN>``; never ``${...}``, which a later resolution would read
again). What gdwm writes takes that text instead of the value: a stage's config subset (so its cache key, manifest,
run params and the plan's "why stages re-run" hold no secret, and the key stays the same when the secret rotates),
the launch, row and trial runs' params. The stage itself reads the real value (``RunEnv.env_values``).

A consequence worth knowing: a hyper-parameter set from the environment does not enter the cache key. Set those with
overrides (``stage.lora.rank=16``), which the key sees.
"""

from __future__ import annotations

import contextlib
import copy
import re
from collections.abc import Mapping
from typing import Any

__all__ = ["env_keys", "env_values", "masked", "recorded", "restore", "unshown"]

_INNER = re.compile(r"\$\{([^${}]*)\}")
_SHOWN_ENV = re.compile(r"<env:([A-Za-z_][A-Za-z0-9_]*)>")
_STEP = re.compile(r"\[(\d+)\]|\.?([^.\[\]]+)")


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def _leaves(raw: Any, path: str = "") -> dict[str, str]:
    """``{path: text}`` of every string holding an interpolation in an unresolved container (``a.b[0].c`` paths)."""
    if isinstance(raw, Mapping):
        return {
            k: v for key, value in raw.items() for k, v in _leaves(value, f"{path}.{key}" if path else str(key)).items()
        }
    if isinstance(raw, list | tuple):
        return {k: v for i, value in enumerate(raw) for k, v in _leaves(value, f"{path}[{i}]").items()}
    return {path: raw} if isinstance(raw, str) and "${" in raw else {}


def _shown(text: str) -> str:
    """The text with each interpolation, innermost first, as ``<env:NAME>`` (``oc.env``) or ``<what it names>``."""
    while (m := _INNER.search(text)) is not None:
        inner = m[1].strip()
        shown = f"<env:{inner[7:].split(',')[0].strip()}>" if inner.startswith("oc.env:") else f"<{inner}>"
        text = text[: m.start()] + shown + text[m.end() :]
    return text


def _refs(path: str, text: str) -> list[str]:
    """Absolute paths of the config keys ``text`` interpolates (``${a.b}``, ``${.sibling}``, ``${..uncle}``)."""
    out, parent = [], path.rsplit(".", 1)[0] if "." in path else ""
    probe = text
    while (m := _INNER.search(probe)) is not None:
        inner = m[1].strip()
        if ":" not in inner:  # a resolver call (oc.env:, abspath:) names no key itself; its arguments were seen
            if inner.startswith("."):
                dots = len(inner) - len(inner.lstrip("."))
                base = parent.split(".") if parent else []
                base = base[: len(base) - (dots - 1)] if dots > 1 else base
                out.append(".".join([*base, inner[dots:]]).strip("."))
            else:
                out.append(inner)
        probe = probe[: m.start()] + "_" + probe[m.end() :]
    return out


def _related(a: str, b: str) -> bool:
    return a == b or a.startswith((b + ".", b + "[")) or b.startswith((a + ".", a + "["))


def env_keys(raw: Mapping) -> dict[str, str]:
    """``{path: text shown instead}`` of every key of the unresolved config ``raw`` (``OmegaConf.to_container(cfg,
    resolve=False)``) whose value comes from the environment, directly or through the keys it interpolates."""
    leaves = _leaves(raw)
    found = {p for p, text in leaves.items() if "oc.env:" in text}
    grew = True
    while grew:  # a key interpolating one that comes from the environment (or a subtree holding one) does too
        new = {p for p, text in leaves.items() if p not in found and any(_related(r, f) for r in _refs(p, text)
                                                                           for f in found)}  # fmt: skip
        found |= new
        grew = bool(new)
    return {p: _shown(leaves[p]) for p in sorted(found)}


def _steps(path: str) -> list[str | int]:
    return [int(m[1]) if m[1] is not None else m[2] for m in _STEP.finditer(path)]


def _set(container: Any, steps: list[str | int], value: Any) -> None:
    for s in steps[:-1]:
        container = container[s]
    container[steps[-1]] = value


def masked(subset: Mapping[str, Any], from_env: Mapping[str, str]) -> dict[str, Any]:
    """A stage's config subset (declared dotted key -> plain subtree) with every value from the environment replaced
    by its shown text; the subset itself is left as it was."""
    out = copy.deepcopy(dict(subset))
    for path, shown in from_env.items():
        for key in out:
            if path == key:
                out[key] = shown
            elif path.startswith((key + ".", key + "[")):
                with contextlib.suppress(KeyError, IndexError, TypeError):  # not in this subset's resolved shape
                    _set(out[key], _steps(path[len(key) :]), shown)
    return out


def restore(subset: Mapping[str, Any], values: Mapping[str, Any]) -> dict[str, Any]:
    """The inverse of ``masked`` for the stage's own use: ``values`` (``env_values``) put back."""
    return masked(subset, values)


def env_values(cfg: Any) -> dict[str, Any]:
    """``{path: resolved value}`` of every key of the composed ``cfg`` that came from the environment."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    out = {}
    for path in cfg.get("from_env") or {}:
        value = OmegaConf.select(cfg, path)
        out[path] = OmegaConf.to_container(value, resolve=True) if isinstance(value, DictConfig | ListConfig) else value
    return out


def recorded(cfg: Any) -> dict[str, Any]:
    """The composed config as gdwm records it (runs' params): plain containers, values from the environment shown as
    their interpolation."""
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg, resolve=True)
    for path, shown in (cfg.get("from_env") or {}).items():
        with contextlib.suppress(KeyError, IndexError, TypeError):
            _set(plain, _steps(path), shown)
    return plain


def unshown(value: Any) -> Any:
    """A recorded config (``recorded``) made live again: every ``<env:NAME>`` back to ``${oc.env:NAME}``, so a run
    composed from the record (``gdwm reproduce``) reads the environment it runs in, as the recorded run did."""
    if isinstance(value, Mapping):
        return {k: unshown(v) for k, v in value.items()}
    if isinstance(value, list):
        return [unshown(v) for v in value]
    if isinstance(value, str):
        return _SHOWN_ENV.sub(lambda m: "${oc.env:" + m[1] + "}", value)
    return value
