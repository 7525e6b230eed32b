"""Cache housekeeping: ``gdwm cache ls``, ``gdwm cache gc`` and ``gdwm cache invalidate``, on any ``pyarrow.fs`` URI.

What an entry is worth comes from two places: the cache itself (size, creation, the ``<stage>/.used/<key>`` marker
a cache hit leaves, the run that produced it) and the tracking store, which says who still needs it:

- a zoo version with an alias (its lineage tags name its stage's key and its upstream keys),
- a regression baseline (``gdwm.kind=regression``, ``gdwm.baseline=true``; its ``cache_keys.json`` artifact lists the
  entries its results came from),
- a RUNNING run (a stage run's ``gdwm.cache_key`` and the entries it is publishing; a trial's ``cache_keys.json``).

Those entries are never deleted, and neither is an entry created or used within the grace period (``args.grace``).
gc deletes only complete entries (with a manifest), through ``Cache.invalidate`` (moved aside first where the
filesystem renames directories), re-reads an entry's marker just before deleting it, and removes ``.tmp-*``/
``.trash-*`` leftovers and incomplete entries only when nothing in them changed for a day: safe while another driver
publishes.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import os
import re
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow.fs as pafs
from omegaconf import DictConfig
from rich.table import Table

from gdwm.cache import CACHE_KEYS, MANIFEST, USED_DIR, Cache, Manifest, cache_key, canonical_json
from gdwm.config import sqlite_path
from gdwm.owned import CACHE_MARKER, NotOurs, own_cache
from gdwm.term import console, err_console

log = logging.getLogger(__name__)

BASES_DIR = ".bases"
"""``<stage>/.bases/<base>/<key>``: the index ``cache.reuse=all`` looks up; its base-named dirs are no leftovers."""
LEFTOVER_AGE_S = 86400.0
"""``.tmp-*``/``.trash-*`` dirs and incomplete entries untouched for this long are debris, not a publish in progress."""
_MAX_COMBINATIONS = 256
_KEY_RE = re.compile(r"[0-9a-f]{64}")
_PREFIX_RE = re.compile(r"[0-9a-f]{8,64}")
# No installed library parses "30d"-style ages (pydantic's timedelta wants ISO 8601 or HH:MM:SS), so a small regex.
_AGE_RE = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*([smhdw])")
_AGE_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0, "w": 604800.0}
GC_OPTIONS = ("--keep-last", "--older-than", "--max-size")
GC_FLAGS = ("--dry-run",)


class UsageError(Exception):
    """Bad arguments (the CLI prints the message and exits 2); the message names the flag or argument."""


class HousekeepingError(Exception):
    """gc cannot tell what is protected (the tracking store is unreadable): nothing was deleted, exit 1."""


# --- limits -------------------------------------------------------------------------------------------------------


def parse_age(text: str, what: str) -> float:
    """``30d`` -> seconds; units s, m, h, d, w (``1.5h`` works too)."""
    m = _AGE_RE.fullmatch(text.strip().lower())
    if m is None:
        raise UsageError(f"{what}: '{text}' is not an age: a number with a unit s, m, h, d or w (e.g. 30d)")
    return float(m[1]) * _AGE_UNITS[m[2]]


def parse_size(text: str, what: str) -> int:
    """``50GB`` -> bytes: B, KB, MB, GB, TB are powers of 1000, KiB, MiB, GiB, TiB powers of 1024 (pydantic's
    ``ByteSize``, case-insensitive; a bare number is bytes)."""
    from pydantic import ByteSize, TypeAdapter, ValidationError

    try:
        return int(TypeAdapter(ByteSize).validate_python(text.strip()))
    except ValidationError:
        raise UsageError(
            f"{what}: '{text}' is not a size: a number with a unit B, KB, MB, GB, TB (powers of 1000) or KiB, MiB, "
            "GiB, TiB (powers of 1024), e.g. 50GB"
        ) from None


def parse_count(text: str, what: str) -> int:
    if not re.fullmatch(r"\d+", text.strip()):
        raise UsageError(f"{what}: '{text}' is not a count (an integer >= 0)")
    return int(text)


@dataclass(frozen=True)
class Limits:
    """What ``gdwm cache gc`` deletes (see ``plan_gc``)."""

    keep_last: int | None = None
    older_than: float | None = None
    """Seconds."""
    max_size: int | None = None
    """Bytes."""
    dry_run: bool = False

    def __post_init__(self) -> None:
        if self.keep_last is None and self.older_than is None and self.max_size is None:
            raise UsageError(
                "no limit given: pass --keep-last N (per stage and scene), --older-than AGE (e.g. 30d) and/or "
                "--max-size SIZE (e.g. 50GB); --dry-run shows what they would delete"
            )


def parse_gc_args(argv: Iterable[str]) -> Limits:
    """``--keep-last N``, ``--older-than AGE``, ``--max-size SIZE`` (``--flag VALUE`` or ``--flag=VALUE``) and
    ``--dry-run``; other arguments (overrides) are ignored. Each limit at most once."""
    argv = list(argv)
    given: dict[str, str] = {}
    dry_run = False
    i = 0
    while i < len(argv):
        arg = argv[i]
        name, eq, value = arg.partition("=")
        if name in GC_OPTIONS:
            if not eq:
                if i + 1 >= len(argv) or argv[i + 1].startswith("--") or "=" in argv[i + 1]:
                    raise UsageError(f"{name} needs a value ({name} VALUE or {name}=VALUE)")
                value, i = argv[i + 1], i + 1
            if name in given:
                raise UsageError(f"{name}: given twice ({given[name]} and {value}); give each limit once")
            given[name] = value
        elif arg in GC_FLAGS:
            dry_run = True
        i += 1
    keep = given.get("--keep-last")
    age = given.get("--older-than")
    size = given.get("--max-size")
    return Limits(
        keep_last=None if keep is None else parse_count(keep, "--keep-last"),
        older_than=None if age is None else parse_age(age, "--older-than"),
        max_size=None if size is None else parse_size(size, "--max-size"),
        dry_run=dry_run,
    )


# --- what the cache holds -----------------------------------------------------------------------------------------


@dataclass
class Entry:
    manifest: Manifest
    path: str
    size: int
    """Bytes of every file in the entry's directory (its manifest included)."""
    used_at: float | None = None
    """The time its ``.used/<key>`` marker holds (its latest cache hit); None without one."""

    @property
    def stage(self) -> str:
        return self.manifest.stage

    @property
    def key(self) -> str:
        return self.manifest.key

    @property
    def scene(self) -> str | None:
        return self.manifest.scene

    @property
    def last_used(self) -> float:
        return max(self.used_at or 0.0, self.manifest.created_at)


