"""`gdwm cache ls|gc|invalidate` on a real cache and a real MLflow store (sqlite): what gc keeps (zoo aliases and their
upstream, regression baselines, running runs, the grace period), what it frees (measured on the filesystem), the
"last used" markers cache hits leave, and the exit-2 messages of bad limits."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import time
from pathlib import Path

import pytest
from pyarrow.fs import FileSelector, FileType

from gdwm.cache import Cache, Manifest, cache_key
from gdwm.cli import main
from gdwm.housekeeping import (
    Limits,
    UsageError,
    gc,
    parse_age,
    parse_gc_args,
    parse_size,
    references,
    scan,
)
from gdwm.tracking import TrackingBackend
from gdwm.zoo.registry import lineage_tags

DATA = "toy@seed0"
DAY = 86400.0


def publish(
    cache: Cache,
    stage: str,
    tmp: Path,
    value: int,
    nbytes: int,
    scene: str | None = None,
    upstream: dict[str, str] | None = None,
    run_id: str | None = None,
    code: dict | None = None,
) -> Manifest:
    """An entry of ``stage`` whose config is ``{"value": value}``, holding ``nbytes`` bytes of payload."""
    config, upstream = {"value": value}, upstream or {}
    key = cache_key(stage, "1", config, upstream, DATA, scene, code and code["digest"])
    src = tmp / f"src-{key[:12]}"
    (src / "sub").mkdir(parents=True)
    (src / "weights.bin").write_bytes(os.urandom(nbytes))
    (src / "sub" / "log.txt").write_text(f"{stage} {value} {scene}\n")
    return cache.publish(
        stage, key, src, config=config, upstream=upstream, data_fingerprint=DATA, version="1", scene=scene,
        run_id=run_id, code=code,
    )  # fmt: skip


def backdate(cache_root: Path, m: Manifest, days: float) -> None:
    """Rewrite the entry's manifest as if it had been published ``days`` ago."""
    path = entry_dir(cache_root, m) / "MANIFEST.json"
    d = json.loads(path.read_text())
    text = path.read_text().replace(repr(d["created_at"]), repr(round(d["created_at"] - days * DAY, 3)))
    assert text != path.read_text()
    path.write_text(text)


def tree_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def entry_dir(cache_root: Path, m: Manifest) -> Path:
    return cache_root / m.stage / m.key[:2] / m.key


def keys_on_disk(cache: Cache) -> set[str]:
    return {m.key for m in cache.entries()}


def cells(line: str) -> list[str]:
    """A rich table row (header ┃, body │) as stripped cells."""
    return [c.strip() for c in re.split("[│┃]", line)[1:-1]]


def table(out: str) -> dict[str, list[str]]:
    """First cell -> the row's cells, for every body row of the tables in ``out``."""
    return {c[0]: c for c in (cells(ln) for ln in out.splitlines() if ln.startswith("│")) if c}


class Store:
    """A workdir as ``gdwm`` sees it: ``cache/`` and the MLflow store ``mlflow.db`` with its artifacts."""

    def __init__(self, work: Path):
        self.work = work
        self.cache = Cache(work / "cache")
        self.uri = f"sqlite:///{work.resolve()}/mlflow.db"
        self._backend: TrackingBackend | None = None

    @property
    def backend(self) -> TrackingBackend:
        if self._backend is None:
            art = str(self.work.resolve() / "mlartifacts")
            self._backend = TrackingBackend(self.uri, "gdwm", art, system_metrics_interval_s=0)
        return self._backend

    def run(self, name: str, tags: dict[str, str], status: str | None = "FINISHED", keys: dict | None = None) -> str:
        run_id = self.backend.create_run(name, tags)
        if keys is not None:
            self.backend.log_text(run_id, json.dumps(keys), "cache_keys.json")
        if status is not None:
            self.backend.end_run(run_id, status)
        return run_id

    def cli(self, capsys, *args: str) -> tuple[int, str, str]:
        capsys.readouterr()
        rc = main(["cache", *args, f"workdir={self.work}"])
        out, err = capsys.readouterr()
        return rc, out, err


