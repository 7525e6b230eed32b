"""The per-key lock (gdwm.keylock) and the sqlite store's one-writer lock, across real processes."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import socket
import threading
import time
from pathlib import Path

import psutil
import pytest

from gdwm import keylock
from gdwm.cache import Cache
from gdwm.keylock import KeyLock
from gdwm.tracking.backend import TrackingBackend

KEY = "ab" * 32


def _contend(root: str, log: str, barrier, rounds: int) -> None:
    cache = Cache(root)
    barrier.wait()
    for _ in range(rounds):
        with KeyLock(cache, "diffusion", KEY):
            with open(log, "a") as f:
                f.write("enter\n")
            time.sleep(0.02)
            with open(log, "a") as f:
                f.write("leave\n")


def test_processes_never_hold_one_key_together(tmp_path, monkeypatch):
    monkeypatch.setattr(keylock, "POLL_S", 0.02)  # forked children inherit it
    ctx = mp.get_context("fork")
    barrier = ctx.Barrier(4)
    log = tmp_path / "log"
    procs = [ctx.Process(target=_contend, args=(str(tmp_path / "c"), str(log), barrier, 3)) for _ in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0, 0, 0]
    lines = log.read_text().split()
    assert len(lines) == 24
    assert lines == ["enter", "leave"] * 12  # never two holders between an enter and its leave
    assert list((tmp_path / "c" / ".locks" / "diffusion" / KEY).iterdir()) == []  # every claim released


def _claim(root: Path, owner: str, beat: float) -> Path:
    d = root / ".locks" / "lora" / KEY
    d.mkdir(parents=True, exist_ok=True)
    p = d / "00000000000000000001-deadclaim.json"
    p.write_text(json.dumps({"owner": owner, "beat": beat}))
    return p


def test_a_dead_holder_on_this_host_is_taken_over_at_once(tmp_path):
    proc = mp.get_context("fork").Process(target=time.sleep, args=(0,))
    proc.start()
    proc.join()
    stale = _claim(tmp_path, f"{socket.gethostname()}:{proc.pid}:1.00", time.time())
    seen = []
    t0 = time.monotonic()
    with KeyLock(Cache(tmp_path), "lora", KEY, on_wait=seen.append):
        assert not stale.exists()
    assert seen == [] and time.monotonic() - t0 < 5


def test_a_holder_elsewhere_blocks_until_its_beat_goes_stale(tmp_path, monkeypatch):
    monkeypatch.setattr(keylock, "STALE_S", 1.5)
    other = _claim(tmp_path, "node-7:4242:1718000000.00", time.time())
    seen = []
    t0 = time.monotonic()
    with KeyLock(Cache(tmp_path), "lora", KEY, on_wait=seen.append) as lock:
        waited = time.monotonic() - t0
        assert not other.exists()
    assert seen == ["node-7:4242:1718000000.00"]  # told once who it waited for
    assert 1.0 < waited < 10 and lock.waited == pytest.approx(waited, abs=0.5)


@pytest.mark.parametrize(
    "claim",
    [
        b'{"owner": "node-7:4242:1718000000.00", "beat": NaN}',  # a buggy writer: never older than STALE_S
        b'{"owner": "node-7:4242:1718000000.00", "beat": Infinity}',
        b'{"owner": "node-7:4242:1718000000.00", "beat": 1e300}',  # a beat from the far future
        b'{"owner": "node-7:4242:1718000000.00", "beat": "soon"}',
        b'{"owner": 7, "beat": 1}',
        b"[1, 2]",
        b'{"owner": "node-7:4242:17180',  # torn
        b"\x00\xff\xfe",
    ],
)
def test_a_claim_that_does_not_parse_or_has_no_finite_time_is_stale(tmp_path, claim):
    d = tmp_path / ".locks" / "lora" / KEY
    d.mkdir(parents=True)
    (d / "00000000000000000001-badclaim.json").write_bytes(claim)
    seen, held = [], threading.Event()

    def take() -> None:
        with KeyLock(Cache(tmp_path), "lora", KEY, on_wait=seen.append):
            held.set()

    taker = threading.Thread(target=take, daemon=True)  # a claim wrongly taken as live would block it for good
    taker.start()
    assert held.wait(10), f"still waiting for the claim {claim!r}"
    taker.join(10)
    assert seen == [] and list(d.iterdir()) == []  # the bad claim deleted, ours released


def test_scope_and_key_are_checked_like_cache_entries(tmp_path):
    with pytest.raises(ValueError, match=r"stage name '\.\./x'"):
        KeyLock(Cache(tmp_path), "../x", KEY)
    with pytest.raises(ValueError, match="is not a sha256 hex digest"):
        KeyLock(Cache(tmp_path), "lora", "../../etc")


def _open_store(uri: str, barrier, out) -> None:
    barrier.wait()
    try:
        b = TrackingBackend(uri, "gdwm")
        run = b.create_run("r", {"k": "v"})
        b.end_run(run)
        out.put("ok")
    except Exception as e:  # reported to the test, which names it
        out.put(f"{type(e).__name__}: {e}")


def test_drivers_initialising_one_fresh_sqlite_store_together_both_succeed(tmp_path):
    # Without the store's file lock this fails most times: "duplicate column name: step" or
    # "Online migration expected to match one row" from the racing alembic migrations.
    ctx = mp.get_context("fork")
    n = 3
    barrier, out = ctx.Barrier(n), ctx.Queue()
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    procs = [ctx.Process(target=_open_store, args=(uri, barrier, out)) for _ in range(n)]
    for p in procs:
        p.start()
    results = [out.get(timeout=180) for _ in range(n)]
    for p in procs:
        p.join(30)
    assert results == ["ok"] * n
    assert len(TrackingBackend(uri, "gdwm").search_runs("tags.k = 'v'")) == n


def test_a_held_store_lock_names_its_holder_and_is_given_up_after_the_timeout(tmp_path):
    """A hung or stopped gdwm holds mlflow.db.lock: `gdwm status` says it waits and for whom, then gives up after
    tracking.lock_timeout_s with one line naming the lock and the holder's pid (exit 1), instead of waiting forever."""
    import subprocess
    import sys

    from filelock import FileLock

    TrackingBackend(f"sqlite:///{tmp_path}/mlflow.db", "gdwm")
    with FileLock(f"{tmp_path}/mlflow.db.lock"):  # this process stands in for the stuck driver
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "gdwm", "status", f"workdir={tmp_path}", "tracking.lock_timeout_s=3"],
                           capture_output=True, text=True, timeout=120)  # fmt: skip
        took = time.monotonic() - t0
    lines = r.stderr.strip().splitlines()
    holder = f"pid {os.getpid()} ({psutil.Process().name()})"  # read from /proc/locks
    assert r.returncode == 1 and r.stdout == ""
    assert (
        lines[0]
        == f"gdwm: waiting for the tracking store's lock {tmp_path}/mlflow.db.lock, held by {holder} (up to 3 s)"
    )
    assert lines[-1] == (
        f"gdwm status: TrackingError: tracking store {tmp_path}/mlflow.db: its lock mlflow.db.lock is still held by "
        f"{holder} after 3 s; stop that process if it hangs, or raise tracking.lock_timeout_s"
    )
    assert took < 60