@dataclass
class Leftover:
    """A ``.tmp-*``/``.trash-*`` dir, an entry dir without a (readable) manifest, or a marker of no entry."""

    path: str
    kind: str
    size: int
    age: float | None
    """Seconds since anything in it changed; None when the filesystem reports no times."""


@dataclass
class Scan:
    entries: list[Entry]
    leftovers: list[Leftover]

    @property
    def stages(self) -> list[str]:
        return sorted({e.stage for e in self.entries})


def _mtime(info: pafs.FileInfo) -> float | None:
    return info.mtime.timestamp() if info.mtime is not None else None


def read_marker(cache: Cache, path: str, mtime: float | None = None) -> float | None:
    """The unix time a ``.used/<key>`` marker holds (its mtime if the text is unreadable); None when absent."""
    try:
        with cache.fs.open_input_stream(path) as f:
            text = f.read().decode(errors="replace")
    except FileNotFoundError:
        return None
    try:
        t = float(text)
        return t if math.isfinite(t) else mtime
    except ValueError:
        return mtime


def scan(cache: Cache, stage: str | None = None, now: float | None = None) -> Scan:
    """Every complete entry (sized from one recursive listing per stage) and every leftover, of one stage or all."""
    now = time.time() if now is None else now
    stages = [stage] if stage is not None else scan_stages(cache)
    entries: list[Entry] = []
    leftovers: list[Leftover] = []
    for s in stages:
        base = f"{cache.root}/{s}"
        infos = cache.walk(base)  # never into a symlink's target
        items: dict[str, list[int | float | None]] = {}  # <shard>/<name> -> [size, newest mtime]
        markers: dict[str, tuple[str, float | None, int]] = {}  # key -> (path, mtime, size)
        for info in infos:
            parts = info.path[len(base) + 1 :].split("/")
            if parts[0] == USED_DIR:
                if len(parts) == 2 and info.type == pafs.FileType.File:
                    markers[parts[1]] = (info.path, _mtime(info), info.size)
                continue
            if parts[0] == BASES_DIR or len(parts) < 2:  # the code-free index is kept by Cache.lookup_base
                continue
            item = items.setdefault(f"{parts[0]}/{parts[1]}", [0, None])
            if info.type == pafs.FileType.File:
                item[0] += info.size
            if (t := _mtime(info)) is not None:
                item[1] = t if item[1] is None else max(item[1], t)
        complete = {m.key: m for m in cache.entries(s)}
        for rel, (size, newest) in sorted(items.items()):
            name, path = rel.split("/")[1], f"{base}/{rel}"
            age = None if newest is None else now - newest
            if name in complete:
                marker = markers.pop(name, None)
                used = read_marker(cache, *marker[:2]) if marker else None
                entries.append(Entry(complete[name], path, int(size), used))
            elif name.startswith((".tmp-", ".trash-")):
                leftovers.append(Leftover(path, name.split("-", 1)[0], int(size), age))
            elif _KEY_RE.fullmatch(name):
                leftovers.append(Leftover(path, "incomplete", int(size), age))
        for key, (path, mtime, size) in sorted(markers.items()):
            if f"{key[:2]}/{key}" not in items:  # the entry is gone: the marker is debris
                leftovers.append(Leftover(path, "marker", size, None if mtime is None else now - mtime))
    return Scan(sorted(entries, key=lambda e: (e.stage, -e.last_used, e.key)), leftovers)