@pytest.fixture
def store(tmp_path) -> Store:
    return Store(tmp_path / "w")


@pytest.fixture
def referenced(store, tmp_path):
    """Ten entries; five referenced by what protects them, the other five by nothing that does."""
    c, b = store.cache, store
    e = {}
    e["tok1"] = publish(c, "tok", tmp_path, 1, 3000)
    e["tok2"] = publish(c, "tok", tmp_path, 2, 5000)
    lora_run1 = b.run("lora-1", {"gdwm.kind": "stage", "gdwm.stage": "lora"})
    e["lora1"] = publish(c, "lora", tmp_path, 1, 7000, upstream={"tok": e["tok1"].key}, run_id=lora_run1)
    lora_run2 = b.run("lora-2", {"gdwm.kind": "stage", "gdwm.stage": "lora"})
    e["lora2"] = publish(c, "lora", tmp_path, 2, 11000, upstream={"tok": e["tok2"].key}, run_id=lora_run2)
    for name, scene, value in (("rec0", "s0", 1), ("rec1", "s1", 1), ("rec2", "s0", 2)):
        e[name] = publish(c, "recon", tmp_path, value, 2000 + 100 * value, scene=scene)
    running = b.run("eval-run", {"gdwm.kind": "stage", "gdwm.stage": "eval"}, status=None)
    e["eval1"] = publish(c, "eval", tmp_path, 1, 1500, run_id=running)
    e["eval2"] = publish(c, "eval", tmp_path, 2, 1700)
    e["eval3"] = publish(c, "eval", tmp_path, 3, 1900)
    b.backend.set_tags(running, {"gdwm.cache_key": e["eval1"].key})

    # zoo: version 1 (lora2) loses the candidate alias to version 2 (lora1, upstream tok1)
    for m, run_id in ((e["lora2"], lora_run2), (e["lora1"], lora_run1)):
        component = tmp_path / f"component-{m.key[:8]}"
        component.mkdir()
        (component / "w.bin").write_bytes(b"w")
        b.backend.register_component(
            run_id, "gdwm-lora", str(component), "v", lineage_tags("lora", m.key, m.upstream, {"nuinteract/avg": 40})
        )
    # a baseline naming rec1, an older baseline without cache_keys.json, a non-baseline regression run naming rec0,
    # a RUNNING trial naming eval3, a FINISHED one naming eval2
    regression = {"gdwm.kind": "regression", "gdwm.benchmark": "nightly"}
    baseline = b.run("regress-1", {**regression, "gdwm.baseline": "true"}, keys={"recon": [e["rec1"].key]})
    old = b.run("regress-0", {**regression, "gdwm.baseline": "true"})
    b.run("regress-2", regression, keys={"recon": [e["rec0"].key]})
    b.run("trial-a", {"gdwm.kind": "trial"}, status=None, keys={"eval": [e["eval3"].key]})
    b.run("trial-b", {"gdwm.kind": "trial"}, keys={"eval": [e["eval2"].key]})
    protected = {e[n].key for n in ("lora1", "tok1", "rec1", "eval1", "eval3")}
    return e, protected, old, baseline


