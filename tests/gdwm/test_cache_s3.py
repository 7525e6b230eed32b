"""The stage cache on S3: a loopback moto server (server mode, real HTTP) behind pyarrow's S3FileSystem.

Publish, lookup, verify, materialize and gc as on a local disk; credentials from the environment only; a wrong
credential or an endpoint lost mid-publish fails with one line naming the bucket and never a half-published entry.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import posixpath
import re
import subprocess
import time
from pathlib import Path

import pytest
from moto.core.authorization import enable_iam_authentication

from gdwm.cache import MANIFEST, Cache, CacheError, Manifest, cache_key
from gdwm.housekeeping import Limits, gc, scan
from tests.gdwm.servers import BUCKET, SECRET, Moto
from tests.gdwm.test_run import ALL, Toy, _ok

pytestmark = pytest.mark.heavy(1.5)

WRONG_SECRET = "a-wrong-secret-that-must-never-be-printed"
CONFIG = {"lora": {"rank": 8, "alpha": 16.0}, "lr": 0.1}
UPSTREAM = {"tokenizer": "a" * 64}
DATA = "synthetic_mini@seed0"
FILES = {"adapter.bin": b"\x00\x01" * 5000, "metrics.json": b'{"loss": 1.25}', "sub/dir/log.txt": b"step 1\n"}


@pytest.fixture(scope="module")
def s3():
    moto = Moto()
    moto.client().create_bucket(Bucket=BUCKET)
    yield moto
    if moto.up:
        moto.stop()


@pytest.fixture(autouse=True)
def aws_env(monkeypatch, tmp_path):
    """Credentials as pyarrow reads them, from the environment; downloads into a per-test local cache."""
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", SECRET)
    monkeypatch.delenv("AWS_SESSION_TOKEN", raising=False)
    monkeypatch.delenv("AWS_ENDPOINT_URL", raising=False)
    monkeypatch.setenv("AWS_REGION", "us-east-1")
    monkeypatch.setenv("GDWM_LOCAL_CACHE", str(tmp_path / "local-copies"))


def key_of(config: dict = CONFIG, code: str | None = None) -> str:
    return cache_key("lora", "1", config, UPSTREAM, DATA, code=code)


def make_src(root: Path, files: dict[str, bytes] = FILES) -> Path:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def publish(cache: Cache, src: Path, config: dict = CONFIG, code: str | None = None) -> Manifest:
    """``code``: the entry's code digest (its key then differs from its code-free ``base``)."""
    return cache.publish(
        "lora", key_of(config, code), src, config=config, upstream=UPSTREAM, data_fingerprint=DATA, version="1",
        code=None if code is None else {"digest": code}, base=None if code is None else key_of(config),
    )  # fmt: skip


def entry_prefix(prefix: str, key: str) -> str:
    return f"{prefix}/lora/{key[:2]}/{key}"


# --- publish, verify, materialize -----------------------------------------------------------------------------------


def test_publish_verify_materialize_match_a_local_twin(s3, tmp_path):
    src = make_src(tmp_path / "src")
    local = Cache(tmp_path / "cache")
    remote = Cache(s3.uri("twin"))
    assert (remote.fs.type_name, remote.root, remote.atomic_dirs) == ("s3", f"{BUCKET}/twin", False)
    m_local, m_s3 = publish(local, src), publish(remote, src)
    assert dataclasses.replace(m_s3, created_at=m_local.created_at) == m_local
    key = key_of()
    # the entry's files and its manifest, nothing else (but the root's marker): no directory or temp objects
    objects = s3.objects("twin")
    assert sorted(objects) == sorted(["twin/.gdwm-cache", *(f"{entry_prefix('twin', key)}/{p}" for p in
                                                            [*FILES, MANIFEST])])  # fmt: skip
    assert Manifest.from_json(objects[f"{entry_prefix('twin', key)}/{MANIFEST}"].decode()) == m_s3
    assert remote.entries() == [m_s3] and remote.entries("lora") == [m_s3]
    assert remote.lookup("lora", key) == m_s3 and remote.last_invalid == []
    assert f"twin/lora/.used/{key}" in s3.objects("twin")  # the hit recorded its use
    there = remote.materialize(m_s3)
    assert there == tmp_path / "local-copies" / "lora" / key
    here = Path(local.entry_uri("lora", key))
    for rel in FILES:
        assert (there / rel).read_bytes() == (here / rel).read_bytes() == FILES[rel]
    assert Manifest.from_json((there / MANIFEST).read_text()) == m_s3
    assert remote.materialize(m_s3) == there  # a second call reuses the verified copy
    assert publish(remote, src) == m_s3  # a second publish of the key returns the entry in place


