"""The model zoo on a real MLflow registry (sqlite): stages register on publish, `gdwm zoo promote|load|list|show`
round-trip, and a stage reading ``zoo:NAME@ALIAS`` gets that alias's exact version in its cache key and files.

The stages are tests/gdwm/zoo_stages.py, run through the real CLI on local Ray.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mlflow import MlflowClient
from omegaconf import OmegaConf

from gdwm.cache import Cache
from gdwm.tracking import TrackingBackend
from gdwm.zoo.refs import ZooError, parse_ref
from gdwm.zoo.registry import flavor, pin_references, resolve
from tests.gdwm.toydata import make_dataset

pytestmark = pytest.mark.heavy(2)

REPO = Path(__file__).resolve().parents[2]


class Zoo:
    """A workdir + toy dataset; runs `gdwm` against them."""

    def __init__(self, root: Path):
        self.root, self.data, self.work = root, root / "ds", root / "w"
        make_dataset(self.data)
        self.uri = f"sqlite:///{self.work.resolve()}/mlflow.db"

    def gdwm(self, *args: str) -> subprocess.CompletedProcess:
        env = {**os.environ, "PYTHONPATH": str(REPO), "GDWM_CONF_PATH": str(REPO / "tests" / "conf")}
        cmd = [sys.executable, "-m", "gdwm", *args, f"workdir={self.work}"]
        return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)

    def run(self, *overrides: str) -> subprocess.CompletedProcess:
        return self.gdwm("run", "experiment=toy_zoo", f"data.root={self.data}", *overrides)

    def client(self) -> MlflowClient:
        return MlflowClient(self.uri, registry_uri=self.uri)

    def versions(self) -> dict[int, dict[str, str]]:
        return {int(v.version): v.tags for v in self.client().search_model_versions("name = 'gdwm-toy'")}

    def promote(self, version: int) -> None:
        self.client().set_registered_model_alias("gdwm-toy", "champion", str(version))

    def aliases(self) -> dict[str, int]:
        return {a: int(v) for a, v in self.client().get_registered_model("gdwm-toy").aliases.items()}

    def entry(self, stage: str, key: str) -> Path:
        return self.work / "cache" / stage / key[:2] / key


def _ok(r: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"exit {r.returncode}\nSTDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"
    return r


def _files(d: Path) -> dict[str, bytes]:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def zoo(tmp_path_factory) -> Zoo:
    """Versions 1 and 2 of gdwm-toy, trained by zoo_train with value=1 and value=2."""
    z = Zoo(tmp_path_factory.mktemp("zoo"))
    _ok(z.run("targets=[zoo_train]"))
    _ok(z.run("targets=[zoo_train]", "stage.toy_zoo_train.value=2"))
    return z


def test_a_published_stage_registers_its_component_with_lineage(zoo):
    cache = Cache(zoo.work / "cache")
    keys = {m.config["stage.toy_zoo_train"]["value"]: m.key for m in cache.entries("zoo_train")}
    runs = {m.key: m.run_id for m in cache.entries("zoo_train")}
    assert zoo.versions() == {
        v: {
            "gdwm.variant": f"toy-v{v}",
            "gdwm.stage": "zoo_train",
            "gdwm.cache_key": keys[v],
            "gdwm.metric.score": str(v / 10),  # the stage's numeric return values; "label" is not a number
            "toy.note": "from a test",
        }
        for v in (1, 2)
    }
    assert zoo.aliases()["candidate"] == 2  # the newest version is the candidate
    mv = zoo.client().get_model_version("gdwm-toy", "1")
    assert mv.run_id == runs[keys[1]]  # the stage run that trained it
    assert mv.source.endswith(f"{runs[keys[1]]}/artifacts/zoo/gdwm-toy")
    assert flavor(zoo.uri, "gdwm-toy", 1) == {
        "component": "gdwm-toy",
        "variant": "toy-v1",
        "files": ["meta.json", "sub/weights.bin"],
    }


def test_promote_then_load_returns_the_stage_output_byte_for_byte(zoo, tmp_path):
    r = _ok(zoo.gdwm("zoo", "promote", "args.name=gdwm-toy", "args.version=1"))
    assert "gdwm-toy@champion -> version 1" in r.stdout
    assert zoo.aliases()["champion"] == 1
    _ok(zoo.gdwm("zoo", "load", "args.name=gdwm-toy", "args.alias=champion", f"args.out={tmp_path / 'v1'}"))
    (entry,) = [
        m for m in Cache(zoo.work / "cache").entries("zoo_train") if m.config["stage.toy_zoo_train"]["value"] == 1
    ]
    published = _files(zoo.entry("zoo_train", entry.key) / "model")
    loaded = _files(tmp_path / "v1")
    assert {k: loaded[k] for k in published} == published
    assert set(loaded) == {*published, "MLmodel", ".gdwm-download"}
    # @ALIAS also works as a version; promoting the candidate moves champion to version 2
    _ok(zoo.gdwm("zoo", "promote", "args.name=gdwm-toy", "args.version=@candidate", "args.alias=champion"))
    assert zoo.aliases() == {"candidate": 2, "champion": 2}


def test_a_cache_hit_or_a_failed_stage_registers_nothing(zoo):
    hit = _ok(zoo.run("targets=[zoo_train]"))
    assert "nothing to run" in hit.stdout
    # zoo_train fails after ctx.register (its run FAILED, nothing published) while zoo_use runs on
    zoo.promote(1)
    failed = zoo.run("stage.toy_zoo_train.value=3", "stage.toy_zoo_train.fail=true")
    assert failed.returncode == 1 and "injected failure after ctx.register" in failed.stderr
    used = [m.config["stage.toy_zoo_use"]["source"] for m in Cache(zoo.work / "cache").entries("zoo_use")]
    assert used == ["zoo:gdwm-toy/1"]
    assert sorted(zoo.versions()) == [1, 2]


def test_a_stage_reading_the_zoo_uses_the_pinned_version(zoo):
    cache = Cache(zoo.work / "cache")
    seen = {}
    for version in (1, 2, 1):
        zoo.promote(version)
        _ok(zoo.run("targets=[zoo_use]"))  # stage.toy_zoo_use.source: zoo:gdwm-toy@champion
        (m,) = [m for m in cache.entries("zoo_use") if m.config["stage.toy_zoo_use"]["source"].endswith(f"/{version}")]
        assert m.config == {"stage.toy_zoo_use": {"source": f"zoo:gdwm-toy/{version}"}}  # the key names the version
        assert json.loads((zoo.entry("zoo_use", m.key) / "meta.json").read_text()) == {"value": version}
        seen.setdefault(version, m.key)
        assert seen[version] == m.key  # back to version 1: the same key, a cache hit
    assert len(set(seen.values())) == 2 and len(cache.entries("zoo_use")) == 2


def test_an_unknown_reference_fails_before_anything_runs(zoo):
    bad = zoo.run("targets=[zoo_use]", "stage.toy_zoo_use.source=zoo:gdwm-toy@best")
    assert bad.returncode == 1 and "Started a local Ray" not in bad.stderr
    assert "stage.toy_zoo_use.source=zoo:gdwm-toy@best: model 'gdwm-toy' has no alias 'best'" in bad.stderr


def test_zoo_list_show_and_an_error(zoo):
    zoo.promote(1)
    rows = [line for line in _ok(zoo.gdwm("zoo", "list")).stdout.splitlines() if "gdwm-toy" in line]
    assert len(rows) == 2
    assert "toy-v2" in rows[0] and "candidate" in rows[0] and "score=0.2" in rows[0]
    assert "toy-v1" in rows[1] and "champion" in rows[1] and "zoo_train" in rows[1]
    show = _ok(zoo.gdwm("zoo", "show", "args.name=gdwm-toy", "args.version=@champion")).stdout
    assert "gdwm-toy version 1" in show and "sub/weights.bin" in show and "toy-v1" in show
    r = zoo.gdwm("zoo", "promote", "args.name=gdwm-toy", "args.version=9")
    assert r.returncode == 1
    assert "gdwm zoo promote: ZooError: model 'gdwm-toy' has no version 9 (versions: 1, 2)" in r.stderr


def test_pin_references_resolve_and_tag_versions_on_a_store(tmp_path):
    """Without Ray: a backend registers two versions; references pin; errors name them; a sweep's tags land."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    backend = TrackingBackend(uri, "gdwm", str(tmp_path / "art"))
    for value in (1, 2):
        component = tmp_path / f"c{value}"
        component.mkdir()
        (component / "w.bin").write_bytes(bytes([value]))
        run_id = backend.create_run(f"r{value}", {})
        version = backend.register_component(run_id, "gdwm-x", str(component), "v", {"gdwm.cache_key": f"k{value}"})
        assert version == value
    client = MlflowClient(uri, registry_uri=uri)

    cfg = OmegaConf.create({"stage": {"a": {"src": "zoo:gdwm-x@candidate", "more": ["zoo:gdwm-x/1"]}, "b": "zoo:n@a"}})
    pinned = pin_references(cfg, uri, ["stage.a"])  # stage.b: no stage about to run reads it
    assert OmegaConf.to_container(pinned) == {
        "stage": {"a": {"src": "zoo:gdwm-x/2", "more": ["zoo:gdwm-x/1"]}, "b": "zoo:n@a"}
    }
    assert cfg.stage.a.src == "zoo:gdwm-x@candidate"  # the caller's config is left as it was
    with pytest.raises(ZooError, match=r"^stage\.b=zoo:n@a: no registered model 'n' in the zoo \(registered: gdwm-x\)"):
        pin_references(cfg, uri)
    with pytest.raises(
        ZooError, match=r"^stage\.a\.more\[0\]=zoo:gdwm-x/7: model 'gdwm-x' has no version 7 \(versions: 1, 2\)"
    ):
        pin_references(OmegaConf.create({"stage": {"a": {"more": ["zoo:gdwm-x/7"]}}}), uri)
    with pytest.raises(ZooError, match=r"model 'gdwm-x' has no alias 'champion' \(aliases: candidate -> 2\)"):
        resolve(client, "gdwm-x", alias="champion")
    with pytest.raises(ZooError, match="'zoo:gdwm-x': not a zoo reference"):
        parse_ref("zoo:gdwm-x")
    assert int(resolve(client, "gdwm-x").version) == 2  # neither version nor alias: the newest

    sweep_tags = {"gdwm.sweep": "s", "gdwm.metric.nuinteract/avg": 41.5}
    assert backend.tag_versions(["k2", "k9"], sweep_tags) == [("gdwm-x", 2)]
    assert client.get_model_version("gdwm-x", "2").tags == {
        "gdwm.variant": "v",
        "gdwm.cache_key": "k2",
        "gdwm.sweep": "s",
        "gdwm.metric.nuinteract/avg": "41.5",
    }
    assert client.get_model_version("gdwm-x", "1").tags == {"gdwm.variant": "v", "gdwm.cache_key": "k1"}
    backend.close()


