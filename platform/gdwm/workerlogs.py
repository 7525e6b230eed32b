"""Worker output in the driver's log (``run.worker_logs``) to its last line.

Ray forwards what its workers write through each node's log monitor: a pass reads the new lines of every worker
log file it has open and publishes them, and a pass that found nothing sleeps 0.1 s; the driver prints what arrives
from a listener thread that ``ray.shutdown`` stops at once. So a stage that logs a warning and returns could be
done, and Ray shut down, before a pass read that warning: a launch lost its last lines (a local Ray, three tasks
that each print a line, then ``ray.shutdown``: none of the three printed in two of three tries).

``drain`` waits for them: a task on every node prints a marker line, and once the driver has received every
node's marker, it does it again. The second round starts after the first round's markers arrived, so each node's
pass that published the first marker (and every file after it in that pass) has published before the second
marker can, and everything a worker wrote before ``drain`` began is printed. The markers themselves are not
printed: ``drain`` puts a filter in front of Ray's printer. What can still be cut, as in Ray: the output of a
worker whose log file the monitor has not found yet (it looks for new files every 0.5 s; a stage's worker has
been up longer, importing its libraries), and more lines than a pass reads of one file (Ray's
``LOG_MONITOR_NUM_LINES_TO_READ``) written just before the end.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

MARK = "gdwm-worker-logs-mark "
"""What a marker line starts with (a uuid follows)."""

TIMEOUT_S = 10.0
"""How long ``drain`` waits for the markers by default."""

_PRINTER = "ray_print_logs"
"""The name Ray's driver gives its printer of worker output (present only with ``log_to_driver=True``)."""


class _Filter:
    """Ray's printer of worker output with the marker lines taken out; records the markers it saw."""

    def __init__(self, printer: Callable[[dict], Any]):
        self.printer = printer
        self.seen: set[str] = set()
        self.arrived = threading.Condition()

    def __call__(self, data: dict) -> None:
        lines = data.get("lines") or []
        marks = {line for line in lines if line.startswith(MARK)}
        if marks:
            with self.arrived:
                self.seen |= marks
                self.arrived.notify_all()
            data = {**data, "lines": [line for line in lines if line not in marks]}
            if not data["lines"]:
                return
        self.printer(data)


def _filter() -> _Filter | None:
    """The filter in front of Ray's printer, put there now if it is not yet; None when Ray prints no worker output
    (``log_to_driver=False``) or its dispatcher is not as this module knows it."""
    from ray._private.ray_logging import global_worker_stdstream_dispatcher as dispatcher

    lock = getattr(dispatcher, "_lock", None)
    if lock is None:
        return None
    with lock:  # Ray's emit iterates the list under this lock, and its remove_handler replaces it
        handlers = getattr(dispatcher, "handlers", None)
        for i, (name, handler) in enumerate(handlers if isinstance(handlers, list) else []):
            if name == _PRINTER:
                if not isinstance(handler, _Filter):
                    # The same name: Ray's disconnect removes it by that name, and the next connection starts clean.
                    handler = _Filter(handler)
                    handlers[i] = (name, handler)
                return handler
    return None


@ray.remote(num_cpus=0)
def _mark(line: str) -> None:
    print(line, flush=True)


def drain(timeout_s: float = TIMEOUT_S) -> bool:
    """Wait until the driver has printed what every worker wrote before this call (module docstring). True when it
    has, or when Ray prints no worker output; False when a node's markers did not come back within ``timeout_s``."""
    printer = _filter()
    if printer is None:
        return True
    nodes = [n["NodeID"] for n in ray.nodes() if n["Alive"]]
    deadline = time.monotonic() + timeout_s
    for _ in range(2):
        marks = set()
        for node in nodes:
            marks.add(line := f"{MARK}{uuid.uuid4().hex}")
            _mark.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)).remote(line)
        with printer.arrived:
            if not printer.arrived.wait_for(lambda m=marks: m <= printer.seen, timeout=deadline - time.monotonic()):
                return False
    return True