def test_flipped_byte_on_s3_is_caught_and_the_entry_removed(s3, tmp_path, caplog):
    cache = Cache(s3.uri("flip"))
    m = publish(cache, make_src(tmp_path / "src"))
    obj = f"{entry_prefix('flip', m.key)}/adapter.bin"
    data = bytearray(FILES["adapter.bin"])
    data[777] ^= 0xFF
    s3.client().put_object(Bucket=BUCKET, Key=obj, Body=bytes(data))
    with pytest.raises(CacheError) as e:
        cache.materialize(m)
    good, bad = m.files[0].sha256, hashlib.sha256(bytes(data)).hexdigest()
    assert str(e.value) == (
        f"stage lora key {m.key[:12]}: adapter.bin: downloaded sha256 {bad[:12]} != {good[:12]} in the manifest"
    )
    assert cache.lookup("lora", m.key, verify=False) == m  # the manifest alone cannot tell
    assert cache.lookup("lora", m.key) is None
    assert cache.last_invalid == [("lora", m.key, f"adapter.bin: sha256 {bad[:12]} != {good[:12]} in the manifest")]
    assert "moving the entry aside to recompute" in caplog.text
    assert [k for k in s3.objects("flip") if f"/{m.key}/" in k] == []
    assert cache.entries() == []


@pytest.mark.parametrize("evil", ["../../../escaped.txt", "sub/../../../../escaped.txt", "/tmp/escaped.txt"])
@pytest.mark.parametrize("verify", [True, False])
def test_a_manifest_naming_a_path_outside_its_entry_writes_nothing_outside(s3, tmp_path, evil, verify):
    """Someone with write access to the bucket adds a file ``../../../escaped.txt`` to an entry's manifest and puts
    the object where pyarrow would read it (it normalises the ``..``): the entry is refused, moved aside and
    recomputed; nothing is written outside the local cache, whether or not lookups re-hash."""
    prefix = f"evil-{len(evil)}-{verify}"
    cache = Cache(s3.uri(prefix))
    m = publish(cache, make_src(tmp_path / "src"))
    payload = b"echo pwned\n"
    doctored = json.loads(m.to_json())
    doctored["files"].append({"path": evil, "sha256": hashlib.sha256(payload).hexdigest(), "size": len(payload)})
    entry, client = entry_prefix(prefix, m.key), s3.client()
    client.put_object(Bucket=BUCKET, Key=f"{entry}/{MANIFEST}", Body=json.dumps(doctored).encode())
    for where in {f"{entry}/{evil}", posixpath.normpath(f"{entry}/{evil}").lstrip("/")}:  # as listed and as read
        client.put_object(Bucket=BUCKET, Key=where, Body=payload)
    hit = cache.lookup("lora", m.key, verify=verify)  # what the next `gdwm run` does with the entry
    if hit is not None:
        cache.materialize(hit)
    written = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file())
    assert [p for p in written if not p.startswith(("src/", "local-copies/"))] == []
    assert not Path("/tmp/escaped.txt").exists()
    assert hit is None
    assert cache.last_invalid == [("lora", m.key, f"{MANIFEST}: unreadable (file {evil!r}: not a plain relative "
                                                  "path inside the entry)")]  # fmt: skip
    assert cache.entries() == []  # moved aside: the next run recomputes it
    with pytest.raises(ValueError, match="not a plain relative path inside the entry"):
        Manifest.from_json(json.dumps(doctored))  # nothing can hand materialize() such a manifest


# --- credentials and endpoint -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "uri, named",
    [
        ("s3://AKIAEXAMPLE:{secret}@gdwm/cache", "user:secret@"),
        ("s3://gdwm/cache?endpoint_override=127.0.0.1:9&access_key=AKIAEXAMPLE&secret_key={secret}", "access_key=, "
         "secret_key="),
        ("s3://gdwm/cache?session_token={secret}", "session_token="),
    ],
)  # fmt: skip
def test_a_uri_with_credentials_is_refused_without_echoing_them(uri, named):
    with pytest.raises(CacheError) as e:
        Cache(uri.format(secret=SECRET))
    assert str(e.value) == (
        f"cache.uri s3://gdwm/cache: credentials in the URI ({named}) are refused; set AWS_ACCESS_KEY_ID / "
        "AWS_SECRET_ACCESS_KEY (and AWS_SESSION_TOKEN) in the environment"
    )
    assert SECRET not in str(e.value) and "AKIAEXAMPLE" not in str(e.value)


def test_endpoint_from_aws_endpoint_url(s3, tmp_path, monkeypatch):
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3.endpoint)
    cache = Cache(f"s3://{BUCKET}/by-env")
    m = publish(cache, make_src(tmp_path / "src"))
    assert f"{entry_prefix('by-env', m.key)}/{MANIFEST}" in s3.objects("by-env")
    assert Cache(s3.uri("by-env")).lookup("lora", m.key) == m  # the same entry through the URI's query