def test_gc_keeps_exactly_what_is_referenced_and_frees_what_it_reports(store, referenced, capsys):
    e, protected, old_baseline, baseline = referenced
    root = store.work / "cache"
    doomed = [m for m in e.values() if m.key not in protected]
    assert len(doomed) == 5
    doomed_bytes = sum(tree_bytes(entry_dir(root, m)) for m in doomed)
    before = tree_bytes(root)

    # the dry run reports what the real one then does, and deletes nothing
    rc, out, err = store.cli(capsys, "gc", "--keep-last", "0", "--older-than=0s", "args.grace=0s", "--dry-run")
    assert rc == 0, err
    assert f"would delete 5 entries, {doomed_bytes} bytes (" in out
    for m in doomed:
        assert f"would delete {m.stage}/{m.key[:12]}" in out
    assert "kept 5 protected entries (alias: 2, baseline: 1, running: 2):" in out
    assert f"gdwm cache gc: warning: baseline run {old_baseline} (benchmark nightly) has no cache_keys.json" in err
    assert tree_bytes(root) == before and keys_on_disk(store.cache) == {m.key for m in e.values()}

    rc, out, err = store.cli(capsys, "gc", "--keep-last=0", "--older-than", "0s", "args.grace=0s")
    assert rc == 0, err
    assert f"deleted 5 entries, {doomed_bytes} bytes (" in out and "freed" in out
    assert keys_on_disk(store.cache) == protected
    assert before - tree_bytes(root) == doomed_bytes  # what it says it frees, measured
    assert not [p for p in root.rglob("*") if p.name.startswith((".tmp-", ".trash-"))]
    lines = {ln.strip() for ln in out.splitlines()}
    lora1, tok1, rec1 = e["lora1"].key[:12], e["tok1"].key[:12], e["rec1"].key[:12]
    assert f"lora/{lora1}: zoo gdwm-lora/2@candidate" in lines
    assert f"tok/{tok1}: zoo gdwm-lora/2@candidate (upstream)" in lines
    assert f"recon/{rec1}: baseline run {baseline[:12]} (nightly)" in lines

    rc, out, _ = store.cli(capsys, "gc", "--keep-last=0", "--older-than", "0s", "args.grace=0s")
    assert rc == 0 and "deleted 0 entries, 0 bytes" in out


def foreign_store(root: Path, layout: str) -> dict[str, bytes]:
    """Another tool's content-addressed store, untouched for 40 days; returns its files' bytes. ``oci``: an OCI image
    layout (``blobs/sha256/<64 hex>`` files); ``builds``: a build cache (``outputs/<2 hex>/<64 hex>/`` dirs)."""
    files = {"index.json": b'{"manifests": []}'}
    for i in range(4):
        blob = os.urandom(64 + i)
        digest = hashlib.sha256(blob).hexdigest()
        files[f"blobs/sha256/{digest}" if layout == "oci" else f"outputs/{digest[:2]}/{digest}/result.bin"] = blob
    old = time.time() - 40 * DAY
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    for p in [root, *root.rglob("*")]:
        os.utime(p, (old, old))
    return files


@pytest.mark.parametrize("layout", ["oci", "builds"])
def test_gc_and_invalidate_refuse_a_directory_gdwm_did_not_create(store, tmp_path, capsys, monkeypatch, layout):
    foreign = tmp_path / "store"
    files = foreign_store(foreign, layout)
    first = "blobs/sha256" if layout == "oci" else "index.json"
    top, _, digest = next(k for k in files if k != "index.json").split("/")[:3]
    for args in (["gc", "--older-than", "30d"], ["gc", "--keep-last", "0", "args.grace=0s"],
                 ["invalidate", f"args.stage={top}", f"args.key={digest[:12]}"]):  # fmt: skip
        rc, out, err = store.cli(capsys, *args, f"cache.uri={foreign}")
        assert (rc, err.strip()) == (2, (
            f"gdwm cache {args[0]}: cache.uri={foreign}: not a gdwm cache ({first} is not gdwm's, and there is "
            "no .gdwm-cache); gc and invalidate act only on a directory gdwm created, and deleted nothing"
        )), out  # fmt: skip
    assert {p.relative_to(foreign).as_posix(): p.read_bytes() for p in foreign.rglob("*") if p.is_file()} == files
    # a launch refuses it too, before anything runs (a typo'd cache.uri must not fill someone's directory)
    monkeypatch.setenv("GDWM_CONF_PATH", str(Path(__file__).parents[1] / "conf"))
    rc = main(["run", "--dry-run", "experiment=toy", f"workdir={store.work}", f"cache.uri={foreign}"])
    assert rc == 2 and f"not a gdwm cache ({first} is not gdwm's" in capsys.readouterr().err


