"""The dashboard's reads of a workdir's sqlite store without importing MLflow.

Why this exists: on 2 cores ``import mlflow`` and its SQLAlchemy store take 4-5 s before the first query, which alone
misses the dashboard's 3 s start. The reads the pages make are few and simple (an experiment by name, runs by tag
equality ordered by start time, one run, a metric's history, a run's local artifacts), so for a sqlite store they are
answered here, read-only (``mode=ro``: a reader never creates, migrates or locks the file), with MLflow's own
semantics: the same run dicts, the same order (start time descending, then run id, unless told), NaN metrics as NaN.
``tests/gdwm/ui/test_sqlite.py`` checks every read against ``mlflow.MlflowClient`` on a real store.

Anything else returns ``None`` and ``gdwm.ui.store.Store`` asks MLflow's client: another filter or order, an MLflow
whose schema lacks a column read here (checked once per store), artifacts not on a local path, the model registry.
"""

from __future__ import annotations

import math
import os
import re
import sqlite3
import urllib.parse
from pathlib import Path

# The tables and columns read here (MLflow's tracking schema, unchanged since MLflow 1.x).
COLUMNS = {
    "experiments": {"experiment_id", "name", "lifecycle_stage"},
    "runs": {
        *("run_uuid", "name", "status", "start_time", "end_time", "lifecycle_stage", "artifact_uri", "experiment_id"),
    },
    "tags": {"key", "value", "run_uuid"},
    "params": {"key", "value", "run_uuid"},
    "latest_metrics": {"key", "value", "is_nan", "run_uuid"},
    "metrics": {"key", "value", "timestamp", "step", "is_nan", "run_uuid"},
}
# One equality on a tag or param: tags.`gdwm.kind` = 'trial' (a value with a quote or backslash goes to MLflow, whose
# unescaping this does not repeat).
_CLAUSE = re.compile(r"\s*(tags|params)\.(?:`([^`]+)`|([\w.]+))\s*=\s*'([^'\\]*)'\s*", re.IGNORECASE)
_AND = re.compile(r"and\b", re.IGNORECASE)
_ORDER = re.compile(r"\s*attributes\.(start_time|end_time)(?:\s+(ASC|DESC))?\s*", re.IGNORECASE)
_TEMP_PREFIX = ".artifact.uploading."  # MLflow's local artifact repository hides its partial uploads


def parse_filter(text: str) -> list[tuple[str, str, str]] | None:
    """``[(table, key, value)]`` for a conjunction of tag/param equalities; None for anything else."""
    out: list[tuple[str, str, str]] = []
    pos, text = 0, text.strip()
    while pos < len(text):
        m = _CLAUSE.match(text, pos)
        if m is None:
            return None
        out.append((m.group(1).lower(), m.group(2) or m.group(3), m.group(4)))
        pos = m.end()
        if pos < len(text):
            a = _AND.match(text, pos)
            if a is None or a.end() == len(text):  # not "and", or "and" with nothing after it
                return None
            pos = a.end()
    return out


def parse_order(order_by: list[str] | None) -> list[tuple[str, bool]] | None:
    """``[(column, ascending)]`` for start/end time orders (MLflow's default: ascending); None for anything else."""
    out: list[tuple[str, bool]] = []
    for clause in order_by or []:
        m = _ORDER.fullmatch(clause)
        if m is None or any(c == m.group(1).lower() for c, _ in out):
            return None
        out.append((m.group(1).lower(), (m.group(2) or "ASC").upper() == "ASC"))
    return out


def local_artifacts(uri: str | None) -> Path | None:
    """The folder of an artifact URI that is a local path (a plain path or ``file://``); None for any other."""
    if not uri:
        return None
    if uri.startswith("file://"):
        parsed = urllib.parse.urlparse(uri)
        return Path(urllib.parse.unquote(parsed.path)) if parsed.netloc in ("", "localhost") else None
    return Path(uri) if uri.startswith("/") else None


