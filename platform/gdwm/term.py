"""The consoles gdwm prints with: wide enough when piped (CI logs, tests) that tables do not wrap."""

from __future__ import annotations

import sys

from rich.console import Console


def _width(stream) -> int | None:
    return None if stream.isatty() else 160


console = Console(highlight=False, width=_width(sys.stdout))
err_console = Console(stderr=True, highlight=False, soft_wrap=True)