# --- who references an entry --------------------------------------------------------------------------------------


@dataclass
class Refs:
    """What the tracking store says about the cache's keys."""

    zoo: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))
    """key -> the zoo versions whose lineage names it: ``gdwm-lora/3@champion``, ``... (upstream)``."""
    protect: dict[str, list[tuple[str, str]]] = field(default_factory=lambda: defaultdict(list))
    """key -> ``(why, detail)``, why one of ``alias``, ``baseline``, ``running``."""
    runs: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))
    """key -> runs other than the producing one that name it (baselines, running trials)."""
    warnings: list[str] = field(default_factory=list)


class _Resolver:
    """A referenced ``(stage, key)`` -> the keys of the cache entries it means. A downstream stage names a per-scene
    upstream by its aggregate key (``gdwm.executor.aggregate_key``), which no entry has: it is matched against the
    aggregates of that stage's per-scene entries (same version, config and data, one entry per scene)."""

    def __init__(self, entries: Iterable[Entry]):
        self.keys = {e.key for e in entries}
        self.by_stage: dict[str, list[Manifest]] = defaultdict(list)
        for e in entries:
            if e.scene is not None:
                self.by_stage[e.stage].append(e.manifest)
        self._aggregates: dict[str, dict[str, list[str]]] = {}

    def __call__(self, stage: str, key: str) -> list[str]:
        if key in self.keys:
            return [key]
        if stage not in self._aggregates:
            self._aggregates[stage] = self._aggregate(self.by_stage.get(stage, []))
        return self._aggregates[stage].get(key, [])

    @staticmethod
    def _aggregate(manifests: list[Manifest]) -> dict[str, list[str]]:
        groups: dict[tuple, dict[str, list[Manifest]]] = defaultdict(lambda: defaultdict(list))
        for m in manifests:
            digest = (m.code or {}).get("digest")
            groups[(m.version, canonical_json(m.config), m.data_fingerprint, digest)][m.scene].append(m)
        out: dict[str, list[str]] = {}
        for (version, config, data, digest), scenes in groups.items():
            names = sorted(scenes)
            if math.prod(len(scenes[s]) for s in names) > _MAX_COMBINATIONS:
                log.warning("cache gc: too many entries per scene to match the aggregate keys of %s", names[:3])
                continue
            for combo in itertools.product(*(scenes[s] for s in names)):
                upstream = {f"scene:{m.scene}": m.key for m in combo}
                for code in {None, digest}:
                    agg = cache_key(combo[0].stage, version, json.loads(config), upstream, data, None, code)
                    out[agg] = [m.key for m in combo]
        return out


