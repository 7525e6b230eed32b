"""The stage cache: content keys, atomic publish with a manifest written last, verified lookups."""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
from pathlib import Path

import pytest
from pyarrow.fs import FileType

from gdwm.cache import MANIFEST, Cache, CacheError, FileEntry, Manifest, cache_key, canonical_json
from gdwm.owned import mark_cache

CONFIG = {"lora": {"rank": 8, "alpha": 16.0, "targets": ("q_proj", "v_proj")}, "lr": 0.1}
UPSTREAM = {"tokenizer": "a" * 64}
DATA = "synthetic_mini@seed0"
FILES = {"adapter.bin": b"\x00\x01" * 5000, "metrics.json": b'{"loss": 1.25}', "sub/dir/log.txt": b"step 1\n"}


def key_of(**overrides) -> str:
    args = {"stage": "lora", "version": "1", "config": CONFIG, "upstream": UPSTREAM, "data_fingerprint": DATA}
    return cache_key(**{**args, **overrides})


def make_src(root: Path, files: dict[str, bytes] = FILES) -> Path:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def publish(cache: Cache, src: Path, key: str | None = None, **kw) -> Manifest:
    key = key or key_of(scene=kw.get("scene"))
    return cache.publish("lora", key, src, config=CONFIG, upstream=UPSTREAM, data_fingerprint=DATA, version="1", **kw)


def debris(root: Path) -> list[str]:
    return sorted(p.name for p in root.rglob("*") if p.name.startswith((".tmp-", ".trash-")))


# --- keys ---------------------------------------------------------------------------------------------------------


def test_canonical_json_format():
    assert canonical_json({"b": 0.1, "a": (1, 2.5, None, True)}) == '{"a":[1,2.5,null,true],"b":0.1}'
    assert canonical_json({"x": 1e-7, "y": 3.0}) == '{"x":1e-07,"y":3.0}'


def test_key_stable_across_dict_order():
    reordered = {"lr": 0.1, "lora": {"targets": ["q_proj", "v_proj"], "alpha": 16.0, "rank": 8}}
    assert key_of() == key_of(config=reordered)
    assert len(key_of()) == 64 and int(key_of(), 16) >= 0


@pytest.mark.parametrize(
    "change",
    [
        {"stage": "diffusion"},
        {"version": "2"},
        {"config": {**CONFIG, "lora": {**CONFIG["lora"], "rank": 16}}},
        {"config": {**CONFIG, "lr": 0.10000001}},
        {"upstream": {"tokenizer": "b" * 64}},
        {"upstream": {"adapter": "a" * 64}},
        {"data_fingerprint": "synthetic_mini@seed1"},
        {"scene": "scene-0001"},
    ],
)
def test_key_changes_with_every_input(change):
    assert key_of(**change) != key_of()


def test_per_scene_keys_are_distinct():
    keys = {key_of(scene=f"scene-{i:04d}") for i in range(5)} | {key_of()}
    assert len(keys) == 6


def test_nan_and_inf_rejected_naming_the_path():
    with pytest.raises(TypeError) as e:
        key_of(config={"lora": {"dropout": float("nan")}})
    assert str(e.value) == "config.lora.dropout: non-finite float nan is not allowed"
    with pytest.raises(TypeError) as e:
        canonical_json({"sched": [1.0, float("inf")]})
    assert str(e.value) == "sched[1]: non-finite float inf is not allowed"


def test_unsupported_types_rejected_naming_the_path():
    with pytest.raises(TypeError) as e:
        key_of(config={"lora": {"rank": {1, 2}}})
    assert str(e.value) == "config.lora.rank: unsupported type set"
    with pytest.raises(TypeError) as e:
        canonical_json({"a": {3: "x"}})
    assert str(e.value) == "a: key 3 has unsupported type int (keys must be str)"


# --- publish / lookup ---------------------------------------------------------------------------------------------