def test_a_cache_of_an_older_gdwm_is_recognised_by_its_layout_and_marked(store, tmp_path, capsys):
    old, new = publish(store.cache, "lora", tmp_path, 1, 100), publish(store.cache, "lora", tmp_path, 2, 100)
    backdate(store.work / "cache", old, 40)
    marker = store.work / "cache" / ".gdwm-cache"
    assert json.loads(marker.read_text())["gdwm"] == "cache"  # written with the first entry
    marker.unlink()  # as an older gdwm left it
    rc, _, err = store.cli(capsys, "gc", "--older-than", "30d")
    assert rc == 0, err
    assert err.strip() == (
        f"gdwm cache: {store.work / 'cache'} has gdwm's layout but no .gdwm-cache (an older gdwm): marked it as a "
        "gdwm cache"
    )
    assert keys_on_disk(store.cache) == {new.key} and marker.is_file()
    # gdwm's layout but no manifest anywhere: not recognised
    fake = tmp_path / "fake"
    (fake / "lora" / "ab" / ("ab" + "0" * 62)).mkdir(parents=True)
    rc, _, err = store.cli(capsys, "gc", "--older-than", "30d", f"cache.uri={fake}")
    assert rc == 2 and "not a gdwm cache (no .gdwm-cache and no readable gdwm manifest in lora)" in err


def test_a_root_marked_by_another_process_between_the_marker_check_and_the_listing_is_ours(tmp_path):
    """Scene actors publish at once into a root that holds only gdwm's launch locks (a first launch that died before
    its first entry): one writes the marker after another looked for it and before that one lists the root. The
    listing shows the marker: the root is gdwm's (it was refused as 'not a gdwm cache (.gdwm-cache is not gdwm's')."""
    from gdwm.owned import CACHE_MARKER, cache_state, own_cache

    root = tmp_path / "cache"
    (root / ".locks" / "launch").mkdir(parents=True)
    cache = Cache(root)
    real = cache.fs.get_file_info

    def marked_meanwhile(arg):
        out = real(arg)
        if isinstance(arg, str) and arg.endswith(CACHE_MARKER):
            (root / CACHE_MARKER).write_text('{"gdwm": "cache"}')  # the other actor, right after our check
        return out

    fs = cache.fs
    cache.fs = type("RacingFS", (), {"get_file_info": staticmethod(marked_meanwhile), "__getattr__":
                                     lambda self, name: getattr(fs, name)})()  # fmt: skip
    assert cache_state(cache) == "marked"
    assert own_cache(cache, create=True) == "marked"


def test_a_symlink_in_an_entry_is_neither_sized_nor_followed_by_gc(store, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "big.bin").write_bytes(b"x" * 100_000)
    m = publish(store.cache, "lora", tmp_path, 1, 100)
    entry = entry_dir(store.work / "cache", m)
    size = tree_bytes(entry)
    (entry / "sub" / "stray").symlink_to(outside)
    assert [e.size for e in scan(store.cache).entries] == [size]
    r = gc(store.cache, store.uri, Limits(keep_last=0), grace=0)
    assert [e.key for e in r.deleted] == [m.key] and r.freed == size
    assert not entry.exists() and (outside / "big.bin").stat().st_size == 100_000


def test_grace_period_and_keep_last_keep_entries(store, referenced):
    e, protected, _, _ = referenced
    refs = references(store.uri, scan(store.cache).entries)
    assert set(refs.protect) == protected
    now = time.time()
    # every entry was just created: inside a 1h grace period nothing goes
    r = gc(store.cache, store.uri, Limits(keep_last=0, older_than=0.0, dry_run=True), grace=3600, now=now)
    assert r.deleted == [] and {x.key for x, _ in r.plan.kept} == {m.key for m in e.values()}
    assert {w for _, why in r.plan.kept for w, _ in why} >= {"grace", "alias", "baseline", "running"}
    # --keep-last 1 per stage and scene: eval keeps its newest (eval3, also protected), tok its newest (tok2) ...
    r = gc(store.cache, store.uri, Limits(keep_last=1, dry_run=True), grace=0, now=now + 10)
    by_recency = {}
    for m in e.values():
        by_recency.setdefault((m.stage, m.scene), []).append(m)
    newest = {max(ms, key=lambda m: (m.created_at, m.key)).key for ms in by_recency.values()}
    assert {x.key for x in r.deleted} == {m.key for m in e.values()} - newest - protected
    # --keep-last with --older-than: only what both select (nothing is older than a day)
    r = gc(store.cache, store.uri, Limits(keep_last=0, older_than=DAY, dry_run=True), grace=0, now=now + 10)
    assert r.deleted == []