def _client(tracking_uri: str):
    """An MlflowClient, or None for a sqlite store that does not exist yet (nothing references anything)."""
    if (db := sqlite_path(tracking_uri)) is not None and not Path(db).exists():
        return None
    from mlflow import MlflowClient

    return MlflowClient(tracking_uri, registry_uri=tracking_uri)


def _paged(fetch: Callable[[str | None], list]) -> list:
    out, token = [], None
    while True:
        page = fetch(token)
        out += list(page)
        token = getattr(page, "token", None)
        if not token:
            return out


@contextlib.contextmanager
def _no_progress_bars() -> Iterator[None]:
    """MLflow draws a progress bar per artifact download (read from the environment per call); a run's
    ``cache_keys.json`` is one tiny file among many. (``gdwm.compare.samples.quiet_downloads`` does the same but
    imports Ray with the tracking backend.)"""
    from mlflow.environment_variables import MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR as bar

    old = os.environ.get(bar.name)
    os.environ[bar.name] = "false"
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(bar.name, None)
        else:
            os.environ[bar.name] = old


def _cache_keys(client, run_id: str, tmp: str) -> dict[str, list[str]] | None:
    """A run's ``cache_keys.json``; None when it has none."""
    if not any(a.path == CACHE_KEYS for a in client.list_artifacts(run_id)):
        return None
    with open(client.download_artifacts(run_id, CACHE_KEYS, tmp)) as f:
        data = json.load(f)
    if not isinstance(data, dict):
        raise ValueError(f"run {run_id}: {CACHE_KEYS} is not a JSON object of stage -> [keys]")
    return {str(s): [str(k) for k in (keys if isinstance(keys, list) else [keys])] for s, keys in data.items()}


def references(tracking_uri: str, entries: list[Entry]) -> Refs:
    """Zoo versions, baselines and RUNNING runs of the tracking store, matched to the cache's entries."""
    from mlflow.entities import ViewType

    refs = Refs()
    client = _client(tracking_uri)
    if client is None:
        return refs
    resolve = _Resolver(entries)
    by_run: dict[str, list[str]] = defaultdict(list)
    for e in entries:
        if e.manifest.run_id:
            by_run[e.manifest.run_id].append(e.key)

    aliases: dict[tuple[str, str], list[str]] = defaultdict(list)
    for model in _paged(lambda t: client.search_registered_models(max_results=1000, page_token=t)):
        for alias, version in sorted(model.aliases.items()):
            aliases[(model.name, str(version))].append(alias)
    for mv in _paged(lambda t: client.search_model_versions(max_results=1000, page_token=t)):
        tags = mv.tags or {}
        if "gdwm.cache_key" not in tags:
            continue
        mine = aliases.get((mv.name, str(mv.version)), [])
        label = f"{mv.name}/{mv.version}" + (f"@{','.join(mine)}" if mine else "")
        named = [(tags.get("gdwm.stage", ""), tags["gdwm.cache_key"], "")]
        named += [(k.removeprefix("gdwm.upstream."), v, " (upstream)") for k, v in sorted(tags.items())
                  if k.startswith("gdwm.upstream.")]  # fmt: skip
        for stage, key, how in named:
            for k in resolve(stage, key):
                refs.zoo[k].append(label + how)
                if mine:
                    refs.protect[k].append(("alias", f"zoo {label}{how}"))

    experiments = [x.experiment_id for x in client.search_experiments(view_type=ViewType.ACTIVE_ONLY)]
    if not experiments:
        return refs

    def runs(filter_string: str) -> list:
        return _paged(
            lambda t: client.search_runs(experiments, filter_string, ViewType.ACTIVE_ONLY, 1000, page_token=t)
        )

    with tempfile.TemporaryDirectory(prefix="gdwm-gc-") as tmp, _no_progress_bars():
        for r in runs("tags.`gdwm.kind` = 'regression' and tags.`gdwm.baseline` = 'true'"):
            rid, bench = r.info.run_id, r.data.tags.get("gdwm.benchmark", "?")
            listed = _cache_keys(client, rid, tmp)
            if listed is None:
                refs.warnings.append(
                    f"baseline run {rid} (benchmark {bench}) has no {CACHE_KEYS} (recorded by an older "
                    "gdwm): the entries it used cannot be told apart and are not protected"
                )
                continue
            for stage, keys in listed.items():
                for k in (k for key in keys for k in resolve(stage, key)):
                    refs.protect[k].append(("baseline", f"baseline run {rid[:12]} ({bench})"))
                    refs.runs[k].append(rid)
        for r in runs("attributes.status = 'RUNNING'"):
            rid, tags = r.info.run_id, r.data.tags
            why = ("running", f"running run {rid[:12]}")
            if tags.get("gdwm.kind") == "stage":
                named = resolve(tags.get("gdwm.stage", ""), tags.get("gdwm.cache_key", ""))
                for k in {*named, *by_run.get(rid, [])}:  # a per-scene stage publishes its scenes under its run
                    refs.protect[k].append(why)
            elif (listed := _cache_keys(client, rid, tmp)) is not None:
                for stage, keys in listed.items():
                    for k in (k for key in keys for k in resolve(stage, key)):
                        refs.protect[k].append(why)
                        refs.runs[k].append(rid)
    return refs