def test_wrong_credentials_name_the_bucket_never_the_secret(s3, tmp_path, monkeypatch):
    cache = Cache(s3.uri("auth"))
    publish(cache, make_src(tmp_path / "src"))
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "AKIAWRONGWRONGWRONG1")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", WRONG_SECRET)
    with enable_iam_authentication():  # moto checks keys only when asked to
        with pytest.raises(CacheError) as listing:
            Cache(s3.uri("auth")).entries()
        with pytest.raises(CacheError) as writing:
            publish(Cache(s3.uri("auth")), tmp_path / "src", {"lr": 0.2})
    assert str(listing.value) == (
        f"cache {s3.uri('auth')}: listing the entries: bucket gdwm: access denied (INVALID_ACCESS_KEY_ID during "
        "ListObjectsV2); check the credentials in AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY / AWS_SESSION_TOKEN"
    )
    key = key_of({"lr": 0.2})
    assert str(writing.value) == (
        f"stage lora key {key[:12]}: lookup in cache {s3.uri('auth')}: bucket gdwm: access denied (ACCESS_DENIED "
        "during HeadObject); check the credentials in AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY / AWS_SESSION_TOKEN"
    )
    assert WRONG_SECRET not in str(listing.value) + str(writing.value)


def test_gdwm_run_with_wrong_credentials_exits_1_naming_the_bucket(s3, tmp_path):
    toy = Toy(tmp_path)
    uri = s3.uri("run-auth")
    with enable_iam_authentication():
        r = toy.run(f'cache.uri="{uri}"', AWS_ACCESS_KEY_ID="AKIAWRONGWRONGWRONG1", AWS_SECRET_ACCESS_KEY=WRONG_SECRET)
    assert r.returncode == 1, r.stderr[-3000:]
    # the plan's first lookup is the first request: a HEAD, whose 403 carries no error code
    assert re.fullmatch(
        re.escape("gdwm run: CacheError: stage reconstruct key ")
        + "[0-9a-f]{12}"
        + re.escape(
            f": lookup in cache {uri}: bucket gdwm: access denied (ACCESS_DENIED during HeadObject); check the "
            "credentials in AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY / AWS_SESSION_TOKEN"
        ),
        r.stderr.strip().splitlines()[-1],
    )
    assert WRONG_SECRET not in r.stderr + r.stdout


def test_endpoint_down_mid_publish_leaves_no_entry(s3, tmp_path, monkeypatch):
    """The server stops after the first file's upload: the publish fails naming the entry and the bucket, no
    manifest was written, and once the server is back the objects left over are invisible, replaced by the next
    publish of the key or removed by gc once a day old."""
    cache = Cache(s3.uri("down"))
    key = key_of()
    upload = Cache._upload

    def upload_then_go_down(self, src, dst):
        out = upload(self, src, dst)
        if s3.up:
            s3.stop()
        return out

    try:
        with monkeypatch.context() as patch, pytest.raises(CacheError) as e:
            patch.setattr(Cache, "_upload", upload_then_go_down)
            publish(cache, make_src(tmp_path / "src"))
    finally:
        if not s3.up:
            s3.start()
    assert str(e.value).startswith(
        f"stage lora key {key[:12]}: could not write {cache.entry_uri('lora', key)}: bucket gdwm: NETWORK_CONNECTION "
        "during "
    )
    left = s3.objects("down")
    # the cleanup could not reach the store
    assert sorted(left) == ["down/.gdwm-cache", f"{entry_prefix('down', key)}/adapter.bin"]
    assert cache.lookup("lora", key) is None and cache.entries() == [] and cache.last_invalid == []
    found = scan(cache)
    assert found.entries == [] and [(x.kind, x.size) for x in found.leftovers] == [("incomplete", 10000)]
    # a day later gc removes what is left
    store = f"sqlite:///{tmp_path}/mlflow.db"
    r = gc(cache, store, Limits(keep_last=0), grace=0, now=time.time() + 2 * 86400)
    assert [x.kind for x in r.leftovers_removed] == ["incomplete"] and list(s3.objects("down")) == ["down/.gdwm-cache"]
    # and a publish over an interrupted one (a stray object of another output) replaces it whole
    s3.client().put_object(Bucket=BUCKET, Key=f"{entry_prefix('down', key)}/stray.bin", Body=b"old")
    m = publish(cache, tmp_path / "src")
    assert cache.lookup("lora", key) == m and cache.last_invalid == []
    assert sorted(k for k in s3.objects("down") if "/.used/" not in k and k != "down/.gdwm-cache") == sorted(
        f"{entry_prefix('down', key)}/{p}" for p in [*FILES, MANIFEST]
    )


