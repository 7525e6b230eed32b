"""Who owns a RUNNING run: ``<hostname>:<pid>:<process start time>`` of the driver that created it."""

from __future__ import annotations

import os
import socket

import psutil

OWNER_TAG = "gdwm.owner"
RECONCILED_TAG = "gdwm.reconciled"
# psutil derives start times from the boot time, which the kernel may report a second apart between reads.
_START_TOLERANCE_S = 1.0


def process_owner(pid: int | None = None) -> str:
    """Owner string of a process on this host (default: the current one), e.g. ``node-1:4242:1718000000.12``."""
    pid = os.getpid() if pid is None else pid
    return f"{socket.gethostname()}:{pid}:{psutil.Process(pid).create_time():.2f}"


def parse_owner(owner: str) -> tuple[str, int, float] | None:
    """``(host, pid, start_time)``, or None for a malformed owner string."""
    host, sep, rest = owner.partition(":")
    pid, sep2, start = rest.partition(":")
    try:
        return (host, int(pid), float(start)) if sep and sep2 and host else None
    except ValueError:
        return None


def owner_is_alive(owner: str) -> bool:
    """True for a live process on this host with the same start time, and for any owner on another host
    (this host cannot tell, so it leaves those runs alone); False for a malformed owner."""
    parsed = parse_owner(owner)
    if parsed is None:
        return False
    host, pid, start = parsed
    if host != socket.gethostname():
        return True
    try:
        proc = psutil.Process(pid)
        return proc.status() != psutil.STATUS_ZOMBIE and abs(proc.create_time() - start) <= _START_TOLERANCE_S
    except (psutil.NoSuchProcess, psutil.ZombieProcess):
        return False


class AliveExcept:
    """``is_alive`` for ``reconcile`` that treats ``owner`` as gone: an interrupted driver ends its own runs."""

    def __init__(self, owner: str):
        self.owner = owner

    def __call__(self, owner: str) -> bool:
        return owner != self.owner and owner_is_alive(owner)