# --- gc -------------------------------------------------------------------------------------------------------------


@dataclass
class GcPlan:
    delete: list[Entry]
    kept: list[tuple[Entry, list[tuple[str, str]]]]
    """Entries a limit selected that are kept, with why (``alias``, ``baseline``, ``running``, ``grace``)."""
    leftovers: list[Leftover]
    over_by: int = 0
    """Bytes still above ``--max-size`` after every deletable entry is gone."""

    @property
    def freed(self) -> int:
        return sum(e.size for e in self.delete)


def plan_gc(entries: list[Entry], refs: Refs, limits: Limits, grace: float, now: float) -> GcPlan:
    """Which entries go. ``--keep-last N`` selects every entry beyond the N most recently used of its stage and scene,
    ``--older-than AGE`` every entry unused for longer than AGE; with both, an entry must be selected by both (the N
    newest are always kept). Then ``--max-size`` deletes least recently used entries until the rest fits (never one
    of those N). A protected or grace-period entry is never deleted."""

    def protected(e: Entry) -> list[tuple[str, str]]:
        why = list(dict.fromkeys(refs.protect.get(e.key, [])))
        if now - e.last_used < grace:
            why.append(("grace", f"used {_ago(now - e.last_used)} ago (grace {_ago(grace)})"))
        return why

    guard: set[str] = set()
    beyond: set[str] = set()
    if limits.keep_last is not None:
        groups: dict[tuple[str, str | None], list[Entry]] = defaultdict(list)
        for e in entries:
            groups[(e.stage, e.scene)].append(e)
        for group in groups.values():
            group.sort(key=lambda e: (-e.last_used, e.key))
            guard |= {e.key for e in group[: limits.keep_last]}
            beyond |= {e.key for e in group[limits.keep_last :]}
    old = set() if limits.older_than is None else {e.key for e in entries if now - e.last_used > limits.older_than}
    if limits.keep_last is not None and limits.older_than is not None:
        selected = beyond & old
    else:
        selected = beyond if limits.keep_last is not None else old

    delete, kept, gone = [], [], set()
    for e in entries:
        if e.key in selected:
            if why := protected(e):
                kept.append((e, why))
            else:
                delete.append(e)
                gone.add(e.key)
    over_by = 0
    if limits.max_size is not None:
        total = sum(e.size for e in entries if e.key not in gone)
        kept_keys = {e.key for e, _ in kept}
        for e in sorted(entries, key=lambda e: (e.last_used, e.manifest.created_at, e.key)):
            if total <= limits.max_size:
                break
            if e.key in gone or e.key in guard:
                continue
            if why := protected(e):
                if e.key not in kept_keys:
                    kept.append((e, why))
                    kept_keys.add(e.key)
                continue
            delete.append(e)
            gone.add(e.key)
            total -= e.size
        over_by = max(0, total - limits.max_size)
    return GcPlan(delete, kept, [], over_by)


