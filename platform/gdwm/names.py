"""Names that become paths or path components (a sweep's name: ``<workdir>/reports/<name>``; row labels and benchmark
names, which reports and dashboards file their outputs under) are plain names: one path component, nothing a
filesystem or a shell reads otherwise. A name carried by a shared sweep or benchmark file (``sweep.name=../../x``,
``/etc``) is refused before anything runs, exit 2."""

from __future__ import annotations

import re

MAX_NAME = 200
"""Characters (a path component holds at most 255 bytes; room for a suffix)."""
_BAD = re.compile(r"[/\\\x00-\x1f\x7f]")


def check_name(value: object, what: str) -> str:
    """``value`` when it is a plain name; a ``ValueError`` naming ``what`` (the key) and the reason otherwise."""
    text = str(value)
    if not text.strip():
        why = "is empty"
    elif text in (".", "..") or text.startswith("."):
        why = "starts with '.' (a hidden or parent directory)"
    elif m := _BAD.search(text):
        why = f"holds {m[0]!r} (a path separator or control character)"
    elif text != text.strip():
        why = "starts or ends with whitespace"
    elif len(text) > MAX_NAME:
        why = f"has {len(text)} characters (at most {MAX_NAME})"
    else:
        return text
    shown = text if len(text) <= 60 else text[:57] + "..."
    raise ValueError(f"{what}={shown!r} {why}: a name that becomes a path must be one plain path component")