def test_an_entry_looked_up_after_the_scan_is_not_deleted(store, tmp_path):
    c = store.cache
    hit, idle = publish(c, "lora", tmp_path, 1, 100), publish(c, "lora", tmp_path, 2, 100)
    assert c.lookup("lora", hit.key) == hit  # a driver's cache hit, "now"
    # gc planned 10 hours later sees both unused for 10h; deleting, it re-reads the markers against the clock
    r = gc(c, store.uri, Limits(older_than=3600.0), grace=3600, now=time.time() + 10 * 3600)
    assert {x.key for x in r.plan.delete} == {hit.key, idle.key}
    assert [x.key for x in r.skipped] == [hit.key] and [x.key for x in r.deleted] == [idle.key]
    assert keys_on_disk(c) == {hit.key}


def test_max_size_frees_least_recently_used_first(store, tmp_path, capsys):
    c = store.cache
    ms = [publish(c, "lora", tmp_path, v, 4000 + 1000 * v) for v in range(4)]
    for m in ms:
        backdate(store.work / "cache", m, 10)
    now = time.time()
    for m, hours_ago in zip(ms, (5, 1, 9, 3), strict=True):  # least recently used: ms[2], then ms[0]
        c.touch(m.stage, m.key, now - hours_ago * 3600)
    sizes = {m.key: tree_bytes(entry_dir(store.work / "cache", m)) for m in ms}
    total = sum(sizes.values())
    limit = total - sizes[ms[2].key] - 1  # one entry too many: the two least recently used go
    r = gc(c, store.uri, Limits(max_size=limit, dry_run=True), grace=0)
    assert [x.key for x in r.deleted] == [ms[2].key, ms[0].key]
    assert r.freed == sizes[ms[2].key] + sizes[ms[0].key]

    rc, out, err = store.cli(capsys, "gc", "--max-size", f"{limit}B", "args.grace=30m")
    assert rc == 0, err
    assert f"deleted 2 entries, {sizes[ms[2].key] + sizes[ms[0].key]} bytes" in out
    assert keys_on_disk(c) == {ms[1].key, ms[3].key}
    assert not (store.work / "cache" / "lora" / ".used" / ms[2].key).exists()  # marker gone too
    # the rest does not fit in 1 byte, but ms[1] was used 1h ago, inside a 2h grace period
    rc, out, err = store.cli(capsys, "gc", "--max-size=1", "args.grace=2h")
    assert rc == 0 and keys_on_disk(c) == {ms[1].key}
    assert f"lora/{ms[1].key[:12]}: used 1h ago (grace 2h)" in out
    assert "gdwm cache gc: still " in err and "over --max-size 1B" in err


def test_lookup_records_last_use_and_never_fails_on_the_marker(store, tmp_path):
    c = store.cache
    m = publish(c, "lora", tmp_path, 1, 100)
    marker = store.work / "cache" / "lora" / ".used" / m.key
    assert not marker.exists()  # publishing is not a use
    t0 = time.time()
    assert c.lookup("lora", m.key) == m
    assert t0 <= float(marker.read_text()) <= time.time()
    (e,) = scan(c).entries
    assert e.last_used == e.used_at == float(marker.read_text())
    marker.unlink()
    marker.mkdir()  # the marker cannot be written: the lookup still hits
    assert c.lookup("lora", m.key) == m
    marker.rmdir()
    assert c.lookup("lora", "0" * 64) is None and not (store.work / "cache" / "lora" / "00").exists()