def _ago(seconds: float) -> str:
    for unit, n in (("w", 604800), ("d", 86400), ("h", 3600), ("m", 60)):
        if seconds >= n:
            return f"{seconds / n:.1f}{unit}".replace(".0" + unit, unit)
    return f"{max(seconds, 0):.0f}s"


def human(n: int) -> str:
    """Decimal units, as ``--max-size`` reads them (``12.3MB``)."""
    from pydantic import ByteSize

    return ByteSize(n).human_readable(decimal=True)


def _when(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(t)) if t else "-"


@dataclass
class GcResult:
    plan: GcPlan
    deleted: list[Entry]
    skipped: list[Entry]
    """Planned deletions found in use (a fresh marker) just before deleting: kept."""
    leftovers_removed: list[Leftover]
    warnings: list[str] = field(default_factory=list)

    @property
    def freed(self) -> int:
        return sum(e.size for e in self.deleted)


def gc(
    cache: Cache,
    tracking_uri: str,
    limits: Limits,
    *,
    grace: float = 3600.0,
    stage: str | None = None,
    now: float | None = None,
) -> GcResult:
    """Plan with ``plan_gc`` and, unless ``limits.dry_run``, delete (see the module docstring for the safety rules);
    a dry run reports what it would delete in ``deleted``."""
    now = time.time() if now is None else now
    if own(cache) == "empty":
        return GcResult(GcPlan([], [], []), [], [], [])
    found = scan(cache, stage, now)
    try:
        refs = references(tracking_uri, found.entries)
    except Exception as e:  # whatever the store's client raises: without it nothing is known to be safe to delete
        raise HousekeepingError(
            f"tracking store {tracking_uri} unreadable ({e!r}); gc needs it to know which entries zoo aliases, "
            "baselines and running runs protect, and deleted nothing"
        ) from e
    plan = plan_gc(found.entries, refs, limits, grace, now)
    plan.leftovers = [x for x in found.leftovers if x.age is not None and x.age > LEFTOVER_AGE_S]
    if limits.dry_run:
        return GcResult(plan, list(plan.delete), [], list(plan.leftovers), refs.warnings)
    deleted, skipped = [], []
    for e in plan.delete:
        marker = cache.used_marker(e.stage, e.key)
        used = read_marker(cache, marker)
        if (used is not None and time.time() - used < grace) or _republished(cache, e):  # in use since the scan
            skipped.append(e)
            continue
        if cache.invalidate(e.stage, e.key):
            deleted.append(e)
        with contextlib.suppress(FileNotFoundError):
            cache.fs.delete_file(marker)
    removed = []
    for x in plan.leftovers:
        with contextlib.suppress(FileNotFoundError):
            if x.kind == "marker":
                cache.fs.delete_file(x.path)
            else:
                cache.fs.delete_dir(x.path)
            removed.append(x)
    return GcResult(plan, deleted, skipped, removed, refs.warnings)


def own(cache: Cache) -> str:
    """``gdwm.owned.own_cache`` for a command that deletes: a root gdwm did not create is a ``UsageError`` (exit 2);
    one an older gdwm wrote is marked, and said so."""
    try:
        state = own_cache(cache, create=False)
    except NotOurs as e:
        raise UsageError(f"{e}; gc and invalidate act only on a directory gdwm created, and deleted nothing") from None
    if state == "legacy":
        err_console.print(f"gdwm cache: {cache.uri} has gdwm's layout but no {CACHE_MARKER} (an older gdwm): marked "
                          "it as a gdwm cache", markup=False)  # fmt: skip
    return state


def _republished(cache: Cache, e: Entry) -> bool:
    """Whether the entry was replaced (a forced recompute published it anew) since the scan."""
    try:
        with cache.fs.open_input_stream(f"{e.path}/{MANIFEST}") as f:
            return Manifest.from_json(f.read().decode()).created_at != e.manifest.created_at
    except (FileNotFoundError, ValueError, KeyError, TypeError):
        return False  # gone or unreadable: invalidate() handles both