def test_zoo_load_refuses_a_version_whose_files_lie_outside_its_run(tmp_path):
    """A registered version's source is copied only from inside the artifact directory of the run that registered it:
    another directory, a ``..`` out of the run, or a symlink inside it leading out is refused, naming the path."""
    zoo = Zoo.__new__(Zoo)  # a store without the toy dataset or Ray
    zoo.root, zoo.work = tmp_path, tmp_path / "w"
    zoo.uri = f"sqlite:///{zoo.work.resolve()}/mlflow.db"
    backend = TrackingBackend(zoo.uri, "gdwm", str(zoo.work / "mlartifacts"))
    component = tmp_path / "c"
    component.mkdir()
    (component / "w.bin").write_bytes(b"ok")
    run_id = backend.create_run("r", {})
    assert backend.register_component(run_id, "gdwm-x", str(component), "v", {}) == 1
    backend.close()
    secret = tmp_path / "outside"
    secret.mkdir()
    (secret / "secret.pth").write_bytes(b"secret")
    client = zoo.client()
    run_dir = Path(client.get_run(run_id).info.artifact_uri)
    (run_dir / "zoo" / "gdwm-x" / "link.pth").symlink_to(secret / "secret.pth")  # version 1 now leads out too
    escape = f"{run_dir}/../../../../outside"  # <w>/mlartifacts/<run>/artifacts/..
    for source in (str(secret), escape):
        client.create_model_version("gdwm-x", source, run_id)  # versions 2, 3
    base = run_dir.resolve()
    refused = {
        1: f"{run_dir}/zoo/gdwm-x/link.pth leads outside the artifact directory {base} of its run {run_id} "
        f"(to {secret / 'secret.pth'})",
        2: f"source {secret}: {secret} leads outside the artifact directory {base} of its run {run_id} (to {secret})",
        3: f"source {escape}: {escape} leads outside the artifact directory {base} of its run {run_id} (to {secret})",
    }
    for version, message in refused.items():
        out = tmp_path / f"v{version}"
        r = zoo.gdwm("zoo", "load", "args.name=gdwm-x", f"args.version={version}", f"args.out={out}")
        assert r.returncode == 1, r.stdout + r.stderr
        assert f"gdwm zoo load: ZooError: gdwm-x version {version}: source " in r.stderr
        assert f"{message}; refusing to copy it" in r.stderr
        assert not out.exists()
    (run_dir / "zoo" / "gdwm-x" / "link.pth").unlink()
    _ok(zoo.gdwm("zoo", "load", "args.name=gdwm-x", "args.version=1", f"args.out={tmp_path / 'v1'}"))
    got = _files(tmp_path / "v1")
    assert got.pop(".gdwm-download").startswith(b'{"gdwm": "download"')  # the folder is gdwm's now
    assert got == {"w.bin": b"ok", "MLmodel": (run_dir / "zoo" / "gdwm-x" / "MLmodel").read_bytes()}