def test_a_renewal_that_keeps_failing_warns_once_half_way_to_stale(tmp_path, monkeypatch, caplog):
    """A full disk under a holder: each failed renewal is an info line, one warning once the claim is half way to
    stale (another driver may take the key over), not a line per beat repeating the cause the run reports."""
    import logging

    monkeypatch.setattr(keylock, "BEAT_S", 0.01)
    monkeypatch.setattr(keylock, "STALE_S", 0.4)
    records: list[logging.LogRecord] = []
    enough = threading.Event()

    class Collect(logging.Handler):
        def emit(self, record):
            records.append(record)
            if sum(r.levelno == logging.WARNING for r in records) and len(records) >= 40:
                enough.set()

    handler = Collect(logging.INFO)
    caplog.set_level(logging.INFO, logger=keylock.log.name)
    keylock.log.addHandler(handler)
    try:
        lock = KeyLock(Cache(tmp_path), "lora", KEY)
        with lock:

            def full() -> None:
                raise OSError(28, "No space left on device")

            start = time.monotonic()
            monkeypatch.setattr(lock, "_write", full)
            assert enough.wait(30)
            took = time.monotonic() - start
    finally:
        keylock.log.removeHandler(handler)
    levels = [r.levelno for r in records]
    assert levels.count(logging.WARNING) == 1 and took >= 0.2
    first = levels.index(logging.WARNING)
    assert set(levels[:first]) == {logging.INFO} and first >= 5  # the beats before it: info only
    assert all(f"lock lora {KEY[:12]}: could not renew the claim in cache" in r.getMessage() for r in records)
    assert "No space left on device" in records[first].getMessage()
