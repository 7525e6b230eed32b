"""A workdir's own MLflow store stays with the workdir when it is copied or moved.

MLflow records artifact locations as absolute paths (an experiment's root, each run's ``artifact_uri``, each logged
model's and model version's location). A workdir copied elsewhere would therefore read the original's artifacts and
write new ones into it. ``relocate_store`` re-roots them: when the sqlite store's experiment under the configured
``artifact_location``'s name (``<workdir>/mlartifacts``) records another root, every location under that old root
is rewritten to the new one, in one transaction. Run ids, metrics, params and tags are untouched, and nothing
outside the store is read or written. A store on a server (any non-sqlite URI) keeps its URIs: it is shared, and
its artifact root is the server's.
"""

from __future__ import annotations

import sqlite3
import sys
from pathlib import Path
from urllib.parse import unquote, urlparse

from gdwm.config import sqlite_path

COLUMNS = (
    ("experiments", "artifact_location"),
    ("runs", "artifact_uri"),
    ("logged_models", "artifact_location"),
    ("model_versions", "source"),
    ("model_versions", "storage_location"),
)
"""Where MLflow's sqlite schema keeps artifact locations."""


def _tables(db: sqlite3.Connection) -> set[str]:
    return {r[0] for r in db.execute("select name from sqlite_master where type = 'table'")}


def relocate_store(uri: str, artifact_location: str | None) -> int:
    """Re-root a moved workdir's sqlite store onto ``artifact_location`` (module docstring); returns how many
    locations were rewritten (0: nothing to do, or not a local sqlite store). The caller holds the store's lock."""
    db_path = sqlite_path(uri)
    new = _path(artifact_location) if artifact_location else None
    if db_path is None or new is None or not Path(db_path).is_file():
        return 0
    new = str(Path(new).resolve())
    with sqlite3.connect(db_path) as db:
        tables = _tables(db)
        if "experiments" not in tables:
            return 0
        roots = (_path(loc) for (loc,) in db.execute("select artifact_location from experiments") if loc)
        old_roots = [old for old in roots if old and Path(old).name == Path(new).name and old != new]
        changed = 0
        for old in dict.fromkeys(old_roots):
            # a location is written as a path, as file://<path> or as a percent-quoted file URI (Path.as_uri)
            forms = {(old, new), (f"file://{old}", f"file://{new}"), (Path(old).as_uri(), Path(new).as_uri())}
            for prefix, target in forms:
                for table, col in COLUMNS:
                    if table not in tables:
                        continue
                    # the root itself, or a path below it (never a sibling that merely starts with its name)
                    cur = db.execute(
                        f"update {table} set {col} = ? || substr({col}, ?) where {col} = ? or {col} like ? escape '\\'",
                        (target, len(prefix) + 1, prefix, _like(prefix) + "/%"),
                    )
                    changed += cur.rowcount
    if changed:
        _forget_artifact_repos()
    return changed


def _path(location: str) -> str | None:
    """The local path an artifact location names (a path or a ``file:`` URI, quoted or not); None for a remote one."""
    if location.startswith("file:"):
        return unquote(urlparse(location).path)
    return None if "://" in location else location


def _forget_artifact_repos() -> None:
    """MLflow keeps each run's artifact repository per process, keyed by run id: one this process opened before
    the move still names the old root. A process that has not imported MLflow has none (and importing it only to
    clear nothing costs seconds)."""
    if "mlflow" not in sys.modules:
        return
    try:
        from mlflow.tracking._tracking_service import utils
    except ImportError:  # a later MLflow without the cache
        return
    getattr(utils, "_artifact_repos_cache", {}).clear()


def _like(text: str) -> str:
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
