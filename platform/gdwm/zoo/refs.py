"""Zoo references in config values and the arguments of ``gdwm zoo`` (no MLflow import: the CLI loads this at start).

A reference names one registered version: ``zoo:gdwm-lora/3``, or an alias that ``gdwm run`` pins to the version it
points at before planning (``zoo:gdwm-lora@champion`` -> ``zoo:gdwm-lora/3``), so cache keys hold exact versions.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

PREFIX = "zoo:"
NAME_PREFIX = "gdwm-"
CANDIDATE, CHAMPION = "candidate", "champion"
_REF = re.compile(r"zoo:(?P<name>[A-Za-z0-9_.-]+)(?:@(?P<alias>[A-Za-z0-9_-]+)|/(?P<version>[0-9]+))")


class ZooError(ValueError):
    """A zoo name, version, alias or reference that does not exist or does not parse; the message names it."""


@dataclass(frozen=True)
class Ref:
    """``zoo:NAME/VERSION`` (pinned) or ``zoo:NAME@ALIAS``."""

    name: str
    version: int | None = None
    alias: str | None = None

    def __str__(self) -> str:
        pin = f"/{self.version}" if self.version is not None else f"@{self.alias}"
        return f"{PREFIX}{self.name}{pin}"


def is_ref(value: object) -> bool:
    return isinstance(value, str) and value.startswith(PREFIX)


def parse_ref(text: str) -> Ref:
    m = _REF.fullmatch(text)
    if m is None:
        raise ZooError(f"'{text}': not a zoo reference (zoo:NAME@ALIAS or zoo:NAME/VERSION)")
    version = m["version"]
    return Ref(m["name"], int(version) if version is not None else None, m["alias"])


@dataclass
class ZooArgs:
    """``gdwm zoo list|show|promote|load args.name=NAME [args.version=N|@ALIAS] [args.alias=ALIAS] [args.out=DIR]``."""

    name: str | None = None
    """Registered model, e.g. ``gdwm-lora`` (list: only this one; the others need it)."""
    version: str | None = None
    """A version number, or ``@ALIAS``; show/load: null = by ``alias``, else the latest version."""
    alias: str | None = None
    """promote: the alias to set (null = champion); show/load: select the version this alias points at."""
    out: str | None = None
    """load: directory to write the files to (null = <workdir>/zoo/<name>/<version>)."""
