"""Every YAML under conf/ composes; bad overrides are exit-2 errors naming the key."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from gdwm.config import ConfigError, conf_dir, load_config

CONF = conf_dir()
GROUP_YAMLS = sorted(p.relative_to(CONF) for p in CONF.rglob("*.yaml") if p.parent != CONF)


def _gdwm(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, cwd=cwd)


def test_conf_tree_has_the_design_groups():
    groups = {p.parts[0] for p in GROUP_YAMLS}
    assert {"data", "cluster", "tracking"} <= groups
    assert {p.stem for p in (CONF / "data").glob("*.yaml")} == {"synthetic_mini", "nuscenes", "gaussiandwm_release",
                                                                 "nuinteract", "nuinstruct", "omnidrive"}  # fmt: skip


def test_root_config_composes_with_defaults(tmp_path):
    cfg = load_config([f"workdir={tmp_path}"])
    assert cfg.pipeline.name == "gaussiandwm_pp"
    assert list(cfg.pipeline.stages) == [
        "llm",
        "reconstruct",
        "distill",
        "tokenizer",
        "lora",
        "evaluate_qa",
        "diffusion_vae",
        "diffusion",
        "evaluate_gen",
    ]
    assert cfg.data.name == "synthetic_mini"
    assert cfg.data.root == f"{tmp_path}/data/synthetic_mini"
    assert cfg.tracking.uri == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    assert cfg.cluster.num_cpus == 2


# Options valid only with another key set: the identity adapter takes exactly K_f candidates (K_c must equal K_f).
COMPANIONS = {"model/fine_adapter/identity.yaml": ["model.selector.k_c=16"]}


@pytest.mark.parametrize("rel", GROUP_YAMLS, ids=str)
def test_every_yaml_composes(rel, tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:5000")
    group = "/".join(rel.parts[:-1])
    cfg = load_config([f"workdir={tmp_path}", f"{group}={rel.stem}", *COMPANIONS.get(str(rel), [])])
    node = cfg
    if "@package _global_" not in (CONF / rel).read_text().splitlines()[0]:
        for part in rel.parts[:-1]:
            node = node[part]
    # The option's own YAML values must be what ended up in the config.
    own = {k: v for k, v in yaml.safe_load((CONF / rel).read_text()).items() if k != "defaults"}
    for key, value in own.items():
        assert _holds(node[key], value), key


def _holds(node, value) -> bool:
    """``node`` (composed) carries every value the YAML set, nested mappings included; interpolations aside."""
    if isinstance(value, str) and "${" in value:
        return True
    if isinstance(value, dict):
        return all(k in node and _holds(node[k], v) for k, v in value.items())
    if isinstance(value, list) and any(isinstance(v, dict) or (isinstance(v, str) and "${" in v) for v in value):
        return len(node) == len(value) and all(_holds(n, v) for n, v in zip(node, value, strict=True))
    return node == value


def test_server_tracking_takes_uri_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "https://mlflow.example.internal")
    cfg = load_config([f"workdir={tmp_path}", "tracking=server"])
    assert cfg.tracking.uri == "https://mlflow.example.internal"
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    with pytest.raises(ConfigError, match=r"tracking\.uri.*MLFLOW_TRACKING_URI"):
        load_config([f"workdir={tmp_path}", "tracking=server"])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("data.num_scnes=3", "unknown config key 'data.num_scnes'; allowed keys here: name, root, builder"),
        ("bogus=1", "unknown config key 'bogus'; allowed keys here: workdir, source, overwrite, seed, seeds, data"),
        ("data.num_scenes=many", "invalid value for 'data.num_scenes': Value 'many' of type 'str' could not be"),
        (
            "data=synthetic_maxi",
            "config group 'data' has no option 'synthetic_maxi'; allowed values: "
            "gaussiandwm_release, nuinstruct, nuinteract, nuscenes, omnidrive, synthetic_mini.",
        ),
        ("cluster=a100x61", "config group 'cluster' has no option 'a100x61'; allowed values: a100x16, local, sim."),
        ("data.name=???", "missing mandatory value 'data.name': set it with data.name=VALUE."),
    ],
)
def test_bad_overrides_exit_2_naming_the_key(override, message, tmp_path):
    r = _gdwm("config", "show", f"workdir={tmp_path}", override)
    assert r.returncode == 2, r.stderr
    assert message in r.stderr.replace("\n", " ")
    assert r.stdout == ""
    assert not (tmp_path / "data").exists()


def test_config_show_prints_resolved_yaml(tmp_path):
    r = _gdwm("config", "show", f"workdir={tmp_path}", "data.num_scenes=3")
    assert r.returncode == 0, r.stderr
    assert "num_scenes: 3" in r.stdout
    assert f"root: {tmp_path}/data/synthetic_mini" in r.stdout
    assert "${" not in r.stdout


def test_composing_a_config_imports_no_heavy_library():
    # Every gdwm command composes first: torch, transformers, diffusers, mlflow and ray load only when used.
    code = (
        "import sys; from gdwm.config import load_config; load_config(['experiment=demo']); "
        "print(sorted(m for m in ('torch', 'transformers', 'diffusers', 'mlflow', 'ray') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_compare_takes_its_default_layout_from_conf_and_the_command_line_wins(tmp_path):
    assert load_config([f"workdir={tmp_path}", "args=compare"]).compare.name == "nuinteract"  # conf/args/compare.yaml
    assert load_config([f"workdir={tmp_path}", "args=compare", "compare=omnidrive"]).compare.name == "omnidrive"
    assert load_config([f"workdir={tmp_path}", "compare=omnidrive", "args=compare"]).compare.name == "omnidrive"
    assert load_config([f"workdir={tmp_path}"]).compare is None


def test_sweep_and_benchmark_defaults_name_no_pipeline():
    from gdwm.config import BenchmarkConfig, SweepConfig

    assert SweepConfig(name="s").layout is None  # gdwm compare's default layout
    assert BenchmarkConfig(name="b").targets == []  # the whole pipeline


def test_a_workdir_is_a_path_never_a_uri(tmp_path, monkeypatch):
    """A workdir named like a URI's query and fragment (`w #1?x=1%20`): the store, its artifacts and the cache land
    inside it, nowhere else."""
    from gdwm.cache import Cache, cache_key
    from gdwm.config import drop_mlflow_litter, sqlite_path
    from gdwm.tracking import TrackingBackend

    monkeypatch.chdir(tmp_path)
    work = tmp_path / "w #1?x=1%20"
    cfg = load_config(["workdir='w #1?x=1%20'"])  # quoted, as a shell user writes it for Hydra
    assert sqlite_path(cfg.tracking.uri) == f"{work}/mlflow.db"
    backend = TrackingBackend(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_location)
    run = backend.create_run("r", {})
    backend.log_text(run, "hello", "note.txt")
    backend.end_run(run)
    src = tmp_path / "src"
    src.mkdir()
    (src / "f").write_text("x")
    key = cache_key("s", "1", {}, {}, "d")
    Cache(cfg.cache.uri).publish("s", key, src, config={}, upstream={}, data_fingerprint="d", version="1")
    drop_mlflow_litter(cfg.tracking.uri)  # what every gdwm command does on its way out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src", "w #1?x=1%20"]
    inside = {p.relative_to(work).parts[0] for p in work.rglob("*")}
    assert {"mlflow.db", "mlflow.db.lock", "mlartifacts", "cache"} <= inside
    assert [p.read_text() for p in (work / "mlartifacts").rglob("note.txt")] == ["hello"]