def test_publish_then_lookup_roundtrip(tmp_path):
    cache = Cache(tmp_path / "cache")
    key = key_of()
    m = publish(cache, make_src(tmp_path / "src"), run_id="run-1", extra={"steps": 2})
    assert cache.lookup("lora", key) == m
    assert m.key == key and m.run_id == "run-1" and m.extra == {"steps": 2} and m.upstream == UPSTREAM
    assert m.config == {"lora": {"rank": 8, "alpha": 16.0, "targets": ["q_proj", "v_proj"]}, "lr": 0.1}
    expected = {rel: (hashlib.sha256(b).hexdigest(), len(b)) for rel, b in FILES.items()}
    assert {f.path: (f.sha256, f.size) for f in m.files} == expected
    entry = Path(cache.entry_uri("lora", key))
    assert entry == tmp_path / "cache" / "lora" / key[:2] / key
    assert (entry / "sub/dir/log.txt").read_bytes() == b"step 1\n"
    assert Manifest.from_json((entry / MANIFEST).read_text()) == m
    assert cache.materialize(m) == entry
    assert cache.last_invalid == []
    assert debris(tmp_path / "cache") == []


def test_lookup_absent_returns_none(tmp_path):
    cache = Cache(tmp_path)
    assert cache.lookup("lora", key_of()) is None
    assert cache.last_invalid == []
    assert cache.invalidate("lora", key_of()) is False


def test_manifest_is_written_last(tmp_path, monkeypatch):
    cache = Cache(tmp_path / "cache")
    staged = []

    def fail(self, d, m):
        staged.extend(sorted(p.relative_to(d).as_posix() for p in Path(d).rglob("*") if p.is_file()))
        raise OSError("disk full")

    monkeypatch.setattr(Cache, "_write_manifest", fail)
    with pytest.raises(CacheError) as e:
        publish(cache, make_src(tmp_path / "src"))
    # an I/O error names the entry it was writing (pyarrow's own messages name no path)
    entry = cache.entry_uri("lora", key_of())
    assert str(e.value) == f"stage lora key {key_of()[:12]}: could not write {entry}: disk full"
    assert staged == sorted(FILES)  # every file was in place before the manifest
    assert not Path(cache.entry_uri("lora", key_of())).exists()
    assert debris(tmp_path / "cache") == []
    monkeypatch.undo()
    assert cache.lookup("lora", key_of()) is None
    assert len(publish(cache, tmp_path / "src").files) == 3


def test_flipped_byte_detected_and_entry_moved_away(tmp_path, caplog):
    cache = Cache(tmp_path / "cache")
    key = key_of()
    publish(cache, make_src(tmp_path / "src"))
    target = Path(cache.entry_uri("lora", key)) / "adapter.bin"
    st = target.stat()
    data = bytearray(target.read_bytes())
    data[777] ^= 0xFF
    target.write_bytes(bytes(data))
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (target.stat().st_size, target.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)

    assert cache.lookup("lora", key, verify=False) is not None  # size and mtime alone cannot tell
    assert cache.lookup("lora", key) is None
    good = hashlib.sha256(FILES["adapter.bin"]).hexdigest()
    bad = hashlib.sha256(bytes(data)).hexdigest()
    reason = f"adapter.bin: sha256 {bad[:12]} != {good[:12]} in the manifest"
    assert cache.last_invalid == [("lora", key, reason)]
    assert f"cache lora/{key[:12]}: {reason}" in caplog.text
    assert not target.parent.exists()
    assert debris(tmp_path / "cache") == []
    m = publish(cache, tmp_path / "src")
    assert cache.lookup("lora", key) == m
    assert (Path(cache.entry_uri("lora", key)) / "adapter.bin").read_bytes() == FILES["adapter.bin"]


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda e: (e / "metrics.json").unlink(), "metrics.json: missing"),
        (lambda e: (e / "metrics.json").write_bytes(b"{}"), "metrics.json: size 2 != 14 in the manifest"),
        (lambda e: (e / "stray.txt").write_bytes(b"x"), "stray.txt: not listed in the manifest"),
        (lambda e: (e / MANIFEST).unlink(), "MANIFEST.json: missing (incomplete entry)"),
    ],
)
def test_incomplete_entries_are_reported(tmp_path, mutate, reason):
    cache = Cache(tmp_path / "cache")
    key = key_of()
    publish(cache, make_src(tmp_path / "src"))
    mutate(Path(cache.entry_uri("lora", key)))
    assert cache.lookup("lora", key) is None
    assert cache.last_invalid == [("lora", key, reason)]
    assert not Path(cache.entry_uri("lora", key)).exists()


