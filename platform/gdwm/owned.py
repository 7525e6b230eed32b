"""gdwm overwrites and deletes only what it created: each directory it owns carries a marker file at its top.

- a cache root (``cache.uri``, any ``pyarrow.fs`` URI): ``.gdwm-cache``, written with its first entry. ``gdwm cache
  gc`` and ``gdwm cache invalidate`` act only on a root that has it, and a launch refuses a ``cache.uri`` that holds
  anything else (a typo pointing at a home directory, another tool's store): exit 2, naming the first stranger.
- a report directory (``gdwm compare``'s ``args.out``, ``<workdir>/reports/<sweep>``): ``.gdwm-report``, written
  when gdwm creates it; reports are written only into an empty directory or one that has it. A zoo download
  (``gdwm zoo load``'s ``args.out``) likewise carries ``.gdwm-download``.

Directories an older gdwm wrote without a marker are recognised by gdwm's own layout and marked on first use: a cache
whose top level holds only stage directories (each holding only ``<2 hex>`` shards, ``.used`` and ``.bases``) and
``.locks``, with at least one readable manifest; a report directory holding only report files (``*.md``, ``*.tex``,
``*.csv``, ``*.html``), a download holding a version's ``MLmodel``. Anything else is refused, never marked.
(Datasets are marked by their ``dataset.json``.)
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from pathlib import Path

import pyarrow.fs as pafs

CACHE_MARKER = ".gdwm-cache"
REPORT_MARKER = ".gdwm-report"
REPORT_SUFFIXES = (".md", ".tex", ".csv", ".html")
DOWNLOAD_MARKER = ".gdwm-download"
_CACHE_DOT_DIRS = frozenset({".locks"})
_STAGE_DOT_DIRS = frozenset({".used", ".bases"})
_STAGE_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
_SHARD_RE = re.compile(r"[0-9a-f]{2}")
_KEY_RE = re.compile(r"[0-9a-f]{64}")


class NotOurs(Exception):
    """A directory gdwm did not create (no marker, not gdwm's layout): the message names it and what is foreign."""


def _marker_text(kind: str) -> bytes:
    return json.dumps({"gdwm": kind, "created_at": time.time()}).encode()


# ---- cache roots ---------------------------------------------------------------------------------------------------
def _listing(cache, path: str) -> list[pafs.FileInfo]:
    return cache.fs.get_file_info(pafs.FileSelector(path, allow_not_found=True))


def cache_state(cache) -> str:
    """``marked``, ``empty`` (absent, or nothing in it) or ``legacy`` (gdwm's layout, no marker); ``NotOurs`` else."""
    root = cache.root
    if cache.fs.get_file_info(f"{root}/{CACHE_MARKER}").type == pafs.FileType.File:
        return "marked"
    top = _listing(cache, root)
    if not top:
        return "empty"
    where = f"cache.uri={cache.uri}"
    manifests = 0
    for info in sorted(top, key=lambda i: i.base_name):
        name = info.base_name
        if name == CACHE_MARKER and info.type == pafs.FileType.File:
            # another process (a scene actor beside this one, another driver) marked the root between our two reads
            return "marked"
        if info.type != pafs.FileType.Directory or not (name in _CACHE_DOT_DIRS or _STAGE_RE.fullmatch(name)):
            raise NotOurs(f"{where}: not a gdwm cache ({name} is not gdwm's, and there is no {CACHE_MARKER})")
        if name in _CACHE_DOT_DIRS:
            continue
        for shard in _listing(cache, info.path):
            if shard.type != pafs.FileType.Directory or not (
                shard.base_name in _STAGE_DOT_DIRS or _SHARD_RE.fullmatch(shard.base_name)
            ):
                raise NotOurs(f"{where}: not a gdwm cache ({name}/{shard.base_name} is not gdwm's, and there is no "
                              f"{CACHE_MARKER})")  # fmt: skip
            if manifests or shard.base_name in _STAGE_DOT_DIRS:
                continue
            keys = [e.base_name for e in _listing(cache, shard.path) if _KEY_RE.fullmatch(e.base_name)]
            manifests += any(cache._load(name, k, cache._dir(name, k))[0] is not None for k in keys[:3])
    stages = [i for i in top if i.base_name not in _CACHE_DOT_DIRS]
    if stages and not manifests:
        raise NotOurs(f"{where}: not a gdwm cache (no {CACHE_MARKER} and no readable gdwm manifest in "
                      f"{', '.join(sorted(i.base_name for i in stages)[:3])})")  # fmt: skip
    return "legacy"


def mark_cache(cache) -> None:
    if not cache._dirless:
        cache.fs.create_dir(cache.root, recursive=True)
    with cache.fs.open_output_stream(f"{cache.root}/{CACHE_MARKER}") as f:
        f.write(_marker_text("cache"))


def own_cache(cache, create: bool) -> str:
    """Check that ``cache``'s root is gdwm's before writing (``create``: an empty root is marked now) or deleting in
    it; a legacy cache is marked. Returns what it was; ``NotOurs`` for a foreign root."""
    state = cache_state(cache)
    if state == "legacy" or (state == "empty" and create):
        mark_cache(cache)
    return state


# ---- output directories ------------------------------------------------------------------------------------------
def own_dir(out: Path, marker: str, what: str, legacy: Callable[[list[Path]], bool], create: bool = True) -> None:
    """Make ``out`` a directory gdwm may write into: created (and marked) if absent or empty, marked if ``legacy``
    recognises its contents as an older gdwm's; ``NotOurs`` when it holds anything else. ``create=False`` only
    checks (the caller marks it once it wrote something)."""
    out = Path(out)
    if (out / marker).is_file():
        return
    if out.exists():
        if not out.is_dir():
            raise NotOurs(f"{out}: not a directory; {what}s go into a directory gdwm creates")
        inside = sorted(out.iterdir())
        if inside and not legacy(inside):
            raise NotOurs(f"{out}: not a gdwm {what} directory ({inside[0].name} is not gdwm's, and there is no "
                          f"{marker}); choose an empty or new directory")  # fmt: skip
    if create:
        out.mkdir(parents=True, exist_ok=True)
        (out / marker).write_bytes(_marker_text(what))


def own_report_dir(out: Path) -> None:
    """``own_dir`` for ``gdwm compare``'s outputs: an older gdwm's folder holds only report files."""
    own_dir(
        out, REPORT_MARKER, "report", lambda inside: all(p.is_file() and p.suffix in REPORT_SUFFIXES for p in inside)
    )


def own_download_dir(out: Path, create: bool = True) -> None:
    """``own_dir`` for ``gdwm zoo load``: an older gdwm's download holds the version's ``MLmodel``."""
    own_dir(out, DOWNLOAD_MARKER, "download", lambda inside: any(p.name == "MLmodel" for p in inside), create)