@pytest.mark.parametrize("atomic_dirs", [True, False], ids=["rename", "object-store"])
def test_gc_on_a_remote_filesystem_leaves_an_upload_in_progress(tmp_path, atomic_dirs):
    cache = Cache("mock:///bucket/cache")  # pyarrow's in-memory filesystem; without renames it is what S3 gets
    cache.atomic_dirs = atomic_dirs
    ms = [publish(cache, "lora", tmp_path, v, 1000 * (v + 1)) for v in range(3)]
    assert cache.lookup("lora", ms[0].key) == ms[0]
    uploading = f"bucket/cache/lora/ab/ab{'0' * 62}"  # files arrive in place, the manifest comes last
    cache.fs.create_dir(uploading, recursive=True)
    with cache.fs.open_output_stream(f"{uploading}/weights.bin") as f:
        f.write(b"x" * 777)

    def sizes() -> dict[str, int]:
        infos = cache.fs.get_file_info(FileSelector("bucket/cache", recursive=True))
        return {i.path: i.size for i in infos if i.type == FileType.File}

    before = sizes()
    found = scan(cache)
    assert [(e.key, e.size) for e in sorted(found.entries, key=lambda e: e.manifest.config["value"])] == [
        (m.key, sum(v for k, v in before.items() if f"/{m.key}/" in k)) for m in ms
    ]
    used = {e.key: e.used_at for e in found.entries}
    assert found.entries[0].key == ms[0].key and used[ms[0].key] is not None  # its hit: the most recent use
    assert used[ms[1].key] is None and used[ms[2].key] is None
    assert [(x.kind, x.size) for x in found.leftovers] == [("incomplete", 777)]
    no_store = f"sqlite:///{tmp_path}/none.db"
    r = gc(cache, no_store, Limits(keep_last=0), grace=0)
    assert sorted(x.key for x in r.deleted) == sorted(m.key for m in ms) and r.leftovers_removed == []
    after = sizes()
    assert sum(before.values()) - sum(after.values()) == r.freed + len(repr(used[ms[0].key]))
    assert sorted(after) == ["bucket/cache/.gdwm-cache", f"{uploading}/weights.bin"] and cache.entries() == []
    assert not (tmp_path / "none.db").exists()  # no store: nothing is referenced, and none is created


def test_old_leftovers_are_removed_young_ones_kept(store, tmp_path, capsys):
    c = store.cache
    m = publish(c, "lora", tmp_path, 1, 100)
    shard = store.work / "cache" / "lora" / m.key[:2]
    young, old = shard / f".tmp-{m.key[:12]}-young", shard / f".trash-{m.key[:12]}-old"
    for d in (young, old):
        d.mkdir()
        (d / "part.bin").write_bytes(b"x" * 321)
    for p in (old / "part.bin", old):
        os.utime(p, (time.time() - 2 * DAY, time.time() - 2 * DAY))
    rc, out, err = store.cli(capsys, "gc", "--older-than", "1w")
    assert rc == 0, err
    assert "deleted 0 entries, 0 bytes" in out and "removed 1 leftovers (.trash), 321 bytes" in out
    assert young.is_dir() and not old.exists() and keys_on_disk(c) == {m.key}


def test_ls_summary_and_one_stage(store, referenced, tmp_path, capsys):
    e, _, _, _ = referenced
    code = {"digest": "c0de" * 16, "files": {}, "libraries": {}}
    coded = publish(store.cache, "lora", tmp_path, 3, 900, code=code)
    root = store.work / "cache"
    rc, out, err = store.cli(capsys, "ls")
    assert rc == 0, err
    rows = table(out)
    for stage in ("eval", "lora", "recon", "tok"):
        ms = [m for m in [*e.values(), coded] if m.stage == stage]
        nbytes = sum(tree_bytes(entry_dir(root, m)) for m in ms)
        assert rows[stage][1:2] == [str(len(ms))] and rows[stage][3] == str(nbytes), rows[stage]
    marker = (root / ".gdwm-cache").stat().st_size
    assert rows["total"][1] == "11" and rows["total"][3] == str(tree_bytes(root) - marker)
    # runs: lora1's and lora2's producers; zoo versions: both; protected: lora1
    assert rows["lora"][5:8] == ["2", "2", "1"]
    assert rows["recon"][5:8] == ["1", "0", "1"]  # the baseline names rec1; no zoo version; rec1 protected
    # eval1's running producer and the running trial naming eval3 (finished trials' artifacts are not read)
    assert rows["eval"][5:8] == ["2", "0", "2"]

    rc, out, err = store.cli(capsys, "ls", "args.stage=lora")
    assert rc == 0, err
    rows = table(out)
    lora1, lora2 = rows[e["lora1"].key[:12]], rows[e["lora2"].key[:12]]
    assert lora1[5:] == [e["lora1"].run_id[:12], "unknown", "gdwm-lora/2@candidate", "alias"]
    assert lora2[5:] == [e["lora2"].run_id[:12], "unknown", "gdwm-lora/1", ""]
    assert rows[coded.key[:12]][6] == "c0dec0dec0de"
    assert "lora: 3 entries" in out

    rc, _, err = store.cli(capsys, "ls", "args.stage=nope")
    assert rc == 2
    assert err.strip() == f"gdwm cache ls: args.stage=nope: no such stage in the cache {root.resolve()} " + (
        "(stages: eval, lora, recon, tok)"
    )


