"""Datasets for a command: building one (light: no Ray, no MLflow, so ``gdwm data synth`` starts fast), and checking
the one at ``data.root`` before a run uses it.

Data is verified, not trusted. ``dataset.json`` records every file's sha256, size and mtime (``files``) and the
builder's content-determining parameters (``params``). Before a run:

- ``check_params``: every recorded ``params`` key must equal the requested ``data.<key>``, else ``DataMismatch``
  (``gdwm run`` exits 2 before anything runs). An error, not a silent regeneration: the dataset at ``data.root`` may
  be an expensive import, or shared with other runs, and replacing it is the user's call (``overwrite=true``).
- ``verify_dataset``: a stat of every file; a file whose size and mtime match its record keeps its recorded sha256
  (no read), any other is re-hashed, and added or removed files count too. The fingerprint is recomputed from those
  hashes, so an edited table changes it, and with it the key of every stage that depends on the data.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gdwm.callables import check_callables, resolve_callable
from gdwm.term import console, err_console


class DataMismatch(Exception):
    """The dataset at ``data.root`` was built with other parameters than the run requests (the message names them)."""


def build_dataset(cfg: DictConfig, source: str | None) -> None:
    """Build the dataset selected by ``data=`` (published atomically by its builder), then print its summary."""
    root = Path(cfg.data.root)
    check_callables(cfg)  # every function the config names is registered, before the first one runs
    t0 = time.perf_counter()
    resolve_callable(cfg, "data.builder")(cfg.data, root=root, source=source, overwrite=cfg.overwrite)
    console.print(f"built {cfg.data.name} in {time.perf_counter() - t0:.1f} s")
    for part in resolve_callable(cfg, "data.summarizer")(root):  # the dataset's own lines and tables
        console.print(part)


# ---- parameters --------------------------------------------------------------------------------------------------
def _show(value) -> str:
    return value if isinstance(value, str) else json.dumps(value, separators=(",", ":"))


def check_params(data: DictConfig, root: Path, meta: Mapping) -> None:
    """Raise ``DataMismatch`` naming every ``data.<key>`` whose requested value differs from the recorded ``params``
    (a key the requested ``data=`` option lacks differs too: the dataset comes from another builder)."""
    diffs = []
    for key, built in (meta.get("params") or {}).items():
        if key not in data:
            diffs.append((key, f"nothing (data={data.get('name')} has no '{key}')", built))
            continue
        value = data[key]
        requested = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
        if requested != built:
            diffs.append((key, requested, built))
    if not diffs:
        return
    (key, requested, built), rest = diffs[0], diffs[1:]
    msg = f"data.{key}: requested {_show(requested)}, but the dataset at {root} was built with {_show(built)}"
    msg += "".join(f"; data.{k}: requested {_show(r)}, built with {_show(b)}" for k, r, b in rest)
    sets = " ".join(f"data.{k}={_show(r)}" for k, r, _ in diffs if k in data)
    raise DataMismatch(f"{msg}; use another data.root or rebuild it ({build_hint(data)} {sets} overwrite=true)")


def build_hint(data: DictConfig) -> str:
    """The command line that builds the dataset ``data`` selects, from its config (``data.build_command``)."""
    command = data.get("build_command") or "gdwm data <its build command>"
    source = " source=DIR" if data.get("needs_source", True) else ""
    return f"{command}{source} data={data.get('name')}"


# ---- files -------------------------------------------------------------------------------------------------------
def _stat_tree(root: Path) -> dict[str, tuple[int, int]]:
    """``{relpath: (size, mtime_ns)}`` of every file under ``root`` but dataset.json: one stat each, nothing read."""
    out: dict[str, tuple[int, int]] = {}
    stack = [(str(root), "")]
    while stack:
        folder, prefix = stack.pop()
        with os.scandir(folder) as it:
            for e in it:
                rel = prefix + e.name
                if e.is_dir(follow_symlinks=False):
                    stack.append((e.path, rel + "/"))
                elif e.is_file() and rel != "dataset.json":
                    st = e.stat()
                    out[rel] = (st.st_size, st.st_mtime_ns)
    return out


def file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _in_order(relpaths) -> list[str]:
    """Sorted by path components, as ``pathlib`` sorts paths (the fingerprint's order)."""
    return sorted(relpaths, key=lambda r: r.split("/"))


def fingerprint_of(hashes: Mapping[str, str]) -> str:
    """sha256 over ``relpath \\0 sha256 \\n`` in path-component order."""
    # The dataset format's documented fingerprint, implemented again here (the platform imports no pipeline code).
    h = hashlib.sha256()
    for rel in _in_order(hashes):
        h.update(f"{rel}\0{hashes[rel]}\n".encode())
    return h.hexdigest()


@dataclass
class Verified:
    """What ``verify_dataset`` found."""

    fingerprint: str
    """Recomputed from the files as they are now (equal to the recorded one when nothing changed)."""
    changed: list[str] = field(default_factory=list)
    """Files whose content differs from their record, and files added or removed since the dataset was written."""
    added: list[str] = field(default_factory=list)
    """The files of ``changed`` that dataset.json does not list."""
    removed: list[str] = field(default_factory=list)
    """The files of ``changed`` that dataset.json lists but are gone."""
    rehashed: list[str] = field(default_factory=list)
    """Files read in full: their size or mtime differed from the record (or there was no record)."""
    legacy: bool = False
    """dataset.json has no ``files`` (an older gdwm wrote it): every file was hashed."""
    files: int = 0
    seconds: float = 0.0


def verify_dataset(root: Path, meta: Mapping, stats: Mapping[str, tuple[int, int]] | None = None) -> Verified:
    """The dataset's fingerprint from its files as they are now (module docstring); reads only files whose size or
    mtime differ from ``meta["files"]`` (``stats``: a ``_stat_tree(root)`` already taken)."""
    t0 = time.perf_counter()
    root = Path(root)
    stats = _stat_tree(root) if stats is None else stats
    recorded: Mapping[str, Mapping] | None = meta.get("files")
    hashes: dict[str, str] = {}
    changed, rehashed, added = [], [], []
    for rel, (size, mtime_ns) in stats.items():
        rec = recorded.get(rel) if recorded is not None else None
        if rec is not None and rec["size"] == size and rec["mtime_ns"] == mtime_ns:
            hashes[rel] = rec["sha256"]
            continue
        hashes[rel] = file_sha256(root / rel)
        rehashed.append(rel)
        if recorded is not None and (rec is None or rec["sha256"] != hashes[rel]):
            (added if rec is None else changed).append(rel)
    removed = [rel for rel in recorded if rel not in stats] if recorded is not None else []
    return Verified(
        fingerprint_of(hashes),
        changed=_in_order([*changed, *added, *removed]),
        added=_in_order(added),
        removed=_in_order(removed),
        rehashed=_in_order(rehashed),
        legacy=recorded is None,
        files=len(stats),
        seconds=time.perf_counter() - t0,
    )


def _names(files: Sequence[str], most: int = 5) -> str:
    shown = ", ".join(files[:most])
    return shown if len(files) <= most else f"{shown} and {len(files) - most} more"


def describe(root: Path, meta: Mapping, v: Verified) -> str | None:
    """The warning a run prints for ``v``; None when the dataset is as it was written."""
    rerun = "stages that read the data will re-run"
    if v.legacy:
        same = v.fingerprint == meta.get("fingerprint")
        return (
            f"dataset {root}: its dataset.json (from an older gdwm) records no per-file hashes, so all {v.files} "
            f"files were read ({v.seconds:.1f} s) and {'match' if same else f'no longer match: {rerun}'} its "
            f"fingerprint; rebuild it (overwrite=true) to make this check a stat per file"
        )
    if v.changed:
        edited = [f for f in v.changed if f not in v.added and f not in v.removed]
        parts = [f"{_names(edited)} changed (re-hashed)"] if edited else []
        parts += [f"{_names(v.added)} added"] if v.added else []
        parts += [f"{_names(v.removed)} removed"] if v.removed else []
        return f"dataset {root}: {', '.join(parts)} since it was written; {rerun}"
    if v.rehashed:
        return (
            f"dataset {root}: {len(v.rehashed)} files have another size or mtime than dataset.json records but the "
            f"same content (re-hashed in {v.seconds:.1f} s, on every run until the dataset is rebuilt)"
        )
    return None


_VERIFIED: dict[tuple, Verified] = {}
"""Per process: a sweep composes many trials over one dataset, and each checks it; re-hash and warn once."""


def check_dataset(data: DictConfig, root: Path, meta: dict, checker: Callable | None = None) -> dict:
    """``meta`` with the fingerprint of the files as they are now, after ``check_params`` (raises ``DataMismatch``)
    and ``verify_dataset``: a file the record lists that is gone (a scene deleted) is a ``DataMismatch`` naming it,
    and ``checker(root, files)`` (the dataset's ``data.checker``) reads the files that differ from their record
    before any stage does; a warning says which files changed."""
    check_params(data, root, meta)
    stats = _stat_tree(root)
    key = (str(Path(root).resolve()), meta.get("fingerprint"), tuple(sorted(stats.items())))
    v = _VERIFIED.get(key)
    if v is None:
        v = verify_dataset(root, meta, stats)
        if v.removed:
            n = len(v.removed)
            raise DataMismatch(
                f"dataset {root}: {v.removed[0]} is listed in dataset.json but missing ({n} file{'s' * (n > 1)} "
                f"missing): the dataset is incomplete; rebuild it ({build_hint(data)} overwrite=true)"
            )
        if checker is not None and (differ := [f for f in v.changed if f not in v.removed]):
            try:
                checker(root, differ)
            except ValueError as e:  # the data layer's DataError: one line naming the file
                raise DataMismatch(f"dataset {root}: {e}") from None
        _VERIFIED[key] = v
        warning = describe(root, meta, v)
        if warning:
            err_console.print(f"warning: {warning}", markup=False)
    return {**meta, "fingerprint": v.fingerprint, "recorded_fingerprint": meta.get("fingerprint")}


def verification_line(root: Path) -> str:
    """What ``gdwm data info`` prints under the summary: the files against dataset.json."""
    meta = json.loads((Path(root) / "dataset.json").read_text())
    v = verify_dataset(root, meta)
    warning = describe(root, meta, v)
    if warning:
        return f"warning: {warning} (fingerprint now {v.fingerprint[:12]})"
    return f"verified: {v.files} files match dataset.json (size and mtime, {v.seconds * 1000:.0f} ms)"