def print_gc(result: GcResult, limits: Limits) -> None:
    plan, dry = result.plan, limits.dry_run
    for w in result.warnings:
        err_console.print(f"gdwm cache gc: warning: {w}", markup=False)
    verb = "would delete" if dry else "deleted"
    for e in result.deleted:
        console.print(
            f"{verb} {e.stage}/{e.key[:12]}{' ' + e.scene if e.scene else ''}  {human(e.size)} ({e.size} bytes), "
            f"last used {_when(e.last_used)}",
            markup=False,
        )
    for e in result.skipped:
        console.print(f"kept {e.stage}/{e.key[:12]}: looked up or republished while gc ran", markup=False)
    console.print(
        f"{verb} {len(result.deleted)} entries, {result.freed} bytes ({human(result.freed)})"
        + ("" if dry else " freed"),
        markup=False,
    )
    if plan.kept:
        counts: dict[str, int] = defaultdict(int)
        for _, why in plan.kept:
            for w in dict.fromkeys(w for w, _ in why):
                counts[w] += 1
        console.print(
            f"kept {len(plan.kept)} protected entries ({', '.join(f'{w}: {n}' for w, n in sorted(counts.items()))}):",
            markup=False,
        )
        for e, why in plan.kept:
            console.print(f"  {e.stage}/{e.key[:12]}: {'; '.join(d for _, d in why)}", markup=False)
    if result.leftovers_removed:
        n = sum(x.size for x in result.leftovers_removed)
        kinds = ", ".join(sorted({x.kind for x in result.leftovers_removed}))
        console.print(
            f"{'would remove' if dry else 'removed'} {len(result.leftovers_removed)} leftovers ({kinds}), {n} bytes",
            markup=False,
        )
    if plan.over_by:
        err_console.print(
            f"gdwm cache gc: still {human(plan.over_by)} over --max-size {human(limits.max_size or 0)}: the rest is "
            "protected, in its grace period or kept by --keep-last",
            markup=False,
        )


# --- commands ---------------------------------------------------------------------------------------------------


def _stage_arg(cache: Cache, cfg: DictConfig, required: bool = False) -> str | None:
    stage = cfg.args.get("stage")
    if stage is None:
        if required:
            raise UsageError("args.stage is required (gdwm cache ls lists the stages)")
        return None
    plain = re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", stage)
    if not plain or cache.fs.get_file_info(f"{cache.root}/{stage}").type != pafs.FileType.Directory:
        known = ", ".join(scan_stages(cache)) or "none"
        raise UsageError(f"args.stage={stage}: no such stage in the cache {cache.root} (stages: {known})")
    return stage


def scan_stages(cache: Cache) -> list[str]:
    top = cache.fs.get_file_info(pafs.FileSelector(cache.root, allow_not_found=True))
    return sorted(i.base_name for i in top if i.type == pafs.FileType.Directory and not i.base_name.startswith("."))


def _grace(cfg: DictConfig) -> float:
    return parse_age(str(cfg.args.get("grace", "1h")), "args.grace")


def cmd_ls(cfg: DictConfig, _argv: list[str]) -> int:
    cache = Cache(cfg.cache.uri)
    stage = _stage_arg(cache, cfg)
    found = scan(cache, stage)
    try:
        refs = references(cfg.tracking.uri, found.entries)
    except Exception as e:  # listing stays useful without the tracking store; gc does not run without it
        err_console.print(f"gdwm cache ls: warning: tracking store {cfg.tracking.uri} unreadable ({e!r})", markup=False)
        refs = Refs()
    for w in refs.warnings:
        err_console.print(f"gdwm cache ls: warning: {w}", markup=False)
    if stage is None:
        print_summary(cache, found, refs)
    else:
        print_entries(cache, stage, found, refs)
    return 0