def test_an_upstream_per_scene_stage_is_protected_through_its_aggregate_key(store, tmp_path):
    c = store.cache
    scenes = {s: publish(c, "recon", tmp_path, 1, 500, scene=s) for s in ("s0", "s1")}
    other = publish(c, "recon", tmp_path, 2, 500, scene="s0")
    agg = cache_key("recon", "1", {"value": 1}, {f"scene:{s}": m.key for s, m in scenes.items()}, DATA)
    down = publish(c, "lora", tmp_path, 1, 500, upstream={"recon": agg})
    run_id = store.run("lora", {"gdwm.kind": "stage"})
    component = tmp_path / "component"
    component.mkdir()
    (component / "w.bin").write_bytes(b"w")
    store.backend.register_component(
        run_id, "gdwm-lora", str(component), "v", lineage_tags("lora", down.key, down.upstream, {})
    )
    refs = references(store.uri, scan(c).entries)
    assert set(refs.protect) == {down.key, scenes["s0"].key, scenes["s1"].key}
    assert other.key not in refs.zoo


def test_invalidate_removes_one_entry_and_its_checkpoints(store, tmp_path, capsys):
    c = store.cache
    m, keep = publish(c, "lora", tmp_path, 1, 100), publish(c, "lora", tmp_path, 2, 100)
    c.lookup("lora", m.key)
    steps = store.work / "checkpoints" / "lora" / m.key / "steps" / "step_000000001"
    steps.mkdir(parents=True)
    (steps / "state.pt").write_bytes(b"s")
    rc, out, err = store.cli(capsys, "invalidate", "args.stage=lora", f"args.key={m.key[:8]}")
    assert rc == 0, err
    assert out.startswith(f"removed lora/{m.key} (") and "discarded 1 checkpoint(s) of that key" in out
    assert keys_on_disk(c) == {keep.key} and not steps.exists()
    assert not (store.work / "cache" / "lora" / ".used" / m.key).exists()

    rc, _, err = store.cli(capsys, "invalidate", "args.stage=lora", f"args.key={m.key[:8]}")
    assert (rc, err.strip()) == (2, f"gdwm cache invalidate: args.key={m.key[:8]}: matches no entry of stage lora")
    rc, _, err = store.cli(capsys, "invalidate", "args.stage=lora", "args.key=abc")
    assert rc == 2
    assert err.strip() == "gdwm cache invalidate: args.key=abc: give the entry's key or a prefix of >= 8 hex characters"
    twin = store.work / "cache" / "lora" / keep.key[:2] / (keep.key[:8] + "f" * 56)  # an interrupted upload's dir
    twin.mkdir()
    rc, _, err = store.cli(capsys, "invalidate", "args.stage=lora", f"args.key={keep.key[:8]}")
    shown = ", ".join(sorted([keep.key[:16], twin.name[:16]]))
    assert (rc, err.strip()) == (
        2,
        f"gdwm cache invalidate: args.key={keep.key[:8]}: matches 2 entries of stage lora ({shown}); give more "
        "characters",
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "no limit given: pass --keep-last N (per stage and scene), --older-than AGE (e.g. 30d) and/or "
             "--max-size SIZE (e.g. 50GB); --dry-run shows what they would delete"),
        (["--dry-run"], "no limit given: pass --keep-last N (per stage and scene), --older-than AGE (e.g. 30d) "
                        "and/or --max-size SIZE (e.g. 50GB); --dry-run shows what they would delete"),
        (["--older-than", "30x"], "--older-than: '30x' is not an age: a number with a unit s, m, h, d or w (e.g. 30d)"),
        (["--keep-last", "-1"], "--keep-last: '-1' is not a count (an integer >= 0)"),
        (["--max-size=lots"], "--max-size: 'lots' is not a size: a number with a unit B, KB, MB, GB, TB (powers of "
                              "1000) or KiB, MiB, GiB, TiB (powers of 1024), e.g. 50GB"),
        (["--keep-last", "3", "--keep-last=4"], "--keep-last: given twice (3 and 4); give each limit once"),
        (["--keep-last"], "--keep-last needs a value (--keep-last VALUE or --keep-last=VALUE)"),
        (["--older-than", "--dry-run"], "--older-than needs a value (--older-than VALUE or --older-than=VALUE)"),
        (["--keep-last=1", "args.grace=soon"], "args.grace: 'soon' is not an age: a number with a unit s, m, h, d or "
                                               "w (e.g. 30d)"),
    ],
)  # fmt: skip
def test_bad_limits_exit_2_naming_the_flag(store, tmp_path, capsys, args, message):
    publish(store.cache, "lora", tmp_path, 1, 100)
    rc, out, err = store.cli(capsys, "gc", *args)
    assert (rc, err.strip()) == (2, f"gdwm cache gc: {message}")
    assert out == "" and len(store.cache.entries()) == 1