@pytest.mark.parametrize("target", ["/", "outside"])
def test_a_symlink_in_an_entry_is_refused_never_followed(tmp_path, target):
    """A stray symlink (to '/', or to a directory outside the cache) inside an entry: the lookup lists the link
    itself, never what it points to (a walk of '/' hangs or fails the run), and the entry is recomputed."""
    outside = tmp_path / "outside"
    (outside / "deep").mkdir(parents=True)
    (outside / "deep" / "secret.txt").write_text("not the cache's")
    cache = Cache(tmp_path / "cache")
    key = key_of()
    publish(cache, make_src(tmp_path / "src"))
    entry = Path(cache.entry_uri("lora", key))
    (entry / "sub" / "stray").symlink_to(target if target == "/" else outside)
    assert cache.lookup("lora", key) is None
    assert cache.last_invalid == [("lora", key, "sub/stray: a symlink or special file, not a regular file")]
    assert not entry.exists() and (outside / "deep" / "secret.txt").read_text() == "not the cache's"
    assert cache.lookup("lora", publish(cache, tmp_path / "src").key) is not None


def test_truncated_or_foreign_manifest_is_absent(tmp_path):
    cache = Cache(tmp_path / "cache")
    key = key_of()
    publish(cache, make_src(tmp_path / "src"))
    path = Path(cache.entry_uri("lora", key)) / MANIFEST
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    assert cache.lookup("lora", key) is None
    assert cache.last_invalid[0][2].startswith("MANIFEST.json: unreadable (")
    assert cache.entries() == []

    m = publish(cache, tmp_path / "src")
    other = key_of(version="9")
    moved = Path(cache.entry_uri("lora", other))
    moved.parent.mkdir(parents=True)
    Path(cache.entry_uri("lora", key)).rename(moved)  # a manifest sitting under the wrong key
    assert cache.lookup("lora", other) is None
    assert cache.last_invalid == [("lora", other, f"MANIFEST.json: names lora/{key[:12]}, expected lora/{other[:12]}")]
    assert m.key == key


def test_publish_replaces_an_invalid_entry(tmp_path):
    cache = Cache(tmp_path / "cache")
    mark_cache(cache)  # gdwm's cache (a root holding nothing but an entry without manifest is nobody's)
    key = key_of()
    entry = Path(cache.entry_uri("lora", key))
    entry.mkdir(parents=True)
    (entry / "half.bin").write_bytes(b"partial")  # debris of some crashed tool, no manifest
    m = publish(cache, make_src(tmp_path / "src"))
    assert sorted(p.name for p in entry.iterdir()) == sorted([MANIFEST, "adapter.bin", "metrics.json", "sub"])
    assert cache.lookup("lora", key) == m
    assert debris(tmp_path / "cache") == []


def test_empty_source_and_refusals(tmp_path):
    cache = Cache(tmp_path / "cache")
    (tmp_path / "empty").mkdir()
    m = publish(cache, tmp_path / "empty")
    assert m.files == ()
    assert cache.lookup("lora", key_of()) == m

    src = make_src(tmp_path / "linked")
    (src / "link.bin").symlink_to(tmp_path / "empty")
    key = key_of(version="2")
    with pytest.raises(CacheError) as e:
        cache.publish("lora", key, src, config=CONFIG, upstream=UPSTREAM, data_fingerprint=DATA, version="2")
    assert str(e.value) == f"stage lora key {key[:12]}: link.bin: symlinks are refused"

    with pytest.raises(CacheError) as e:
        publish(cache, tmp_path / "empty", key=key)
    assert str(e.value) == f"stage lora key {key[:12]}: != cache_key() of the given inputs ({key_of()[:12]})"
    with pytest.raises(ValueError) as e:
        cache.lookup("../x", key)
    assert str(e.value) == "stage name '../x': use letters, digits, '_', '.', '-'"
    assert debris(tmp_path / "cache") == []


