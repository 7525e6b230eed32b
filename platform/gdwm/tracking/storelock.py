"""The sqlite store's one-writer lock (``<db>.lock``, ``filelock``), waited for visibly and for a bounded time.

A driver that hangs, or was stopped (SIGSTOP, a suspended terminal) while holding the lock, must not make every other
command wait forever in silence: after ``NOTICE_S`` the waiter says whom it waits for (the holder's pid, from
``/proc/locks`` where the kernel shows it), and after ``timeout_s`` it gives up with one line naming the lock and the
holder (``StoreLockTimeout``, a ``TrackingError`` to the caller; exit 1).
"""

from __future__ import annotations

import os
from pathlib import Path
from types import TracebackType

from filelock import FileLock, Timeout

NOTICE_S = 2.0
"""Waiting longer than this is said once on stderr."""
DEFAULT_TIMEOUT_S = 120.0
"""``tracking.lock_timeout_s``'s default: longer than any one MLflow call gdwm makes holds the lock."""


def lock_holder(path: str | os.PathLike) -> str:
    """``pid N (name)`` of the process holding a ``flock`` on ``path``, read from ``/proc/locks`` (Linux; a holder on
    another host of a shared volume is invisible here); ``another process`` when unknown."""
    try:
        inode = os.stat(path).st_ino
        with open("/proc/locks") as f:
            for line in f:  # "1: FLOCK  ADVISORY  WRITE 4242 fd:00:1234 0 EOF"
                parts = line.split()
                if len(parts) > 5 and parts[1] == "FLOCK" and parts[5].rsplit(":", 1)[-1] == str(inode):
                    pid = int(parts[4])
                    try:
                        import psutil

                        return f"pid {pid} ({psutil.Process(pid).name()})"
                    except Exception:  # gone meanwhile, or not ours to inspect
                        return f"pid {pid}"
    except (OSError, ValueError):
        pass
    return "another process"


class StoreLockTimeout(TimeoutError):
    """The lock stayed held past the timeout; the message names the lock and its holder (the backend raises it as a
    ``TrackingError``)."""


class StoreLock:
    """Re-entrant (a locked method may call another); ``with lock:`` waits up to ``timeout_s``."""

    def __init__(self, db: str, timeout_s: float = DEFAULT_TIMEOUT_S):
        self.db = db
        self.path = f"{db}.lock"
        self.timeout_s = float(timeout_s)
        self._lock = FileLock(self.path)

    def __enter__(self) -> StoreLock:
        if self._lock.is_locked:  # ours already: re-enter
            self._lock.acquire()
            return self
        try:
            self._lock.acquire(timeout=min(NOTICE_S, self.timeout_s))
            return self
        except Timeout:
            pass
        from gdwm.term import err_console

        err_console.print(f"gdwm: waiting for the tracking store's lock {self.path}, held by {lock_holder(self.path)} "
                          f"(up to {self.timeout_s:g} s)", markup=False)  # fmt: skip
        try:
            self._lock.acquire(timeout=max(0.0, self.timeout_s - NOTICE_S))
        except Timeout:
            raise StoreLockTimeout(
                f"tracking store {self.db}: its lock {Path(self.path).name} is still held by {lock_holder(self.path)} "
                f"after {self.timeout_s:g} s; stop that process if it hangs, or raise tracking.lock_timeout_s"
            ) from None
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None):
        self._lock.release()
