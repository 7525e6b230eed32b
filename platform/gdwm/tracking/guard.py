"""No run left RUNNING: the driver wraps each run it owns in a ``RunGuard``."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import traceback
from types import FrameType, TracebackType

from gdwm.errors import one_line
from gdwm.tracking.backend import Sink, TrackingError
from gdwm.tracking.client import TrackingClient
from gdwm.tracking.tracker import Tracker

log = logging.getLogger(__name__)

_SIGNALS = (signal.SIGTERM, signal.SIGINT)
_open: list[RunGuard] = []  # guards of this process, innermost last
_previous: dict[int, object] = {}  # handlers to restore when the outermost guard exits


def _on_signal(signum: int, frame: FrameType | None) -> None:
    for guard in reversed(list(_open)):
        guard._end("KILLED", None)
    previous = _previous.get(signum, signal.SIG_DFL)
    if callable(previous):
        previous(signum, frame)  # SIGINT's default raises KeyboardInterrupt
    elif previous != signal.SIG_IGN:
        # Default SIGTERM: exit via SystemExit so `finally` blocks (closing Ray, the tracking actor) still run.
        raise SystemExit(128 + signum)


class RunGuard:
    """``with RunGuard(sink, run_id) as tracker:`` ends the run FINISHED on a normal exit, FAILED on an
    exception (traceback logged as ``error.txt``), KILLED on KeyboardInterrupt, SIGINT or SIGTERM. While any
    guard is open (and only in the main thread) SIGTERM/SIGINT end all open runs KILLED, then the previous
    handler runs (default SIGTERM: ``SystemExit(143)``); the previous handlers come back when the last closes."""

    def __init__(self, sink: Sink, run_id: str):
        self.client = TrackingClient(sink)
        self.run_id = run_id
        self.tracker = Tracker(sink, run_id)
        self.status: str | None = None

    def __enter__(self) -> Tracker:
        if not _open and threading.current_thread() is threading.main_thread():
            _previous.update({sig: signal.signal(sig, _on_signal) for sig in _SIGNALS})
        _open.append(self)
        return self.tracker

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if exc_type is None:
                try:
                    self.tracker.flush()
                except Exception as e:
                    self._end("FAILED", "".join(traceback.format_exception(e)))
                    raise
                self._end("FINISHED", None)
            elif issubclass(exc_type, Exception):
                self._flush_quietly()
                self._end("FAILED", "".join(traceback.format_exception(exc_type, exc, tb)))
            elif issubclass(exc_type, SystemExit) and exc.code in (0, None):
                self._end("FINISHED", None)
            elif issubclass(exc_type, SystemExit):
                self._end("FAILED", f"SystemExit({exc.code!r})\n")
            else:  # KeyboardInterrupt and other interruptions
                self._flush_quietly()
                self._end("KILLED", None)
        finally:
            _open.remove(self)
            if not _open and _previous:
                for sig, handler in _previous.items():
                    signal.signal(sig, handler)
                _previous.clear()

    def _flush_quietly(self) -> None:
        try:
            self.tracker.flush()
        except Exception:
            # one line: the error that ends the run is what the user must see (GDWM_DEBUG=1: the traceback)
            log.warning("run %s: queued tracking calls failed while the run was failing: %s", self.run_id,
                        one_line(sys.exc_info()[1]), exc_info=bool(os.environ.get("GDWM_DEBUG")))  # fmt: skip

    def _end(self, status: str, error_text: str | None) -> None:
        """End the run once; never masks the exception that is ending it."""
        if self.status is not None:
            return
        self.status = status
        try:
            if error_text is not None:
                self.client.log_text(self.run_id, error_text, "error.txt")
            self.client.end_run(self.run_id, status)
        except Exception:
            # A store that can't be written (TrackingError) is reported once, by the driver; anything else here.
            level = logging.INFO if isinstance(sys.exc_info()[1], TrackingError) else logging.WARNING
            log.log(level, "run %s: could not end it %s (%s); the next gdwm run on this store ends it", self.run_id,
                    status, one_line(sys.exc_info()[1]), exc_info=bool(os.environ.get("GDWM_DEBUG")))  # fmt: skip
