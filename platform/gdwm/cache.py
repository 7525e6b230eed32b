"""Content-addressed stage cache: a stage's output directory, keyed by the sha256 of its inputs.

Layout under the cache root (any ``pyarrow.fs`` URI, or a plain local path)::

    <root>/<stage>/<key[:2]>/<key>/MANIFEST.json    written last: key, config, upstream keys, sha256+size per file
    <root>/<stage>/<key[:2]>/<key>/<files...>       the stage's output, paths as in the source directory
    <root>/<stage>/<key[:2]>/.tmp-<key12>-<uuid>    a publish in progress, renamed onto <key> once complete
    <root>/<stage>/<key[:2]>/.trash-<key12>-<uuid>  a corrupt entry moved aside, being deleted
    <root>/<stage>/.bases/<base>/<key>              index: the entries of one code-free key (``cache.reuse=all``)
    <root>/<stage>/.used/<key>                      unix time of the entry's latest cache hit (``gdwm cache gc``)
    <root>/.gdwm-cache                              the root is gdwm's (``gdwm.owned``): written with the first entry

A manifest comes from a store others may write to (a shared bucket), so every path in it is a plain relative path
(``plain_relpath``: no ``..``, no absolute path; pyarrow's S3 filesystem would resolve ``a/../../b`` to a key outside
the entry, and a download would write outside the local copy), and walks of an entry list a symlink as itself,
never its target (an entry holding one is recomputed).

Written here because no maintained library publishes verified directories atomically through ``pyarrow.fs``.
Object stores (S3, GCS, Azure) cannot rename directories, so there (and on any filesystem not known to rename
atomically) files are uploaded in place and the manifest, one atomic PUT, is what makes an entry visible: a reader
never sees an entry whose manifest is missing, objects an interrupted publish left are deleted by the next publish of
the key (or by ``gdwm cache gc`` once a day old), and a concurrent writer's interleaved bytes fail verification and
are recomputed.

S3 (``s3://bucket/prefix``, through pyarrow's ``S3FileSystem``): credentials come from the environment
(``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_SESSION_TOKEN``) or the AWS SDK's other sources (``~/.aws``
files, an instance or pod role), never from the URI: one carrying them (``user:secret@``, ``access_key=``,
``secret_key=``, ``session_token=``) is refused. An S3-compatible endpoint (MinIO, moto) is ``AWS_ENDPOINT_URL``
(``http://host:port``) or the URI's query, ``s3://bucket/prefix?endpoint_override=host:port&scheme=http`` (quote it
in a Hydra override: ``'cache.uri="s3://..."'``); the query wins over the environment.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import re
import shutil
import stat
import time
import urllib.parse
import uuid
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.fs as pafs

from gdwm.localdir import local_dir

log = logging.getLogger(__name__)

MANIFEST = "MANIFEST.json"
CHUNK = 1 << 20
USED_DIR = ".used"
# pyarrow filesystems whose move() is an atomic directory rename that fails on a non-empty destination.
RENAMES_DIRS = frozenset({"local", "mock"})
# pyarrow filesystems without directories: a write needs no parent created first (each create_dir is a PUT there).
OBJECT_STORES = frozenset({"s3", "gcs", "abfs"})
_URI_SECRETS = ("access_key", "secret_key", "session_token")
_AWS_ERROR_RE = re.compile(r"AWS Error (\w+) during (\w+) operation")
_AWS_AUTH_ERRORS = frozenset(
    {"ACCESS_DENIED", "INVALID_ACCESS_KEY_ID", "SIGNATURE_DOES_NOT_MATCH", "EXPIRED_TOKEN", "INVALID_CLIENT_TOKEN_ID",
     "MISSING_AUTHENTICATION_TOKEN", "UNRECOGNIZED_CLIENT"}
)  # fmt: skip
_STAGE_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
_KEY_RE = re.compile(r"[0-9a-f]{64}")
_ABSENT = pafs.FileType.NotFound
_KINDS = {stat.S_IFREG: pafs.FileType.File, stat.S_IFDIR: pafs.FileType.Directory}


def _plain(obj: Any, path: str) -> Any:
    """``obj`` as JSON-ready containers (tuples become lists); a TypeError names the offending path."""
    where = path or "<root>"
    if obj is None or isinstance(obj, str | bool | int):
        return obj
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise TypeError(f"{where}: non-finite float {obj!r} is not allowed")
        return obj
    if isinstance(obj, Mapping):
        for k in obj:
            if not isinstance(k, str):
                raise TypeError(f"{where}: key {k!r} has unsupported type {type(k).__name__} (keys must be str)")
        return {k: _plain(v, f"{path}.{k}" if path else k) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    raise TypeError(f"{where}: unsupported type {type(obj).__name__}")


def canonical_json(obj: Any) -> str:
    """Sorted keys, no whitespace, floats by ``repr`` (0.1 stays 0.1); rejects NaN/Inf and non-JSON types."""
    return json.dumps(_plain(obj, ""), sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def cache_key(
    stage: str,
    version: str,
    config: Mapping,
    upstream: Mapping[str, str],
    data_fingerprint: str,
    scene: str | None = None,
    code: str | None = None,
) -> str:
    """sha256 hex of the canonical JSON of everything a stage's output depends on: name, version, config subset,
    upstream keys, data fingerprint, scene and ``code`` (the fingerprint of the code and libraries it runs,
    ``gdwm.fingerprint``). ``code=None`` gives the code-free key: an entry's ``base`` (its identity across code
    versions, what ``cache.reuse=all`` looks up), and the whole key of entries written before code was an input."""
    payload = {"stage": stage, "version": version, "config": config, "upstream": dict(upstream)}
    payload |= {"data": data_fingerprint, "scene": scene}
    if code is not None:
        payload["code"] = code
    return hashlib.sha256(canonical_json(payload).encode()).hexdigest()


def plain_relpath(path: str) -> bool:
    """Whether ``path`` names a place inside a directory whatever the filesystem makes of it: relative, posix
    separators, no empty, ``.`` or ``..`` component (pyarrow's S3 filesystem normalises ``a/../../b`` to a key
    outside the entry), no backslash or NUL."""
    parts = path.split("/")
    return bool(path) and not ({"", ".", ".."} & set(parts)) and "\\" not in path and "\x00" not in path


@dataclass(frozen=True)
class FileEntry:
    path: str
    """Path relative to the entry directory, posix separators (a plain relative path: ``plain_relpath``)."""
    sha256: str
    size: int

    def __post_init__(self) -> None:
        # a manifest comes from a store others may write to (a shared bucket): a file it names must stay in the entry
        if not isinstance(self.path, str) or not plain_relpath(self.path) or self.path == MANIFEST:
            raise ValueError(f"file {self.path!r}: not a plain relative path inside the entry")


@dataclass(frozen=True)
class Manifest:
    key: str
    stage: str
    version: str
    config: dict
    upstream: dict[str, str]
    data_fingerprint: str
    scene: str | None
    files: tuple[FileEntry, ...]
    run_id: str | None
    """The MLflow run that produced the entry."""
    created_at: float
    extra: dict
    code: dict | None = None
    """The code the entry was computed with: ``{"digest": ..., "files": {module file: hash}, "libraries":
    {distribution: version}}`` (``gdwm.fingerprint``); None for an entry written before code was part of the key
    ("unknown code", reused only under ``cache.reuse=all``)."""
    base: str | None = None
    """The entry's code-free key (``cache_key(..., code=None)`` over its upstream's bases): the same config, data and
    scene under any code. None = ``key`` (entries written before code was part of the key)."""

    @property
    def identity(self) -> str:
        return self.base or self.key

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True, indent=1, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> Manifest:
        d = json.loads(text)
        names = {f.name for f in fields(cls)}
        optional = {"code", "base"}  # absent in manifests of older gdwm versions
        if not isinstance(d, dict) or not names - optional <= set(d) <= names:
            raise ValueError(f"expected fields {sorted(names)}")
        files = tuple(FileEntry(str(f["path"]), str(f["sha256"]), int(f["size"])) for f in d.pop("files"))
        return cls(files=files, **d)


CACHE_KEYS = "cache_keys.json"
"""Artifact of trial and regression runs: ``{stage: [key, ...]}``, every entry their results came from (per-scene
stages: each scene's), what ``gdwm cache gc`` keeps for runs it must not break."""


class CacheError(Exception):
    """A cache entry that cannot be published or read; the message names stage, key prefix and file."""


def _sha256(stream: Any, sink: Any = None) -> tuple[str, int]:
    h, size = hashlib.sha256(), 0
    while chunk := stream.read(CHUNK):
        h.update(chunk)
        size += len(chunk)
        if sink is not None:
            sink.write(chunk)
    return h.hexdigest(), size


def _scan(stage: str, key: str, src: Path) -> list[tuple[str, Path]]:
    """``(relative posix path, file)`` for every file under ``src``; symlinks and special files are refused."""
    where = f"stage {stage} key {key[:12]}"
    if not src.is_dir():
        raise CacheError(f"{where}: {src}: source is not a directory")
    out = []
    for dirpath, dirnames, filenames in os.walk(src):
        for name in dirnames + filenames:
            p = Path(dirpath, name)
            rel = p.relative_to(src).as_posix()
            if p.is_symlink():  # it could point outside src_dir, and the entry must hold the bytes itself
                raise CacheError(f"{where}: {rel}: symlinks are refused")
            if name in filenames and not p.is_file():
                raise CacheError(f"{where}: {rel}: not a regular file")
            if name in filenames:
                out.append((rel, p))
    if any(rel == MANIFEST for rel, _ in out):
        raise CacheError(f"{where}: {MANIFEST}: name is reserved for the cache manifest")
    return sorted(out)


def _checked_uri(uri: str) -> str:
    """``uri`` unchanged; a ``CacheError`` when it carries credentials (the message shows it without them)."""
    parts = urllib.parse.urlsplit(uri)
    given = {k.lower() for k, _ in urllib.parse.parse_qsl(parts.query, keep_blank_values=True)}
    named = [f"{k}=" for k in _URI_SECRETS if k in given]
    if "@" in parts.netloc:
        named.insert(0, "user:secret@")
    if named:
        shown = f"{parts.scheme}://{parts.netloc.rpartition('@')[2]}{parts.path}"
        raise CacheError(
            f"cache.uri {shown}: credentials in the URI ({', '.join(named)}) are refused; set AWS_ACCESS_KEY_ID / "
            "AWS_SECRET_ACCESS_KEY (and AWS_SESSION_TOKEN) in the environment"
        )
    return uri


class Cache:
    """Stage outputs under a ``pyarrow.fs`` root; see the module docstring for the layout."""

    def __init__(self, uri: str | os.PathLike):
        self.uri = uri = str(uri)
        """As given (never with credentials: those are refused); what errors name."""
        if "://" in uri:
            try:
                self.fs, root = pafs.FileSystem.from_uri(_checked_uri(uri))
            except (OSError, pa.ArrowException) as e:  # an unknown scheme or query key, an unreachable region lookup
                raise CacheError(f"cache {uri}: {_first_line(e)}") from None
            self._scheme = uri.split("://", 1)[0] + "://"
            if isinstance(self.fs, pafs.S3FileSystem):
                # Delayed open: a small object is one PutObject instead of a 3-request multipart upload (what the URI
                # cannot ask for); its errors surface at close, which every write here reaches. The options are
                # those pyarrow pickles the filesystem with.
                options = self.fs.__reduce__()[1][0]
                self.fs = pafs.S3FileSystem(**{**options, "allow_delayed_open": True})
        else:
            self.fs, root, self._scheme = pafs.LocalFileSystem(), os.path.abspath(uri), ""
        self.root = root.rstrip("/")
        self.local = isinstance(self.fs, pafs.LocalFileSystem)
        self.atomic_dirs = self.fs.type_name in RENAMES_DIRS
        self._dirless = self.fs.type_name in OBJECT_STORES
        self._owned = False
        self.last_invalid: list[tuple[str, str, str]] = []
        """``(stage, key, reason)`` of every bad entry the latest ``lookup`` found and moved aside."""

    def _dir(self, stage: str, key: str) -> str:
        if not _STAGE_RE.fullmatch(stage):
            raise ValueError(f"stage name {stage!r}: use letters, digits, '_', '.', '-'")
        if not _KEY_RE.fullmatch(key):
            raise ValueError(f"stage {stage}: cache key {key!r} is not a sha256 hex digest")
        return f"{self.root}/{stage}/{key[:2]}/{key}"

    def _store_error(self, e: OSError, where: str) -> CacheError:
        """``e`` as one line after ``where`` (pyarrow's messages name no URI, and on S3 bury the cause): S3's error
        code and operation with the bucket; an authentication failure points at the credentials' variables."""
        m = _AWS_ERROR_RE.search(str(e))
        if m is None:
            return CacheError(f"{where}: {_first_line(e)}")
        bucket = self.root.split("/", 1)[0]
        if m[1] in _AWS_AUTH_ERRORS:
            return CacheError(
                f"{where}: bucket {bucket}: access denied ({m[1]} during {m[2]}); check the credentials in "
                "AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY / AWS_SESSION_TOKEN"
            )
        return CacheError(f"{where}: bucket {bucket}: {m[1]} during {m[2]} ({_first_line(e)})")

    def entry_uri(self, stage: str, key: str) -> str:
        """``<root>/<stage>/<key[:2]>/<key>`` in the scheme the cache was opened with."""
        return self._scheme + self._dir(stage, key)

    def _load(self, stage: str, key: str, d: str) -> tuple[Manifest | None, str | None]:
        """(manifest, None) when complete; (None, reason) when present but bad; (None, None) when absent."""
        try:
            with self.fs.open_input_stream(f"{d}/{MANIFEST}") as f:
                text = f.read().decode()
        except FileNotFoundError:
            # Without directory renames an upload may be in progress: no manifest simply means absent.
            if self.atomic_dirs and self.fs.get_file_info(d).type != _ABSENT:
                return None, f"{MANIFEST}: missing (incomplete entry)"
            return None, None
        try:
            m = Manifest.from_json(text)
        except (ValueError, KeyError, TypeError) as e:
            return None, f"{MANIFEST}: unreadable ({e})"
        if (m.stage, m.key) != (stage, key):
            return None, f"{MANIFEST}: names {m.stage}/{m.key[:12]}, expected {stage}/{key[:12]}"
        return m, None

    def walk(self, d: str) -> list[pafs.FileInfo]:
        """Every file and directory under ``d`` (none when absent), never following a symlink: on a local disk a
        symlink is listed as itself, type ``Unknown`` (pyarrow's recursive listing would walk into its target)."""
        if not self.local:
            return self.fs.get_file_info(pafs.FileSelector(d, recursive=True, allow_not_found=True))
        out, stack = [], [d]
        while stack:
            try:
                it = os.scandir(stack.pop())
            except (FileNotFoundError, NotADirectoryError):
                continue
            with it:
                for e in it:
                    st = e.stat(follow_symlinks=False)
                    kind = _KINDS.get(stat.S_IFMT(st.st_mode), pafs.FileType.Unknown)  # a symlink is Unknown
                    if kind == pafs.FileType.Directory:
                        stack.append(e.path)
                    size = st.st_size if kind == pafs.FileType.File else None
                    out.append(pafs.FileInfo(e.path, kind, mtime_ns=st.st_mtime_ns, size=size))
        return out

    def _verify(self, m: Manifest, d: str) -> str | None:
        infos = self.walk(d)
        odd = sorted(i.path[len(d) + 1 :] for i in infos if i.type == pafs.FileType.Unknown)
        if odd:  # a symlink (to '/', say) or a special file: an entry holds its bytes itself
            return f"{odd[0]}: a symlink or special file, not a regular file"
        found = {i.path[len(d) + 1 :]: i.size for i in infos if i.type == pafs.FileType.File}
        found.pop(MANIFEST, None)
        for fe in m.files:
            if fe.path not in found:
                return f"{fe.path}: missing"
            if (size := found.pop(fe.path)) != fe.size:
                return f"{fe.path}: size {size} != {fe.size} in the manifest"
        if found:
            return f"{sorted(found)[0]}: not listed in the manifest"
        for fe in m.files:
            try:
                with self.fs.open_input_stream(f"{d}/{fe.path}") as f:
                    digest = _sha256(f)[0]
            except FileNotFoundError:
                return f"{fe.path}: missing"
            if digest != fe.sha256:
                return f"{fe.path}: sha256 {digest[:12]} != {fe.sha256[:12]} in the manifest"
        return None

    def _discard(self, d: str, key: str) -> None:
        """Move an entry aside, then delete it; a concurrent process may have removed it already."""
        trash = d
        with contextlib.suppress(FileNotFoundError):
            if self.atomic_dirs:
                trash = f"{d.rsplit('/', 1)[0]}/.trash-{key[:12]}-{uuid.uuid4().hex}"
                self.fs.move(d, trash)
            else:
                self.fs.delete_file(f"{d}/{MANIFEST}")  # the entry vanishes at once, like a rename
        with contextlib.suppress(FileNotFoundError):
            self.fs.delete_dir(trash)

    def lookup(self, stage: str, key: str, verify: bool = True, use: bool = True) -> Manifest | None:
        """The entry's manifest, or None when absent; a bad entry is reported, moved aside and treated as absent.
        ``verify``: re-hash its files (else only the manifest is checked); ``use``: a hit records its last use (a
        plan's lookups don't)."""
        self.last_invalid = []
        d = self._dir(stage, key)
        try:
            m, bad = self._load(stage, key, d)
            if m is not None and verify:
                bad = self._verify(m, d)
            if bad is None:
                if m is not None and use:
                    self.touch(stage, key)
                return m
            self.last_invalid.append((stage, key, bad))
            log.warning("cache %s/%s: %s; moving the entry aside to recompute (%s)", stage, key[:12], bad,
                        self._scheme + d)  # fmt: skip
            self._discard(d, key)
        except OSError as e:
            raise self._store_error(e, f"stage {stage} key {key[:12]}: lookup in cache {self.uri}") from None
        return None

    def used_marker(self, stage: str, key: str) -> str:
        """Path of the entry's "last used" marker: outside the entry (a file in it would fail verification)."""
        self._dir(stage, key)  # validates both names
        return f"{self.root}/{stage}/{USED_DIR}/{key}"

    def touch(self, stage: str, key: str, when: float | None = None) -> None:
        """Record a use of the entry (best effort: a read-only or flaky store never fails a lookup)."""
        marker, text = self.used_marker(stage, key), repr(time.time() if when is None else when).encode()
        try:
            try:
                with self.fs.open_output_stream(marker) as f:
                    f.write(text)
            except FileNotFoundError:  # the stage's first marker
                self.fs.create_dir(marker.rsplit("/", 1)[0], recursive=True)
                with self.fs.open_output_stream(marker) as f:
                    f.write(text)
        except (OSError, pa.ArrowException) as e:
            log.debug("cache %s/%s: cannot record its use: %s", stage, key[:12], e)

    def _write_manifest(self, d: str, m: Manifest) -> None:
        with self.fs.open_output_stream(f"{d}/{MANIFEST}") as f:
            f.write(m.to_json().encode())

    def _upload(self, src: Path, dst: str) -> tuple[str, int]:
        if not self._dirless:
            self.fs.create_dir(dst.rsplit("/", 1)[0], recursive=True)
        with open(src, "rb") as fin, self.fs.open_output_stream(dst) as fout:
            return _sha256(fin, fout)

    def _move(self, src: str, dst: str) -> bool:
        """Rename ``src`` onto ``dst``; False when another writer's entry is there."""
        # LocalFileSystem.move is rename(2): ENOTEMPTY on a non-empty destination, so it never merges into or
        # replaces a published entry (it always holds MANIFEST.json); only an empty leftover dir is replaced.
        try:
            self.fs.move(src, dst)
            return True
        except OSError:
            if self.fs.get_file_info(dst).type == _ABSENT:
                raise
            return False

    def publish(
        self,
        stage: str,
        key: str,
        src_dir: Path,
        *,
        config: dict,
        upstream: dict[str, str],
        data_fingerprint: str,
        version: str,
        scene: str | None = None,
        run_id: str | None = None,
        extra: dict | None = None,
        code: dict | None = None,
        base: str | None = None,
        replace: bool = False,
    ) -> Manifest:
        """Copy ``src_dir`` into the entry for ``key`` atomically; if another writer won, return its manifest.

        ``code`` is the stage's code fingerprint (its ``digest`` enters the key); ``replace`` puts this output in place
        of an existing entry of the same key (a forced recompute: ``cache.reuse=none``, ``gdwm regress``). An I/O
        error (a full disk, a lost mount) is a ``CacheError`` naming the entry."""
        d = self._dir(stage, key)
        try:
            return self._publish(stage, key, src_dir, d, config, upstream, data_fingerprint, version, scene, run_id,
                                 extra, code, base, replace)  # fmt: skip
        except OSError as e:  # pyarrow's messages name no path
            raise self._store_error(e, f"stage {stage} key {key[:12]}: could not write {self._scheme + d}") from e

    def _publish(self, stage, key, src_dir, d, config, upstream, data_fingerprint, version, scene, run_id, extra,
                 code, base, replace) -> Manifest:  # fmt: skip
        expected = cache_key(stage, version, config, upstream, data_fingerprint, scene, code and code["digest"])
        if key != expected:
            raise CacheError(f"stage {stage} key {key[:12]}: != cache_key() of the given inputs ({expected[:12]})")
        files = _scan(stage, key, Path(src_dir))
        if replace:
            self.invalidate(stage, key)
        elif not self.atomic_dirs and (theirs := self.lookup(stage, key)) is not None:
            return theirs
        if not self._owned:  # the first entry marks the root as gdwm's; a root holding anything else is refused
            from gdwm.owned import NotOurs, own_cache

            try:
                own_cache(self, create=True)
            except NotOurs as e:
                raise CacheError(f"stage {stage} key {key[:12]}: {e}") from None
            self._owned = True
        parent = d.rsplit("/", 1)[0]
        work = f"{parent}/.tmp-{key[:12]}-{uuid.uuid4().hex}" if self.atomic_dirs else d
        if not self.atomic_dirs:
            # objects an interrupted publish left (no manifest): one the new output lacks would fail its verification
            self.fs.delete_dir_contents(d, missing_dir_ok=True)
        if not self._dirless:
            self.fs.create_dir(work, recursive=True)
        committed = False
        try:
            entries = tuple(FileEntry(rel, *self._upload(src, f"{work}/{rel}")) for rel, src in files)
            cfg, ext = json.loads(canonical_json(config)), json.loads(canonical_json(extra or {}))
            m = Manifest(
                key, stage, version, cfg, dict(upstream), data_fingerprint, scene, entries, run_id, time.time(), ext,
                json.loads(canonical_json(code)) if code is not None else None, base,
            )  # fmt: skip
            self._write_manifest(work, m)  # last: only now is the entry complete
            committed = True
            if not self.atomic_dirs:
                self._index_base(m)
                return m
            for _ in range(3):
                if (theirs := self.lookup(stage, key)) is not None:
                    return theirs
                if self._move(work, d):
                    self._index_base(m)
                    return m
            raise CacheError(f"stage {stage} key {key[:12]}: {self._scheme + d}: still contended after 3 attempts")
        except BaseException:
            if not self.atomic_dirs and not committed:
                # best effort (the store may be what failed): unremoved objects stay invisible without a manifest
                with contextlib.suppress(OSError):
                    self._discard(d, key)
            raise
        finally:
            if self.atomic_dirs:
                with contextlib.suppress(FileNotFoundError):
                    self.fs.delete_dir(work)

    def _base_dir(self, stage: str, base: str) -> str:
        self._dir(stage, base)  # validates both
        return f"{self.root}/{stage}/.bases/{base}"

    def _index_base(self, m: Manifest) -> None:
        """Best effort: an entry missing from the index is only invisible to ``lookup_base``."""
        if m.base is None or m.base == m.key:
            return
        with contextlib.suppress(OSError):
            d = self._base_dir(m.stage, m.base)
            if not self._dirless:
                self.fs.create_dir(d, recursive=True)
            with self.fs.open_output_stream(f"{d}/{m.key}") as f:
                f.write(b"")

    def lookup_base(self, stage: str, base: str, verify: bool = True, use: bool = True) -> Manifest | None:
        """The newest complete entry of the code-free key ``base``: any code's (an entry written before code was part
        of the key has key == base). Index files of entries gone (gc, invalidate) are dropped."""
        d = self._base_dir(stage, base)
        try:
            infos = self.fs.get_file_info(pafs.FileSelector(d, allow_not_found=True))
        except OSError as e:
            raise self._store_error(e, f"stage {stage} base {base[:12]}: lookup in cache {self.uri}") from None
        keys = {i.base_name for i in infos if _KEY_RE.fullmatch(i.base_name)} | {base}
        found = []
        for key in keys:
            try:
                m, _ = self._load(stage, key, self._dir(stage, key))
            except OSError as e:
                raise self._store_error(e, f"stage {stage} key {key[:12]}: lookup in cache {self.uri}") from None
            if m is not None:
                found.append(m)
            elif key != base:
                with contextlib.suppress(OSError):
                    self.fs.delete_file(f"{d}/{key}")
        for m in sorted(found, key=lambda m: m.created_at, reverse=True):
            if (hit := self.lookup(stage, m.key, verify, use)) is not None:
                return hit
        return None

    def materialize(self, manifest: Manifest) -> Path:
        """A local directory with the entry's files: the entry itself locally, else a verified download into
        ``$GDWM_LOCAL_CACHE`` (default ``~/.cache/gdwm``) under ``<stage>/<key>``."""
        m, d = manifest, self._dir(manifest.stage, manifest.key)
        if self.local:
            return Path(d)
        dest = local_dir() / m.stage / m.key
        if (dest / MANIFEST).is_file() and (dest / MANIFEST).read_text() == m.to_json():
            return dest
        tmp = dest.parent / f".tmp-{m.key[:12]}-{uuid.uuid4().hex}"
        try:
            tmp.mkdir(parents=True)
            for fe in m.files:
                target = tmp / fe.path
                if not target.resolve().is_relative_to(tmp.resolve()):  # FileEntry refuses such paths already
                    raise CacheError(f"stage {m.stage} key {m.key[:12]}: {fe.path}: outside the entry")
                target.parent.mkdir(parents=True, exist_ok=True)
                try:
                    with self.fs.open_input_stream(f"{d}/{fe.path}") as fin, open(target, "wb") as fout:
                        digest = _sha256(fin, fout)[0]
                except OSError as e:
                    raise self._store_error(
                        e, f"stage {m.stage} key {m.key[:12]}: {fe.path}: download from cache {self.uri}"
                    ) from None
                if digest != fe.sha256:
                    raise CacheError(
                        f"stage {m.stage} key {m.key[:12]}: {fe.path}: downloaded sha256 "
                        f"{digest[:12]} != {fe.sha256[:12]} in the manifest"
                    )
            (tmp / MANIFEST).write_text(m.to_json())
            if dest.exists():  # a copy of an older publish of this key
                stale = dest.parent / f".trash-{m.key[:12]}-{uuid.uuid4().hex}"
                os.rename(dest, stale)
                shutil.rmtree(stale)
            try:
                os.rename(tmp, dest)
            except OSError:
                if not (dest / MANIFEST).is_file():  # a concurrent download won: use that one
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return dest

    def _ls(self, path: str) -> list[pafs.FileInfo]:
        infos = self.fs.get_file_info(pafs.FileSelector(path, allow_not_found=True))
        return [i for i in infos if i.type == pafs.FileType.Directory and not i.base_name.startswith(".")]

    def entries(self, stage: str | None = None) -> list[Manifest]:
        """Every complete manifest (not verified), of one stage or all, ordered by stage then creation time."""
        out = []
        try:
            stages = (
                [stage] if stage else [i.base_name for i in self._ls(self.root) if _STAGE_RE.fullmatch(i.base_name)]
            )
            for s in stages:
                for shard in self._ls(f"{self.root}/{s}"):
                    for e in self._ls(shard.path):
                        # names from a listing, checked as names: never a path built from what a store returned
                        if not _KEY_RE.fullmatch(e.base_name) or shard.base_name != e.base_name[:2]:
                            continue
                        if (m := self._load(s, e.base_name, self._dir(s, e.base_name))[0]) is not None:
                            out.append(m)
        except OSError as e:
            raise self._store_error(
                e, f"cache {self.uri}: listing the entries" + (f" of stage {stage}" if stage else "")
            ) from None
        return sorted(out, key=lambda m: (m.stage, m.created_at, m.key))

    def invalidate(self, stage: str, key: str) -> bool:
        """Remove an entry; False when there was none."""
        d = self._dir(stage, key)
        try:
            if self.fs.get_file_info(d).type == _ABSENT:
                return False
            self._discard(d, key)
        except OSError as e:
            raise self._store_error(e, f"stage {stage} key {key[:12]}: invalidate in cache {self.uri}") from None
        return True


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]
