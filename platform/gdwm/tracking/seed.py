"""A new sqlite MLflow store starts as a copy of an empty one, instead of being migrated from MLflow's first schema.

MLflow creates a sqlite store by creating its first tables and then running every schema migration since (alembic,
some fifty revisions): 3-5 s of CPU on the 2-core CI box, and every fresh workdir -- a user's first run, each test's
-- pays it in the tracking actor before the first run is created. Opening an existing store takes tens of
milliseconds. So the first store made by a given MLflow version is made by MLflow itself (its own table creation and
migrations, nothing else) in ``$GDWM_LOCAL_CACHE/mlflow-schema/`` (default ``~/.cache/gdwm``), and every new store
after it is a copy of that file. MLflow then opens the copy as it opens any store: it checks the schema revision and
creates its default experiment, as it would have in a store it had just migrated.

Anything unexpected (an MLflow without the helper used here, a read-only cache directory) leaves the store to MLflow,
as before: seeding only ever saves time.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
from pathlib import Path

from gdwm.config import sqlite_path
from gdwm.localdir import local_dir

log = logging.getLogger(__name__)


def _umask_mode() -> int:
    """The mode a file created the ordinary way gets (mkstemp's is 0600)."""
    try:  # Linux: read, not set-and-restore (os.umask would change it for every thread meanwhile)
        with open("/proc/self/status") as f:
            mask = next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError):
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def template_dir() -> Path:
    return local_dir() / "mlflow-schema"


def _template() -> Path:
    """The empty store of this MLflow version (made now if it is not there yet)."""
    import mlflow
    import sqlalchemy
    from mlflow.store.db.utils import _initialize_tables  # what SqlAlchemyStore itself calls on an empty database

    path = template_dir() / f"mlflow-{mlflow.__version__}-sqlalchemy-{sqlalchemy.__version__}.db"
    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        engine = sqlalchemy.create_engine(f"sqlite:///{tmp}")
        try:
            _initialize_tables(engine)
        finally:
            engine.dispose()
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, path)  # atomic: a concurrent maker's file is as good as ours
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
    return path


def seed_store(uri: str) -> bool:
    """Make the sqlite store of ``uri`` a copy of the empty template when it does not exist yet; whether it did. The
    caller holds the store's lock (``gdwm.tracking.storelock``); a store that appears meanwhile is never replaced."""
    db = sqlite_path(uri)
    if db is None or Path(db).exists():
        return False
    try:
        Path(db).parent.mkdir(parents=True, exist_ok=True)  # as MLflow does for a sqlite store
        template = _template()
        fd, tmp = tempfile.mkstemp(prefix=".mlflow-seed-", dir=Path(db).parent)
        os.close(fd)
        try:
            shutil.copyfile(template, tmp)
            os.chmod(tmp, _umask_mode())  # as sqlite would have created it
            os.link(tmp, db)  # fails if a store appeared meanwhile: never replaces one
        finally:
            os.unlink(tmp)
    except Exception as e:  # MLflow creates the store itself, as it always did
        log.debug("not seeding %s from the empty-store template: %r", db, e)
        return False
    return True
