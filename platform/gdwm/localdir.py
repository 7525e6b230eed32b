"""This machine's own directory for what gdwm keeps between processes and is safe to lose: local copies of remote
cache entries, code fingerprints by file, the empty MLflow store new stores are copied from, torch's build facts.
``$GDWM_LOCAL_CACHE``, default ``~/.cache/gdwm``."""

from __future__ import annotations

import os
from pathlib import Path

ENV = "GDWM_LOCAL_CACHE"


def local_dir() -> Path:
    return Path(os.environ.get(ENV) or Path.home() / ".cache" / "gdwm")
