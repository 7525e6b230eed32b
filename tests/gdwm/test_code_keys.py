"""Code is an input of the cache key: a temporary plugin package on GDWM_CONF_PATH, edited between real CLI runs.

The plugin ``codeplug`` has four stages in four modules: ``prep`` (per scene), ``side`` (after prep), ``lora``
(after prep; the only importer of ``codeplug/lora_math.py``) and ``evaluate`` (after lora; an evaluation stage).
Executions are counted from the stages' own log; library versions come from a fake ``toylib`` distribution.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import json
import os
import subprocess
import sys
import textwrap
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import mlflow
import pytest

from gdwm import fingerprint
from gdwm.cache import Cache
from gdwm.executor import RunEnv, _open_stage_run, code_artifact, read_code_record
from gdwm.tracking import RunWrite
from gdwm.tracking.backend import TrackingBackend
from tests.gdwm.toydata import make_dataset

pytestmark = pytest.mark.heavy(2)

REPO = Path(__file__).resolve().parents[2]

COMMON = '''
"""Shared by every stage: logs each execution."""
import os
from pathlib import Path


def record(ctx):
    with open(Path(os.environ["GDWM_TEST_DIR"]) / "executions.log", "a") as f:
        f.write(f"{ctx.name} {ctx.scene or '-'}\\n")
'''

PREP = """
from gdwm.stage import stage

from codeplug.common import record


@stage("prep", "1", config=["stage.prep"], per_scene=True)
def prep(ctx):
    record(ctx)
    (ctx.out_dir / "value.txt").write_text(str(len(ctx.scene) * ctx.cfg("stage.prep")["scale"]))
"""

SIDE = """
from gdwm.stage import stage

from codeplug.common import record


@stage("side", "1", config=[], upstream=["prep"])
def side(ctx):
    record(ctx)
    (ctx.out_dir / "n.txt").write_text(str(len(ctx.upstream["prep"].scenes)))
"""

LORA = """
import json

from gdwm.stage import stage

from codeplug.common import record
from codeplug.lora_math import weight


@stage("lora", "1", config=["stage.lora"], upstream=["prep"], libraries=["toylib"])
def lora(ctx):
    record(ctx)
    (ctx.out_dir / "w.json").write_text(json.dumps({"w": weight(ctx.cfg("stage.lora")["rank"])}))
"""

LORA_MATH = '''
"""The LoRA's arithmetic: imported by the lora stage only."""


def weight(rank):
    # the rank scales the weight
    return 10.0 * rank