def print_summary(cache: Cache, found: Scan, refs: Refs) -> None:
    t = Table(title=f"cache {cache.root}", header_style="bold")
    for col in ("stage", "entries", "size", "bytes", "last used", "runs", "zoo versions", "protected"):
        t.add_column(col, justify="left" if col in ("stage", "last used") else "right")
    by_stage: dict[str, list[Entry]] = defaultdict(list)
    for e in found.entries:
        by_stage[e.stage].append(e)
    for stage in found.stages:
        es = by_stage[stage]
        size = sum(e.size for e in es)
        runs = {e.manifest.run_id for e in es if e.manifest.run_id} | {r for e in es for r in refs.runs.get(e.key, [])}
        zoo = {v.split("@")[0].split(" ")[0] for e in es for v in refs.zoo.get(e.key, [])}
        t.add_row(stage, str(len(es)), human(size), str(size), _when(max(e.last_used for e in es)), str(len(runs)),
                  str(len(zoo)), str(sum(1 for e in es if refs.protect.get(e.key))))  # fmt: skip
    total = sum(e.size for e in found.entries)
    t.add_row("total", str(len(found.entries)), human(total), str(total), "", "", "", "", style="bold")
    console.print(t)
    if found.leftovers:
        n = sum(x.size for x in found.leftovers)
        console.print(
            f"{len(found.leftovers)} leftovers (interrupted publishes, deletions, stale markers), {human(n)}: "
            "gdwm cache gc removes those untouched for a day",
            markup=False,
        )


def print_entries(cache: Cache, stage: str, found: Scan, refs: Refs) -> None:
    es = found.entries
    total = sum(e.size for e in es)
    t = Table(title=f"{stage}: {len(es)} entries, {human(total)} in {cache.root}/{stage}", header_style="bold")
    for col in ("key", "scene", "size", "created", "last used", "run", "code", "zoo versions", "protected by"):
        t.add_column(col, justify="right" if col == "size" else "left")
    for e in es:
        m = e.manifest
        code = (m.code or {}).get("digest", "")[:12] or "unknown"
        protected = ", ".join(dict.fromkeys(w for w, _ in refs.protect.get(e.key, [])))
        t.add_row(m.key[:12], m.scene or "", human(e.size), _when(m.created_at), _when(e.last_used),
                  (m.run_id or "")[:12], code, ", ".join(refs.zoo.get(e.key, [])), protected)  # fmt: skip
    console.print(t)


def cmd_gc(cfg: DictConfig, argv: list[str]) -> int:
    limits = parse_gc_args(argv)
    grace = _grace(cfg)
    cache = Cache(cfg.cache.uri)
    result = gc(cache, cfg.tracking.uri, limits, grace=grace, stage=_stage_arg(cache, cfg))
    print_gc(result, limits)
    return 0


def cmd_invalidate(cfg: DictConfig, _argv: list[str]) -> int:
    cache = Cache(cfg.cache.uri)
    stage = _stage_arg(cache, cfg, required=True)
    own(cache)
    prefix = str(cfg.args.get("key") or "")
    if not _PREFIX_RE.fullmatch(prefix):
        raise UsageError(f"args.key={prefix or '?'}: give the entry's key or a prefix of >= 8 hex characters")
    shard = f"{cache.root}/{stage}/{prefix[:2]}"
    infos = cache.fs.get_file_info(pafs.FileSelector(shard, allow_not_found=True))
    matches = sorted(
        i.base_name
        for i in infos
        if i.type == pafs.FileType.Directory and _KEY_RE.fullmatch(i.base_name) and i.base_name.startswith(prefix)
    )
    if len(matches) != 1:
        shown = ", ".join(m[:16] for m in matches)
        what = f"{len(matches)} entries of stage {stage} ({shown}); give more characters" if matches else "no entry"
        raise UsageError(f"args.key={prefix}: matches {what}" + ("" if matches else f" of stage {stage}"))
    key = matches[0]
    size = sum(i.size for i in cache.walk(f"{shard}/{key}") if i.type == pafs.FileType.File)
    cache.invalidate(stage, key)
    with contextlib.suppress(FileNotFoundError):
        cache.fs.delete_file(cache.used_marker(stage, key))
    from gdwm.training import discard_checkpoints

    n = discard_checkpoints(Path(cfg.workdir).resolve() / "checkpoints", stage, key)
    console.print(f"removed {stage}/{key} ({human(size)}); discarded {n} checkpoint(s) of that key", markup=False)
    return 0


SUBCOMMANDS: Mapping[str, Callable[[DictConfig, list[str]], int]] = {
    "ls": cmd_ls,
    "gc": cmd_gc,
    "invalidate": cmd_invalidate,
}