def test_zoo_load_writes_only_into_a_folder_gdwm_owns(tmp_path, capsys):
    """args.out naming a user's folder is refused and left as it was; a fresh one is created and marked."""
    from gdwm.cli import main

    work = tmp_path / "w"
    backend = TrackingBackend(f"sqlite:///{work.resolve()}/mlflow.db", "gdwm", str(work / "mlartifacts"))
    component = tmp_path / "c"
    component.mkdir()
    (component / "w.bin").write_bytes(b"weights")
    assert backend.register_component(backend.create_run("r", {}), "gdwm-x", str(component), "v", {}) == 1
    backend.close()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "w.bin").write_bytes(b"my own file")
    args = ["zoo", "load", f"workdir={work}", "args.name=gdwm-x", "args.version=1"]
    assert main([*args, f"args.out={mine}"]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (  # after MLflow's own lines creating the store
        f"gdwm zoo load: CommandError: {mine}: not a gdwm download directory (w.bin is not gdwm's, and there is no "
        ".gdwm-download); choose an empty or new directory"
    )
    assert (mine / "w.bin").read_bytes() == b"my own file" and sorted(os.listdir(mine)) == ["w.bin"]
    assert main([*args, f"args.out={tmp_path / 'fresh'}"]) == 0
    assert (tmp_path / "fresh" / ".gdwm-download").is_file() and "MLmodel" in os.listdir(tmp_path / "fresh")


def test_a_sweep_tags_the_versions_its_trials_registered_with_their_lineage(tmp_path):
    """The versions a sweep's stages registered carry the sweep, the row and the trial's run (a trial whose stages
    registered nothing skips the zoo search: ``StageResult.registered``)."""
    z = Zoo(tmp_path)
    _ok(z.gdwm("sweep", "sweep=toy_zoo_rows", f"data.root={z.data}"))
    trials = {r.data.tags["gdwm.row"]: r.info.run_id for r in z.client().search_runs(
        [z.client().get_experiment_by_name("gdwm").experiment_id], "tags.`gdwm.kind` = 'trial'")}  # fmt: skip
    lineage = {v["gdwm.row"]: (v["gdwm.sweep"], v["gdwm.trial"]) for v in z.versions().values()}
    assert lineage == {"v3": ("toy_zoo_rows", trials["v3"]), "v4": ("toy_zoo_rows", trials["v4"])}