def test_file_uri_plain_path_and_scenes_share_one_layout(tmp_path):
    by_path, by_uri = Cache(tmp_path / "c"), Cache(f"file://{tmp_path}/c")
    assert by_path.atomic_dirs and by_uri.atomic_dirs and by_uri.local
    src = make_src(tmp_path / "src")
    m1 = publish(by_uri, src, scene="scene-0001")
    m2 = publish(by_path, src, scene="scene-0002")
    assert m1.key != m2.key and (m1.scene, m2.scene) == ("scene-0001", "scene-0002")
    assert by_path.lookup("lora", m1.key) == m1 and by_uri.lookup("lora", m2.key) == m2
    assert by_uri.entry_uri("lora", m1.key) == f"file://{tmp_path}/c/lora/{m1.key[:2]}/{m1.key}"
    assert by_path.entry_uri("lora", m1.key) == f"{tmp_path}/c/lora/{m1.key[:2]}/{m1.key}"
    assert [m.scene for m in by_uri.entries("lora")] == ["scene-0001", "scene-0002"]
    assert by_path.entries("diffusion") == [] and len(by_path.entries()) == 2
    assert by_uri.invalidate("lora", m1.key) is True
    assert [m.key for m in by_path.entries()] == [m2.key]
    assert debris(tmp_path / "c") == []


def test_pyarrow_local_move_refuses_a_non_empty_destination(tmp_path):
    """What publish relies on: LocalFileSystem.move is rename(2), never a merge into an existing entry."""
    fs = Cache(tmp_path).fs
    for name, files in {"a": ["x"], "b": ["y"], "c": ["z"], "empty": []}.items():
        (tmp_path / name).mkdir()
        for f in files:
            (tmp_path / name / f).write_text(name)
    with pytest.raises(OSError, match="Directory not empty"):
        fs.move(str(tmp_path / "a"), str(tmp_path / "b"))
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["y"]
    fs.move(str(tmp_path / "c"), str(tmp_path / "empty"))  # an empty destination is replaced
    assert sorted(p.name for p in (tmp_path / "empty").iterdir()) == ["z"]


def test_relative_plain_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cache = Cache("rel/cache")
    assert cache.root == f"{tmp_path}/rel/cache"


# --- remote filesystems (pyarrow's in-memory mock filesystem) ------------------------------------------------------


@pytest.mark.parametrize("atomic_dirs", [True, False], ids=["rename", "object-store"])
def test_remote_publish_and_materialize(tmp_path, monkeypatch, atomic_dirs):
    monkeypatch.setenv("GDWM_LOCAL_CACHE", str(tmp_path / "local"))
    cache = Cache("mock:///bucket/cache")
    assert cache.atomic_dirs and not cache.local
    cache.atomic_dirs = atomic_dirs  # what S3/GCS get: no directory renames
    key = key_of()
    m = publish(cache, make_src(tmp_path / "src"))
    assert cache.entry_uri("lora", key) == f"mock://bucket/cache/lora/{key[:2]}/{key}"
    assert cache.lookup("lora", key) == m
    assert publish(cache, tmp_path / "src") == m  # a second writer gets the first one's entry
    local = cache.materialize(m)
    assert local == tmp_path / "local" / "lora" / key
    assert {p.relative_to(local).as_posix(): p.read_bytes() for p in local.rglob("*") if p.is_file()} == {
        **FILES,
        MANIFEST: m.to_json().encode(),
    }
    mtime = (local / "adapter.bin").stat().st_mtime_ns
    assert cache.materialize(m) == local and (local / "adapter.bin").stat().st_mtime_ns == mtime
    assert debris(tmp_path / "local") == []

    with cache.fs.open_output_stream(f"bucket/cache/lora/{key[:2]}/{key}/metrics.json") as f:
        f.write(b'{"loss": 9.25}')  # same size, other bytes
    good, bad = (hashlib.sha256(b).hexdigest()[:12] for b in (FILES["metrics.json"], b'{"loss": 9.25}'))
    assert cache.lookup("lora", key) is None
    assert cache.last_invalid == [("lora", key, f"metrics.json: sha256 {bad} != {good} in the manifest")]
    assert cache.fs.get_file_info(f"bucket/cache/lora/{key[:2]}/{key}").type == FileType.NotFound
    m = publish(cache, tmp_path / "src")
    assert cache.invalidate("lora", key) is True
    assert cache.lookup("lora", key) is None and cache.last_invalid == []
    assert cache.entries() == []


