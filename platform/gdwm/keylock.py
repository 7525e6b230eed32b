"""One computer per cache key: a lease-based lock kept next to the cache, so two drivers on one workdir (or one
shared cache) never compute the same stage key twice, never open two MLflow runs for it and never write one
checkpoint directory together. The second driver waits for the first one's entry and reuses it.

Layout: ``<cache root>/.locks/<scope>/<key>/<claim id>.json`` (``scope`` is a stage name, or ``launch``), each
file ``{"owner": "<host>:<pid>:<start time>", "beat": <unix time>}``.

Protocol, through nothing but ``pyarrow.fs`` writes, deletes and listings (so it is the same on a local disk, a
shared volume and an object store, where no exclusive create exists):

1. wait until the key's directory holds no live claim (polling);
2. write our own claim, then list the directory: if ours is the only live claim we hold the lock; otherwise
   delete ours and go back to 1 after a random pause (two claimants that see each other both back off).

Two claimants cannot both win: a claimant wins only if its listing, taken after its own write, shows no other
claim, so the later of two writes always lists the earlier one. A claim is live while its owner renews ``beat``
(every ``BEAT_S``) and, for an owner on this host, while its process runs; a claim whose owner died (same host) or
whose beat is older than ``STALE_S`` (another host: clocks are assumed within ``STALE_S`` of each other) is stale,
deleted by whoever sees it; so is a claim that does not parse, or whose beat is not a finite time within ``STALE_S``
of now (claims are written whole, renamed into place or in one PUT, so a torn one is never one being written).
Written here because pyarrow.fs has no lock and a lock library (filelock, portalocker) covers local files only, not
the object stores the cache runs on.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import random
import threading
import time
import uuid
from collections.abc import Callable

import pyarrow.fs as pafs

from gdwm.cache import RENAMES_DIRS, Cache
from gdwm.tracking.owner import owner_is_alive, parse_owner, process_owner

log = logging.getLogger(__name__)

BEAT_S = 10.0
"""How often a holder renews its claim."""
STALE_S = 120.0
"""A claim not renewed for this long is abandoned (its holder's host died, or its process hangs)."""
POLL_S = 0.5
"""How often a waiter looks at the key again (it backs off to ``4 * POLL_S``)."""


def parse_claim(data: bytes) -> tuple[str, float] | None:
    """``(owner, beat)`` of a claim file; None for anything else (torn, garbage, a non-finite time): a claim is
    written whole (renamed into place, or one PUT), so one that does not parse is stale, never one being written."""
    try:
        rec = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("owner"), str):
        return None
    beat = rec.get("beat")
    if isinstance(beat, bool) or not isinstance(beat, int | float) or not math.isfinite(beat):
        return None
    return rec["owner"], float(beat)


class KeyLock:
    """``with KeyLock(cache, scope, key, on_wait=...):`` holds the key's lock; ``on_wait(owner)`` is called once
    when another live holder makes this one wait."""

    def __init__(self, cache: Cache, scope: str, key: str, on_wait: Callable[[str], None] | None = None):
        cache._dir(scope, key)  # the same name rules as an entry: no path tricks through scope or key
        self.cache = cache
        self.fs = cache.fs
        self.dir = f"{cache.root}/.locks/{scope}/{key}"
        self.where = f"{scope} {key[:12]}"
        self.owner = process_owner()
        self.claim = f"{self.dir}/{time.time_ns():020d}-{uuid.uuid4().hex[:12]}.json"
        self.on_wait = on_wait
        self.waited = 0.0
        """Seconds spent waiting for another holder."""
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None

    # ---- claims ------------------------------------------------------------------------------------------------
    def _write(self) -> None:
        data = json.dumps({"owner": self.owner, "beat": time.time()}).encode()
        if self.fs.type_name not in RENAMES_DIRS:  # an object store's PUT is atomic: no reader sees half a claim
            with self.fs.open_output_stream(self.claim) as f:
                f.write(data)
            return
        # written aside and renamed into place, so a claim that does not parse is never one being written
        part = f"{self.claim}.{uuid.uuid4().hex[:8]}.part"
        with self.fs.open_output_stream(part) as f:
            f.write(data)
        self.fs.move(part, self.claim)

    def _others(self) -> list[str]:
        """Owners of the live claims other than ours; stale ones are deleted on the way."""
        infos = self.fs.get_file_info(pafs.FileSelector(self.dir, allow_not_found=True))
        live = []
        for i in infos:
            if i.path == self.claim or not i.base_name.endswith(".json"):
                continue
            try:
                with self.fs.open_input_stream(i.path) as f:
                    rec = parse_claim(f.read())
            except FileNotFoundError:
                continue  # released while we looked
            if rec is None or self._stale(*rec):
                log.info("lock %s: removing the stale claim %s (%s)", self.where, i.base_name,
                         f"of {rec[0]}" if rec else "malformed")  # fmt: skip
                with contextlib.suppress(FileNotFoundError):
                    self.fs.delete_file(i.path)
                continue
            live.append(rec[0])
        return live

    @staticmethod
    def _stale(owner: str, beat: float) -> bool:
        if parse_owner(owner) is not None and not owner_is_alive(owner):
            return True  # its process on this host is gone: no need to wait out STALE_S
        return not -STALE_S < time.time() - beat <= STALE_S  # not renewed, or a beat from the future

    def _renew(self) -> None:
        """Renew every ``BEAT_S``. A renewal that fails (a full disk, a lost mount) leaves the holder computing; it is
        a warning only once the claim is half way to stale, when another driver may soon take the key over: a
        shorter outage is the cause some other line reports already (the stage that could not publish, the store
        that could not be written), and saying it again every beat would bury that line."""
        renewed, warned = time.monotonic(), False
        while not self._stop.wait(BEAT_S):
            try:
                self._write()
                renewed, warned = time.monotonic(), False
            except OSError as e:
                msg = self.cache._store_error(
                    e, f"lock {self.where}: could not renew the claim in cache {self.cache.uri}"
                )
                late = time.monotonic() - renewed >= STALE_S / 2
                log.log(logging.WARNING if late and not warned else logging.INFO, "%s", msg)
                warned |= late

    # ---- acquire / release -------------------------------------------------------------------------------------
    def acquire(self) -> None:
        """Wait for the lock; a store that cannot be reached is a CacheError naming the lock and the cache."""
        try:
            self._acquire()
        except OSError as e:  # pyarrow's messages name no URI
            where = f"lock {self.where}: could not take it in cache {self.cache.uri}"
            raise self.cache._store_error(e, where) from None

    def _acquire(self) -> None:
        if not self.cache._dirless:  # an object store needs no directory (creating one is a request of its own)
            self.fs.create_dir(self.dir, recursive=True)
        start, told, pause = time.monotonic(), False, POLL_S
        while True:
            others = self._others()
            if not others:
                self._write()
                others = self._others()
                if not others:
                    break
                with contextlib.suppress(FileNotFoundError):
                    self.fs.delete_file(self.claim)
            if not told and self.on_wait is not None and others:
                self.on_wait(others[0])
                told = True
            time.sleep(pause * (1 + random.random()))
            pause = min(pause * 1.5, 4 * POLL_S)
        self.waited = time.monotonic() - start
        self._stop.clear()
        self._beat = threading.Thread(target=self._renew, name=f"gdwm-lock-{self.where}", daemon=True)
        self._beat.start()

    def release(self) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join(timeout=5)
            self._beat = None
        with contextlib.suppress(FileNotFoundError, OSError):
            self.fs.delete_file(self.claim)

    def __enter__(self) -> KeyLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
