"""The consoles gdwm prints with: wide enough when piped (CI logs, tests) that tables do not wrap; text printed
through them has its credentials masked (:func:`gdwm.redact.redact`), whatever message carries a URI."""

from __future__ import annotations

import sys

from rich.console import Console

from gdwm.redact import redact


def _width(stream) -> int | None:
    return None if stream.isatty() else 160


class RedactingConsole(Console):
    """A ``Console`` whose ``print`` masks credentials in its string arguments (tables and other renderables
    are printed as given: build them from redacted text)."""

    def print(self, *objects, **kwargs) -> None:
        super().print(*(redact(o) if isinstance(o, str) else o for o in objects), **kwargs)


QUIET, NORMAL, VERBOSE = 0, 1, 2
"""Verbosity of a launch's progress output (``--quiet``: failures only; ``--verbose``: starts and scenes too)."""


def verbosity(argv: list[str]) -> int:
    """``--quiet`` / ``--verbose`` of a launch command."""
    return QUIET if "--quiet" in argv else VERBOSE if "--verbose" in argv else NORMAL


console = RedactingConsole(highlight=False, width=_width(sys.stdout))
err_console = RedactingConsole(stderr=True, highlight=False, soft_wrap=True)