def test_manifest_json_roundtrip():
    m = Manifest(
        "k" * 64,
        "lora",
        "1",
        {"a": [1, 0.1]},
        {"t": "u" * 64},
        DATA,
        None,
        (FileEntry("x", "0" * 64, 3),),
        None,
        1.5,
        {},
    )
    assert Manifest.from_json(m.to_json()) == m
    assert json.loads(m.to_json())["files"] == [{"path": "x", "sha256": "0" * 64, "size": 3}]
    with pytest.raises(ValueError, match="expected fields"):
        Manifest.from_json('{"key": "x"}')


# --- concurrency --------------------------------------------------------------------------------------------------


def _writer(uri: str, src: str, barrier, out) -> None:
    move, renames = Cache._move, []

    def racing_move(self, s, d):
        if not renames:
            barrier.wait()  # all 8 staged a complete temp entry and found no final one: race for the rename
        renames.append(move(self, s, d))
        return renames[-1]

    Cache._move = racing_move
    m = publish(Cache(uri), Path(src))
    out.put((m.to_json(), renames))


def test_concurrent_writers_publish_one_entry(tmp_path):
    ctx = mp.get_context("spawn")
    src = make_src(tmp_path / "src")
    barrier, out = ctx.Barrier(8), ctx.Queue()
    procs = [ctx.Process(target=_writer, args=(str(tmp_path / "cache"), str(src), barrier, out)) for _ in range(8)]
    for p in procs:
        p.start()
    got = [out.get(timeout=120) for _ in procs]
    results = [Manifest.from_json(text) for text, _ in got]
    for p in procs:
        p.join(timeout=60)
    assert [p.exitcode for p in procs] == [0] * 8
    key = key_of()
    assert {m.key for m in results} == {key}
    assert len({m.to_json() for m in results}) == 1  # every writer got the one winner's manifest
    renames = sorted(r for _, rs in got for r in rs)
    assert renames == [False] * 7 + [True]  # one rename won; the rest were refused, not merged
    cache = Cache(tmp_path / "cache")
    assert cache.lookup("lora", key) == results[0]
    assert [m.key for m in cache.entries()] == [key]
    assert sorted(p.name for p in (tmp_path / "cache" / "lora" / key[:2]).iterdir()) == [key]
    assert debris(tmp_path / "cache") == []
    entry = Path(cache.entry_uri("lora", key))
    assert {f.path: f.sha256 for f in results[0].files} == {
        rel: hashlib.sha256((entry / rel).read_bytes()).hexdigest() for rel in FILES
    }


def test_cache_verify_reaches_the_lookups_a_run_makes(tmp_path):
    """``cache.verify`` (config) -> RunEnv.verify -> the verified lookups: off trusts the manifest, on re-hashes."""
    from gdwm.config import load_config
    from gdwm.executor import verified
    from gdwm.plan import env_settings

    meta = {"fingerprint": "data", "scenes": []}
    assert env_settings(load_config([]), meta)["verify"] is True
    assert env_settings(load_config(["cache.verify=false"]), meta)["verify"] is False
    cache = Cache(tmp_path / "cache")
    m = publish(cache, make_src(tmp_path / "src"))
    f = Path(cache.entry_uri("lora", m.key)) / "adapter.bin"
    f.write_bytes(b"\xff" + f.read_bytes()[1:])  # same size, other bytes
    ckpt = tmp_path / "ckpt"
    (ckpt / "lora" / m.key / "steps").mkdir(parents=True)
    assert verified(cache, str(ckpt), "lora", m.key, verify=False) is True  # trusted: the flip goes unseen
    assert verified(cache, str(ckpt), "lora", m.key, verify=True) is False  # re-hashed: moved aside
    assert cache.entries("lora") == [] and not (ckpt / "lora" / m.key).exists()  # and its checkpoints discarded
