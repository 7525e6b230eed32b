"""Who holds a port: a busy port's one line names the process listening there, so a user knows what to stop (and
another server's URL is never printed as gdwm's: ``gdwm ui`` binds before it says anything)."""

from __future__ import annotations

import contextlib


def holder(port: int) -> str:
    """`` (pid N, name)`` of the process listening on ``port``, when this user may see it; else ``""``."""
    import psutil

    with contextlib.suppress(psutil.Error, OSError):
        for c in psutil.net_connections(kind="tcp"):
            if c.status == psutil.CONN_LISTEN and c.laddr and c.laddr.port == port and c.pid:
                return f" (pid {c.pid}, {psutil.Process(c.pid).name()})"
    return ""
