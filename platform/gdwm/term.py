"""The consoles gdwm prints with: wide enough when piped (CI logs, tests) that tables do not wrap, and a line of text
piped is one line however long (a log is read with grep); text printed through them has its credentials masked
(:func:`gdwm.redact.redact`), whatever message carries a URI."""

from __future__ import annotations

import sys

from rich.console import Console

from gdwm.redact import redact


def _width(stream) -> int | None:
    return None if stream.isatty() else 160


class RedactingConsole(Console):
    """A ``Console`` whose ``print`` masks credentials in its string arguments (tables and other renderables
    are printed as given: build them from redacted text). Strings printed to a pipe or file are not wrapped at
    the console's width: only a terminal wraps a long line, and only on screen."""

    def print(self, *objects, **kwargs) -> None:
        if "soft_wrap" not in kwargs and not self.is_terminal and all(isinstance(o, str) for o in objects):
            kwargs["soft_wrap"] = True
        super().print(*(redact(o) if isinstance(o, str) else o for o in objects), **kwargs)


QUIET, NORMAL, VERBOSE = 0, 1, 2
"""Verbosity of a launch's progress output (``--quiet``: failures only; ``--verbose``: starts and scenes too)."""


def verbosity(argv: list[str]) -> int:
    """``--quiet`` / ``--verbose`` of a launch command."""
    return QUIET if "--quiet" in argv else VERBOSE if "--verbose" in argv else NORMAL


console = RedactingConsole(highlight=False, width=_width(sys.stdout))
err_console = RedactingConsole(stderr=True, highlight=False, soft_wrap=True)