def test_gc_on_s3_deletes_unprotected_entries(s3, tmp_path):
    cache = Cache(s3.uri("gc"))
    src = make_src(tmp_path / "src")
    ms = [publish(cache, src, {"lr": lr}, code="c0de") for lr in (0.1, 0.2, 0.3)]
    assert {m.key for m in cache.entries()} == {m.key for m in ms}
    assert cache.lookup("lora", ms[2].key) == ms[2]  # the most recently used
    store = f"sqlite:///{tmp_path}/mlflow.db"
    dry = gc(cache, store, Limits(keep_last=1, dry_run=True), grace=0)
    assert sorted(e.key for e in dry.deleted) == sorted(m.key for m in ms[:2]) and len(cache.entries()) == 3
    # two days on: the kept entry's code-free index is no leftover (cache.reuse=all still finds it)
    r = gc(cache, store, Limits(keep_last=1), grace=0, now=time.time() + 2 * 86400)
    assert sorted(e.key for e in r.deleted) == sorted(m.key for m in ms[:2]) and r.leftovers_removed == []
    assert r.freed == dry.freed > 2 * sum(map(len, FILES.values()))
    assert cache.entries() == [ms[2]] and cache.lookup_base("lora", key_of({"lr": 0.3})) == ms[2]
    kept = {k for k in s3.objects("gc") if "/.used/" not in k and "/.bases/" not in k}
    assert {k.split("/")[3] for k in kept - {"gc/.gdwm-cache"}} == {ms[2].key} and "gc/.gdwm-cache" in kept


# --- end to end -------------------------------------------------------------------------------------------------------


def test_gdwm_run_on_s3_then_a_rerun_is_all_cache_hits(s3, tmp_path):
    toy = Toy(tmp_path)
    # RAY_ADDRESS=local: a `ray start` cluster elsewhere on this machine must not capture the run
    env = {"AWS_ENDPOINT_URL": s3.endpoint, "GDWM_LOCAL_CACHE": str(tmp_path / "local-copies"), "RAY_ADDRESS": "local"}
    _ok(toy.run(f"cache.uri=s3://{BUCKET}/e2e", **env))
    manifests = [k for k in s3.objects("e2e") if k.endswith(f"/{MANIFEST}")]
    assert sorted({k.split("/")[1] for k in manifests}) == sorted(ALL) and len(manifests) == 11
    assert not (toy.work / "cache").exists()  # nothing went to the local default
    (toy.root / "executions.log").write_text("")
    r = toy.run(f"cache.uri=s3://{BUCKET}/e2e", **env)
    _ok(r)
    assert toy.executions() == []
    assert "all 11 stage outputs cached and verified; nothing to run" in r.stdout


def test_endpoint_down_inside_a_gdwm_run_fails_the_stage_naming_the_cache(s3, tmp_path):
    """The store goes away while reconstruct computes: its scenes cannot be published, the run exits 1 naming the
    cache URI, no entry of the stage is visible once the store is back, and the next run computes them."""
    toy = Toy(tmp_path)
    env = {"AWS_ENDPOINT_URL": s3.endpoint, "GDWM_LOCAL_CACHE": str(tmp_path / "local-copies"), "RAY_ADDRESS": "local"}
    uri = f"s3://{BUCKET}/midrun"
    proc = subprocess.Popen(toy.args(f"cache.uri={uri}", "targets=[reconstruct]", "run.live=false"),
                            env=toy.env(GDWM_TEST_BLOCK="reconstruct", **env), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        end = time.monotonic() + 240
        while not (tmp_path / "blocked-reconstruct").exists():
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.2)
        s3.stop()
        (tmp_path / "release").touch()
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        if not s3.up:
            s3.start()
    assert proc.returncode == 1, f"exit {proc.returncode}\n{out[-3000:]}\n{err[-3000:]}"
    last = err.strip().splitlines()[-1]
    assert last.startswith("gdwm run: ") and f"s3://{BUCKET}/midrun" in last, err[-3000:]
    assert "NETWORK_CONNECTION" in last and SECRET not in out + err
    assert Cache(s3.uri("midrun")).entries("reconstruct") == []
    assert {r.info.status for r in toy.runs()} == {"FAILED"}
    (tmp_path / "executions.log").write_text("")
    r = toy.run(f"cache.uri={uri}", "targets=[reconstruct]", **env)
    _ok(r)
    assert sorted(s for _, s in toy.executions()) == ["scene-0000", "scene-0001", "scene-0002"]
    assert len(Cache(s3.uri("midrun")).entries("reconstruct")) == 3
