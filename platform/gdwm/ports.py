"""Before serving on a port, make sure it is free: another server already listening there must never have its URL
printed as gdwm's (``gdwm ui``, and any page gdwm serves)."""

from __future__ import annotations

import contextlib
import errno
import socket

from gdwm.errors import CommandError


def check_port_free(host: str, port: int, key: str = "ui.port") -> None:
    """A ``CommandError`` (exit 1) naming ``key``, the address and, where this host can tell, the process holding it,
    unless a server could listen on ``host:port`` now."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do: a socket in TIME_WAIT is no holder
        try:
            s.bind((host, port))
            return
        except OSError as e:
            if e.errno != errno.EADDRINUSE:
                raise CommandError(f"{key}={port}: cannot listen on {host}:{port} ({e.strerror})") from None
    raise CommandError(f"{key}={port}: {host}:{port} is already in use by another process{_holder(port)}; stop it or "
                       f"choose another {key}")  # fmt: skip


def _holder(port: int) -> str:
    """`` (pid N, name)`` of the process listening on ``port``, when this user may see it; else ``""``."""
    import psutil

    with contextlib.suppress(psutil.Error, OSError):
        for c in psutil.net_connections(kind="tcp"):
            if c.status == psutil.CONN_LISTEN and c.laddr and c.laddr.port == port and c.pid:
                return f" (pid {c.pid}, {psutil.Process(c.pid).name()})"
    return ""