'''

EVALUATE = """
import json

from gdwm.stage import stage

from codeplug.common import record


@stage("evaluate", "1", config=[], upstream=["lora"], evaluation=True)
def evaluate(ctx):
    record(ctx)
    w = json.loads((ctx.upstream["lora"].path / "w.json").read_text())["w"]
    (ctx.out_dir / "metrics.json").write_text(json.dumps({"plug/score": w}))
    return {"plug/score": w}
"""

PIPELINE = """
defaults:
  - /schema/pipeline/pipeline@_here_
  - _self_

name: codeplug
stages:
  prep: {_target_: codeplug.prep.prep}
  side: {_target_: codeplug.side.side}
  lora: {_target_: codeplug.lora.lora}
  evaluate: {_target_: codeplug.evaluate.evaluate}
"""

EXPERIMENT = """
# @package _global_
defaults:
  - override /pipeline: codeplug

stage:
  prep: {scale: 2}
  lora: {rank: 4}
"""

BENCHMARK = """
defaults:
  - /schema/benchmark/benchmark@_here_
  - _self_

name: codeplug
overrides: [experiment=codeplug]
targets: [evaluate]
metrics:
  - {name: plug/score, direction: higher, tolerance: 1.0}
"""

ALL = {"prep": 3, "side": 1, "lora": 1, "evaluate": 1}


class Plugin:
    """The plugin package, its config tree, a dataset, a workdir, and a fake library version."""

    def __init__(self, root: Path):
        self.root = root
        self.pkg = root / "plug" / "codeplug"
        self.pkg.mkdir(parents=True)
        for name, text in {"__init__": "", "common": COMMON, "prep": PREP, "side": SIDE, "lora": LORA,
                           "lora_math": LORA_MATH, "evaluate": EVALUATE}.items():  # fmt: skip
            (self.pkg / f"{name}.py").write_text(text.lstrip())
        conf = root / "plug" / "conf"
        for rel, text in {"pipeline/codeplug.yaml": PIPELINE, "experiment/codeplug.yaml": EXPERIMENT,
                          "benchmark/codeplug.yaml": BENCHMARK}.items():  # fmt: skip
            (conf / rel).parent.mkdir(parents=True, exist_ok=True)
            (conf / rel).write_text(text.lstrip())
        self.conf = conf
        self.site = root / "site"
        self.data = make_dataset(root / "ds")
        self.work = root / "w"
        self.library("1.0")

    def library(self, v: str) -> None:
        """Install a fake ``toylib`` distribution of version ``v`` (what importlib.metadata reports)."""
        for old in self.site.glob("toylib-*.dist-info"):
            for f in old.iterdir():
                f.unlink()
            old.rmdir()
        d = self.site / f"toylib-{v}.dist-info"
        d.mkdir(parents=True)
        (d / "METADATA").write_text(f"Metadata-Version: 2.1\nName: toylib\nVersion: {v}\n")

    def env(self) -> dict:
        env = {k: v for k, v in os.environ.items() if not k.startswith("GDWM_TEST_")}
        path = os.pathsep.join([str(self.site), str(self.root / "plug"), str(REPO)])
        env.update(PYTHONPATH=path, GDWM_CONF_PATH=str(self.conf), GDWM_TEST_DIR=str(self.root),
                   GDWM_LOCAL_CACHE=str(self.root / "local"))  # fmt: skip
        return env

    def gdwm(self, *args: str) -> subprocess.CompletedProcess:
        (self.root / "executions.log").write_text("")
        base = [f"workdir={self.work}", f"data.root={self.data}"]
        cmd = [sys.executable, "-m", "gdwm", *args[:1], "experiment=codeplug", *base, *args[1:]]
        return subprocess.run(cmd, env=self.env(), capture_output=True, text=True, timeout=600)

    def run(self, *overrides: str) -> subprocess.CompletedProcess:
        r = self.gdwm("run", *overrides)
        assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-5000:]}"
        return r

    def executions(self) -> Counter:
        lines = (self.root / "executions.log").read_text().splitlines()
        return Counter(line.split()[0] for line in lines)

    def edit(self, module: str, old: str, new: str) -> None:
        path = self.pkg / f"{module}.py"
        text = path.read_text()
        assert old in text, (module, old)
        path.write_text(text.replace(old, new))

    def stage_runs(self, stage: str) -> list:
        client = mlflow.MlflowClient(f"sqlite:///{self.work.resolve()}/mlflow.db")
        exp = client.get_experiment_by_name("gdwm")
        return client.search_runs([exp.experiment_id], f"tags.`gdwm.stage` = '{stage}'")


@pytest.fixture(scope="module")
def plug(tmp_path_factory) -> Plugin:
    p = Plugin(tmp_path_factory.mktemp("codeplug"))
    p.run()
    assert p.executions() == ALL
    return p


# ---- the fingerprint itself, in process --------------------------------------------------------------------------
def test_comments_docstrings_and_formatting_do_not_count():
    a = 'def f(x):\n    """Doc."""\n    return x + 1  # add one\n'
    b = "# header\ndef f(  x ):\n\n    return (x+1)\n"
    c = "def f(x):\n    return x + 2\n"
    assert fingerprint.normalized_digest(a) == fingerprint.normalized_digest(b)
    assert fingerprint.normalized_digest(a) != fingerprint.normalized_digest(c)


def test_the_closure_follows_first_party_imports_only(tmp_path, monkeypatch):
    pkg = tmp_path / "fpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import numpy\nfrom . import b\n\ndef f():\n    from fpkg.c import g\n    return g\n")
    (pkg / "b.py").write_text("import json\n")
    (pkg / "c.py").write_text("import torch\ndef g():\n    return 1\n")
    (pkg / "d.py").write_text("")  # imported by nobody
    monkeypatch.syspath_prepend(str(tmp_path))
    fingerprint.clear()
    modules, third = fingerprint.closure(["fpkg.a"], {"fpkg"})
    assert sorted(m.path for m in modules.values()) == ["fpkg/__init__.py", "fpkg/a.py", "fpkg/b.py", "fpkg/c.py"]
    assert {"numpy", "torch", "json"} <= third
    assert "gdwm" not in {m.partition(".")[0] for m in modules}


def test_pipeline_stages_fingerprint_their_own_code_and_libraries():
    from gdwm.config import load_config
    from gdwm.dag import load_pipeline
    from gdwm.executor import stage_config

    cfg = load_config(["experiment=demo"])
    pipe = load_pipeline(cfg, None)
    fps = {n: fingerprint.stage_fingerprint(pipe.stages[n], stage_config(pipe.stages[n], cfg)) for n in pipe.order}
    assert "pipelines/stages/reconstruct.py" in fps["reconstruct"].files
    assert "pipelines/stages/lora.py" not in fps["reconstruct"].files
    assert "pipelines/stages/lora.py" in fps["lora"].files
    assert "torch" in fps["reconstruct"].libraries and "peft" not in fps["reconstruct"].libraries
    assert {"peft", "transformers"} <= fps["lora"].libraries.keys()
    assert "pycocoevalcap" in fps["evaluate_qa"].libraries
    assert fps["reconstruct"].digest != fps["lora"].digest


# ---- end to end through the CLI -----------------------------------------------------------------------------------
def test_the_manifest_and_the_stage_run_record_the_fingerprint(plug):
    cache = Cache(plug.work / "cache")
    [m] = cache.entries("lora")
    assert m.code is not None and set(m.code["files"]) >= {"codeplug/lora.py", "codeplug/lora_math.py"}
    assert "codeplug/side.py" not in m.code["files"]
    assert m.code["libraries"]["toylib"] == "1.0" and "torch" in m.code["libraries"]  # via gdwm.training
    [run] = plug.stage_runs("lora")
    assert run.data.tags["gdwm.code"] == m.code["digest"]
    client = mlflow.MlflowClient(f"sqlite:///{plug.work.resolve()}/mlflow.db")
    # the record is the launch's, once per fingerprint: on the stage runs' parent, none on the stage run itself
    launch = run.data.tags["mlflow.parentRunId"]
    assert run.data.tags["gdwm.code_run"] == launch
    assert "code.json" not in {a.path for a in client.list_artifacts(run.info.run_id)}
    assert read_code_record(client, run, str(plug.root)) == m.code
    records = {a.path for a in client.list_artifacts(launch, "code")}
    assert code_artifact(m.code["digest"]) in records and len(records) == len(ALL)  # one per stage's code here


def test_a_stage_run_points_at_its_launchs_code_record_or_holds_its_own(tmp_path):
    """A stage whose code the launch recorded points there (``gdwm.code_run``); one it did not (a stage the plan
    thought cached, found corrupt) holds ``code.json`` itself, as runs of older gdwm do: both read the same way."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    backend = TrackingBackend(uri, "gdwm", str(tmp_path / "art"))
    launch = backend.create_run("launch", {})
    recorded = {"digest": "d1", "files": {"a.py": "h1"}, "libraries": {"torch": "2.13.0"}}
    own = {"digest": "d2", "files": {"b.py": "h2"}, "libraries": {}}
    backend.write([RunWrite(launch, texts={code_artifact("d1"): json.dumps(recorded)})])
    env = RunEnv(cache_uri=str(tmp_path / "cache"), data_root=str(tmp_path), data_fingerprint="toy", scenes=(),
                 checkpoint_root=str(tmp_path / "ckpt"), sink=backend, parent_run_id=launch, progress=None,
                 resources={}, code={"a": recorded, "b": own}, code_recorded=frozenset({"d1"}))  # fmt: skip
    ids = [_open_stage_run(env, SimpleNamespace(name=n, version="1"), f"key-{n}", {"x": 1}) for n in "ab"]
    client = mlflow.MlflowClient(uri)
    a, b = (client.get_run(i) for i in ids)
    assert (a.data.tags["gdwm.code"], a.data.tags["gdwm.code_run"]) == ("d1", launch)
    assert [x.path for x in client.list_artifacts(a.info.run_id)] == []
    assert (b.data.tags["gdwm.code"], "gdwm.code_run" in b.data.tags) == ("d2", False)
    assert [x.path for x in client.list_artifacts(b.info.run_id)] == ["code.json"]
    assert read_code_record(client, a, str(tmp_path / "dl-a")) == recorded
    assert read_code_record(client, b, str(tmp_path / "dl-b")) == own
    backend.close()


def test_a_comment_docstring_or_reformat_reruns_nothing(plug):
    plug.edit("lora_math", "# the rank scales the weight", "# the rank, times ten")
    plug.edit("lora_math", '"""The LoRA\'s arithmetic: imported by the lora stage only."""', '"""Arithmetic."""')
    plug.edit("lora_math", "    return 10.0 * rank", "    return (10.0\n            * rank)")
    r = plug.run()
    assert plug.executions() == {}
    assert "all 6 stage outputs cached and verified" in r.stdout


def test_a_function_body_edit_reruns_lora_and_descendants_only(plug):
    plug.edit("lora_math", "10.0", "20.0")
    dry = plug.gdwm("run", "--dry-run")
    assert dry.returncode == 0, dry.stderr
    assert plug.executions() == {}
    why = dry.stdout.split("why stages re-run", 1)[1].splitlines()[1:]
    assert [line.split()[0] for line in why if line.strip()] == ["lora", "evaluate"]
    assert "code: codeplug/lora_math.py" in dry.stdout
    assert "upstream: lora" in dry.stdout
    plug.run()
    assert plug.executions() == {"lora": 1, "evaluate": 1}
    cache = Cache(plug.work / "cache")
    assert len(cache.entries("lora")) == 2 and len(cache.entries("prep")) == 3  # the old code's entry is kept


def test_a_library_version_reruns_the_stages_that_declare_it(plug):
    plug.library("2.0")
    dry = plug.gdwm("run", "--dry-run")
    assert "library: toylib 1.0 -> 2.0" in dry.stdout
    plug.run()
    assert plug.executions() == {"lora": 1, "evaluate": 1}


def test_cache_reuse_all_takes_old_code_and_the_plan_says_so(plug):
    plug.edit("lora_math", "20.0", "30.0")
    dry = plug.gdwm("run", "--dry-run", "cache.reuse=all")
    assert "cached (other code)" in dry.stdout
    plug.run("cache.reuse=all")
    assert plug.executions() == {}
    pinned = plug.gdwm("run", "--dry-run", "cache.reuse_stages=[lora]")
    assert "cached (other code)" in pinned.stdout
    bad = plug.gdwm("run", "--dry-run", "cache.reuse_stages=[lroa]")
    assert bad.returncode == 2
    assert "cache.reuse_stages: no stage 'lroa' in pipeline 'codeplug'" in bad.stderr


def test_regress_recomputes_changed_code_and_catches_a_planted_regression(plug):
    r = plug.gdwm("regress", "benchmark=codeplug", "--set-baseline")
    assert r.returncode == 0, r.stdout + r.stderr
    assert plug.executions() == {"lora": 1, "evaluate": 1}  # lora: code changed (30.0); evaluate: always
    assert "recomputed" in r.stdout
    # a planted regression: the weight drops from 30 * rank to 3 * rank
    plug.edit("lora_math", "30.0", "3.0")
    stale = plug.gdwm("regress", "benchmark=codeplug", "cache.reuse=all")  # what gdwm did before code was keyed
    assert stale.returncode == 0, stale.stdout + stale.stderr
    assert "reused (other code)" in stale.stdout
    honest = plug.gdwm("regress", "benchmark=codeplug")
    assert honest.returncode == 1, honest.stdout + honest.stderr
    assert "regression: plug/score 120 -> 12" in honest.stderr
    assert "code changed since the baseline: lora" in honest.stdout
    assert _cells(honest.stdout, "lora")[:2] == ["lora", "recomputed"]
    assert _cells(honest.stdout, "prep")[:2] == ["prep", "reused (same code)"]
    assert _cells(honest.stdout, "evaluate")[:2] == ["evaluate", "recomputed"]
    # --fresh: every stage recomputes (cache.reuse=none; tests/gdwm/test_checkpoints.py runs that mode end to end)
    from gdwm.config import load_config
    from gdwm.regress import honest_overrides

    cfg = load_config(["targets=[evaluate_qa]", "cache.recompute=[tokenizer]"])  # the shipped pipeline
    assert honest_overrides(cfg, fresh=False) == ["cache.recompute=[tokenizer,evaluate_qa]"]
    assert honest_overrides(cfg, fresh=True) == ["cache.recompute=[tokenizer,evaluate_qa]", "cache.reuse=none"]


def _cells(text: str, first: str) -> list[str]:
    """The cells of the last table row of ``text`` whose first cell is ``first`` (regress prints its stages last)."""
    for line in reversed(text.splitlines()):
        cells = [c.strip() for c in line.strip().strip("│┃").split("│")]
        if cells and cells[0] == first:
            return cells
    raise AssertionError(f"no row '{first}' in\n{text}")


def test_unhashable_module_falls_back_to_version_and_is_named(tmp_path, monkeypatch):
    pkg = tmp_path / "binpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / f"fast{importlib.machinery.EXTENSION_SUFFIXES[0]}").write_bytes(b"\0")  # a compiled module: no source
    monkeypatch.syspath_prepend(str(tmp_path))
    fingerprint.clear()
    src = textwrap.dedent("""
        from gdwm.stage import stage

        @stage("bin", "1")
        def bin_stage(ctx):
            import binpkg.fast
    """)
    (pkg / "stages.py").write_text(src)
    modules, _ = fingerprint.closure(["binpkg.stages"], {"binpkg"})
    assert modules["binpkg.fast"].digest == fingerprint.UNHASHABLE
    mod = importlib.import_module("binpkg.stages")
    fp = fingerprint.stage_fingerprint(mod.bin_stage, {})
    assert fp.unhashable == ["binpkg/fast"]  # its digest is a constant: the stage version has to say it changed


def test_an_entry_of_an_older_gdwm_is_unknown_code_reused_only_under_all(tmp_path):
    from gdwm.cache import MANIFEST, Manifest, cache_key
    from gdwm.executor import ALL, SAME_CODE, find_entry

    src = tmp_path / "src"
    src.mkdir()
    (src / "w.json").write_text("{}")
    cache = Cache(tmp_path / "cache")
    base = cache_key("lora", "1", {"stage.lora": {"rank": 4}}, {}, "data")  # the old key: no code in it
    old = cache.publish("lora", base, src, config={"stage.lora": {"rank": 4}}, upstream={}, data_fingerprint="data",
                        version="1")  # fmt: skip
    entry = Path(cache.entry_uri("lora", base)) / MANIFEST
    text = json.loads(entry.read_text())
    del text["code"], text["base"]  # as gdwm wrote manifests before code was keyed
    entry.write_text(json.dumps(text))
    assert Manifest.from_json(entry.read_text()).code is None
    new_key = cache_key("lora", "1", {"stage.lora": {"rank": 4}}, {}, "data", code="c0de")
    assert find_entry(cache, "lora", new_key, base, SAME_CODE) == (None, "")
    hit, how = find_entry(cache, "lora", new_key, base, ALL)
    assert (hit.key, hit.code, how) == (old.key, None, "unknown code")


def test_the_plan_names_an_unhashable_module_once(tmp_path, monkeypatch, capsys):
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from gdwm.plan import code_settings

    pkg = tmp_path / "binplan"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / f"fast{importlib.machinery.EXTENSION_SUFFIXES[0]}").write_bytes(b"\0")
    (pkg / "stages.py").write_text(
        "from gdwm.stage import stage\n\n\n@stage('bin', '1')\ndef bin_stage(ctx):\n    import binplan.fast\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    fingerprint.clear()
    sd = importlib.import_module("binplan.stages").bin_stage
    pipe = SimpleNamespace(name="p", stages={"bin": sd}, order=["bin"])
    cfg = OmegaConf.create({"cache": {"reuse": "same_code", "reuse_stages": [], "recompute": []}})
    first = code_settings(cfg, pipe, ["bin"], "gdwm run")
    again = code_settings(cfg, pipe, ["bin"], "gdwm run")
    assert first == again and first["code"]["bin"]["files"]["binplan/fast"] == fingerprint.UNHASHABLE
    err = capsys.readouterr().err
    assert err.count("binplan/fast has no Python source to hash") == 1
    assert "bump the stage's version when it changes" in err