class SqliteRuns:
    """Read-only reads of one sqlite tracking store (a connection per call: pages read from several threads)."""

    def __init__(self, db: str):
        self.db = db
        self._usable: bool | None = None

    def _connect(self) -> sqlite3.Connection:
        uri = "file:" + urllib.parse.quote(os.path.abspath(self.db)) + "?mode=ro"
        return sqlite3.connect(uri, uri=True, timeout=30, check_same_thread=False)

    def usable(self) -> bool:
        """Whether the file has every column read here (another MLflow schema: every read goes to MLflow)."""
        if self._usable is None:
            with self._connect() as con:
                have = {t: {row[1] for row in con.execute(f"PRAGMA table_info({t})")} for t in COLUMNS}
            self._usable = all(cols <= have[t] for t, cols in COLUMNS.items())
        return self._usable

    def experiment_id(self, name: str) -> str | None:
        """The active experiment of that name (MLflow's default workspace where the schema has workspaces)."""
        with self._connect() as con:
            cols = {row[1] for row in con.execute("PRAGMA table_info(experiments)")}
            where = " AND workspace = 'default'" if "workspace" in cols else ""
            row = con.execute(
                f"SELECT experiment_id, lifecycle_stage FROM experiments WHERE name = ?{where}", (name,)
            ).fetchone()
        return str(row[0]) if row is not None and row[1] == "active" else None

    def search(
        self, experiment_id: str, filter_string: str, max_results: int, order_by: list[str] | None
    ) -> list[dict] | None:
        """Active runs of the experiment matching the filter, in MLflow's order; None where it is not understood."""
        clauses, order = parse_filter(filter_string), parse_order(order_by)
        if clauses is None or order is None:
            return None
        where, args = ["r.experiment_id = ?", "r.lifecycle_stage = 'active'"], [int(experiment_id)]
        for table, key, value in clauses:
            match = f"SELECT 1 FROM {table} x WHERE x.run_uuid = r.run_uuid AND x.key = ? AND x.value = ?"
            where.append(f"EXISTS ({match})")
            args += [key, value]
        keys = [f"(r.{c} IS NULL), r.{c} {'ASC' if asc else 'DESC'}" for c, asc in order]
        if "start_time" not in {c for c, _ in order}:
            keys.append("r.start_time DESC")
        keys.append("r.run_uuid ASC")
        sql = f"SELECT r.run_uuid FROM runs r WHERE {' AND '.join(where)} ORDER BY {', '.join(keys)} LIMIT ?"
        with self._connect() as con:
            ids = [row[0] for row in con.execute(sql, [*args, max_results])]
            return self._runs(con, ids)

    def run(self, run_id: str) -> dict | None:
        """One run as ``gdwm.ui.store.run_dict`` makes it; None where there is no such run."""
        with self._connect() as con:
            found = self._runs(con, [run_id])
        return found[0] if found else None

    def _runs(self, con: sqlite3.Connection, ids: list[str]) -> list[dict]:
        out: dict[str, dict] = {}
        for chunk in (ids[i : i + 500] for i in range(0, len(ids), 500)):  # SQLite's bound-variable limit
            marks = ",".join("?" * len(chunk))
            for rid, name, status, start, end, exp, uri in con.execute(
                "SELECT run_uuid, name, status, start_time, end_time, experiment_id, artifact_uri FROM runs "
                f"WHERE run_uuid IN ({marks})",
                chunk,
            ):
                out[rid] = {
                    "run_id": rid,
                    "name": name or "",
                    "status": status,
                    "start_time": start,
                    "end_time": end,
                    "experiment_id": str(exp),
                    "artifact_uri": uri,
                    "tags": {},
                    "params": {},
                    "metrics": {},
                }
            for table in ("tags", "params"):
                for rid, key, value in con.execute(
                    f"SELECT run_uuid, key, value FROM {table} WHERE run_uuid IN ({marks})", chunk
                ):
                    out[rid][table][key] = value
            for rid, key, value, is_nan in con.execute(
                f"SELECT run_uuid, key, value, is_nan FROM latest_metrics WHERE run_uuid IN ({marks})", chunk
            ):
                out[rid]["metrics"][key] = math.nan if is_nan else float(value)
        for run in out.values():
            if not run["name"]:  # as MLflow: a run without a name takes its mlflow.runName tag
                run["name"] = run["tags"].get("mlflow.runName", "")
        return [out[i] for i in ids if i in out]

    def history(self, run_id: str, key: str) -> list[tuple[int, float]]:
        """(step, value) of every logged point, by step then time."""
        with self._connect() as con:
            rows = con.execute(
                "SELECT step, value, is_nan FROM metrics WHERE run_uuid = ? AND key = ? ORDER BY step, timestamp",
                (run_id, key),
            ).fetchall()
        return [(int(step), math.nan if is_nan else float(value)) for step, value, is_nan in rows]

    def artifact_root(self, run_id: str) -> Path | None:
        """The run's artifact folder where it is a local path; None otherwise (or no such run)."""
        with self._connect() as con:
            row = con.execute("SELECT artifact_uri FROM runs WHERE run_uuid = ?", (run_id,)).fetchone()
        return local_artifacts(row[0]) if row else None


def list_local(root: Path, path: str | None) -> list[tuple[str, bool, int | None]]:
    """(path, is_dir, size) under ``root/path``, sorted by path, as MLflow's local artifact repository lists them."""
    rel = inside(path) if path else ""
    folder = root / rel if rel else root
    if not folder.is_dir():
        return []
    out = []
    for entry in os.scandir(folder):
        if entry.name.startswith(_TEMP_PREFIX):
            continue
        p = f"{rel}/{entry.name}" if rel else entry.name
        is_dir = entry.is_dir()
        out.append((p, is_dir, None if is_dir else entry.stat().st_size))
    return sorted(out)


def inside(path: str) -> str:
    """A relative artifact path with no way out of its run's folder, else ValueError naming it."""
    parts = [p for p in path.replace("\\", "/").split("/") if p not in ("", ".")]
    if path.startswith("/") or ".." in parts:
        raise ValueError(f"artifact path {path!r} is not inside the run's artifacts")
    return "/".join(parts)
