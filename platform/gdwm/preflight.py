"""Checks of the machine before Ray starts, so an environment that cannot work fails at once with one line saying
what is wrong, instead of Ray's own symptom a minute later (a full TMPDIR: "Timed out waiting for file
.../gcs_server_port_...")."""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

RAY_TMP_NEEDS = 64 * 1024 * 1024
"""Bytes Ray's session directory needs to start (sockets, port files, the first logs)."""


def ray_temp_root() -> tuple[str, Path]:
    """``(variable, directory)`` where a local Ray keeps its sessions: ``RAY_TMPDIR``, else ``TMPDIR`` (Linux), else
    ``/tmp`` (as ``ray._private.utils.get_user_temp_dir`` decides; that one is private)."""
    if os.environ.get("RAY_TMPDIR"):
        return "RAY_TMPDIR", Path(os.environ["RAY_TMPDIR"])
    if sys.platform.startswith("linux") and os.environ.get("TMPDIR"):
        return "TMPDIR", Path(os.environ["TMPDIR"])
    return "TMPDIR", Path(tempfile.gettempdir())


def writable_space(path: Path, need: int) -> str | None:
    """Why ``need`` bytes cannot be written under ``path`` (one line), or None when they can: its free space, and a
    1 MiB probe written and synced (a quota or a read-only mount shows only then)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(path).free
        if free < need:
            return f"{path} has only {_mb(free)} free ({_mb(need)} needed)"
        with tempfile.NamedTemporaryFile(dir=path, prefix=".gdwm-probe-") as f:
            f.write(b"\0" * (1 << 20))
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        return f"{path}: {e.strerror or e}"
    return None


def check_ray_temp() -> str | None:
    """One line naming the variable and directory when a local Ray could not start its session there."""
    var, root = ray_temp_root()
    why = writable_space(root, RAY_TMP_NEEDS)
    if why is None:
        return None
    return f"{var}: {why}; Ray keeps its session files there: free some space or point {var} at another disk"


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"
