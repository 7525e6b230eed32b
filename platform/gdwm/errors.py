"""Every failure the CLI reports is one line (``GDWM_DEBUG=1`` shows the traceback): this names what failed.

Ray wraps what went wrong inside a task or actor in its own exceptions, whose text is a remote traceback with
terminal colours; ``one_line`` digs out the original error and the task or actor it happened in.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
from pathlib import Path


class CommandError(Exception):
    """A command that failed at run time; printed without a traceback, exit 1."""


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_WHERE = re.compile(r"ray::([\w.\-]+(?::[\w.]+\(\))?)")
_ACTORS = {
    "TrackingBackend": "the tracking actor",
    "ProgressBoard": "the progress actor",
    "SceneWorker": "a scene worker",
}


def _last_error_line(text: str) -> str:
    """The ``Type: message`` line a Python traceback ends with (else the text's first line)."""
    lines = [ln.rstrip() for ln in _ANSI.sub("", text).splitlines() if ln.strip()]
    for ln in reversed(lines):
        if not ln.startswith((" ", "\t")) and re.match(r"^[A-Za-z_][\w.]*(Error|Exception|Exit|Interrupt)\b", ln):
            return ln
    return lines[0] if lines else ""


def _where(text: str) -> str:
    """``the tracking actor (TrackingBackend.__init__)`` / ``task run_stage()`` from a Ray error's text."""
    m = _WHERE.search(_ANSI.sub("", text))
    if not m:
        return ""
    name = m.group(1).removesuffix("()")
    for cls, label in _ACTORS.items():
        if f":{cls}." in name or name.startswith(f"{cls}."):
            return f"{label} ({name.split(':', 1)[-1]})"
    return f"Ray task {name}"


_NODE_MEMORY = re.compile(r"Memory on the node .*? was ([\d.]+\s*\w+ used / [\d.]+\s*\w+ limit)")
_KILLED_USED = re.compile(r"actual memory used=([\d.]+\s*\w+)")


def oom_line(e: BaseException) -> str:
    """Ray's many-line out-of-memory report as one line: how full the node was and what the killed worker held."""
    text = str(e)
    node = _NODE_MEMORY.search(text)
    used = _KILLED_USED.search(text)
    return (
        "out of memory: Ray's OOM killer ended the worker"
        + (f" (it held {used[1]})" if used else "")
        + (f", the node's memory being {node[1]}" if node else "")
        + "; give the stage more memory or fewer parallel workers (cluster.resources)"
    )


def one_line(e: BaseException) -> str:
    """``Type: message`` of ``e``, or for a Ray error the original error and where it was raised; a ``gdwm_hint``
    attached on the way out (what became of the runs, say) is appended."""
    hint = getattr(e, "gdwm_hint", None)
    return f"{_one_line(e)}; {hint}" if hint else _one_line(e)


def _one_line(e: BaseException) -> str:
    import ray.exceptions as rex  # here, not at import: the CLI's --help must not load Ray

    if isinstance(e, rex.RayError):
        if isinstance(e, rex.OutOfMemoryError):
            return oom_line(e)
        if isinstance(e, rex.RayTaskError):
            cause = e.cause if isinstance(e.cause, BaseException) else None
            what = one_line(cause) if cause is not None else _last_error_line(str(e))
            where = _where(str(e))
        elif isinstance(e, rex.RayActorError):
            text = getattr(e, "error_msg", "") or str(e)
            where = _where(text) or "an actor"
            if getattr(e, "_actor_init_failed", False):
                return f"{where} failed to start: {_last_error_line(text)}"
            what = _last_error_line(text) or "it died"
            return f"{where} died: {what}"
        else:
            what, where = _last_error_line(str(e)), ""
        return f"{what} (in {where})" if where else what
    if isinstance(e, OSError) and e.errno in _ENVIRONMENT and e.filename:
        return environment_line(e)
    msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return f"{type(e).__name__}: {msg}" if msg else type(e).__name__


_ENVIRONMENT = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}
"""What the machine refuses (a full disk, a quota, a read-only or foreign file system), as opposed to a bug."""


def environment_line(e: OSError) -> str:
    """``<path>: <what> (<where it is, and what to change>)``: which file, on which file system, and why."""
    path = Path(os.fsdecode(e.filename))
    what = f"{path}: {e.strerror}"
    home = Path.home()
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        with contextlib.suppress(OSError):
            where = next(p for p in (path, *path.parents) if p.exists())
            what += f" ({shutil.disk_usage(where).free / 1e6:.1f} MB free on that file system)"
    if path == home or home in path.parents:
        what += f"; it is under HOME ({home}), which gdwm and Ray write to: point HOME at a writable directory"
    return what