def test_value_flags_belong_to_cache_gc_only(capsys):
    assert main(["config", "show", "--keep-last", "3"]) == 2
    assert "gdwm config show: unknown flag(s) ['--keep-last']" in capsys.readouterr().err
    assert main(["cache", "ls", "--max-size=1GB"]) == 2
    assert "gdwm cache ls: unknown flag(s) ['--max-size=1GB']" in capsys.readouterr().err


def test_parsers():
    assert parse_size("50GB", "f") == 50 * 10**9 and parse_size("50GiB", "f") == 50 * 2**30
    assert parse_size("1.5 tb", "f") == 1_500_000_000_000 and parse_size("512", "f") == 512
    assert parse_age("30d", "f") == 30 * 86400 and parse_age("1.5h", "f") == 5400 and parse_age("2w", "f") == 1209600
    assert parse_gc_args(["--keep-last=0", "x=1", "--max-size", "1KiB", "--dry-run"]) == Limits(0, None, 1024, True)
    with pytest.raises(UsageError, match=r"^--max-size: '-5GB' is not a size"):
        parse_gc_args(["--max-size=-5GB"])


def test_gc_while_a_run_is_running_keeps_every_entry_it_read_or_published(tmp_path, capsys):
    """`gdwm cache gc --keep-last 0 args.grace=0s` while a `gdwm run` is held inside lora: the upstream entries the
    run published (finished stage runs) and is about to read stay, whatever the grace; the run then finishes."""
    from tests.gdwm.test_run import Toy, _ok

    toy = Toy(tmp_path)
    proc = subprocess.Popen(toy.args("targets=[lora]", "run.live=false"), env=toy.env(GDWM_TEST_BLOCK="lora"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        end = time.monotonic() + 240
        while not (tmp_path / "blocked-lora").exists():
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.2)
        store = Store(toy.work)
        before = {(m.stage, m.key) for m in store.cache.entries()}
        assert {s for s, _ in before} == {"reconstruct", "distill", "tokenizer"} and len(before) == 7
        rc, out, err = store.cli(capsys, "gc", "--keep-last", "0", "args.grace=0s")
        assert rc == 0, err
        assert "deleted 0 entries, 0 bytes" in out and "kept 7 protected entries (running: 7)" in out
        assert {(m.stage, m.key) for m in store.cache.entries()} == before
        (tmp_path / "release").touch()
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    _ok(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
