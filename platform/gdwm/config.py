"""Composing ``conf/`` with Hydra's compose API, validated against structured-config schemas.

Schemas of the platform's own groups live here; schemas of stages, datasets and model
variants are registered by plugins (entry-point group ``gdwm.plugins``: a callable taking the
ConfigStore), so gdwm never imports ``pipelines`` or ``model_zoo`` by name. Each YAML option
pulls its schema from the ``schema/<group>/<name>`` defaults entry, so an unknown key, a wrong
type or a missing mandatory value is caught at compose time.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import urllib.parse
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from functools import cache
from importlib.metadata import entry_points
from pathlib import Path
from typing import Annotated, Any

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException, MissingConfigException
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError, MissingMandatoryValue, OmegaConfBaseException

from gdwm.compare.layout import Direction
from gdwm.fromenv import env_keys
from gdwm.knobs import SEED, Ge, Gt, Interval, Len, check_ranges
from gdwm.simcluster import SimConfig

PLUGIN_GROUP = "gdwm.plugins"
MAIN_GROUPS = ("experiment", "data", "pipeline", "cluster", "tracking", "sweep", "benchmark", "compare")


class ConfigError(Exception):
    """A config that does not compose or validate; the CLI prints it and exits 2."""


@dataclass
class StageResources:
    """Resources of one stage resource class (``cpu``, ``gpu``, ``train``, ``eval``)."""

    num_cpus: Annotated[float, Gt(0)] = 1.0
    """CPUs per task, actor or training worker."""
    num_gpus: Annotated[float, Ge(0)] = 0.0
    """GPUs per task, actor or training worker (fractions allowed for evaluation)."""
    num_workers: Annotated[int, Ge(0)] = 1
    """Parallel actors (per-scene stages) or Ray Train workers (training stages); 0 = in-process."""


@dataclass
class NodeShape:
    """A kind of node of a cluster: what Ray can schedule on each (a head with ``num-cpus: 0`` is not one)."""

    num_cpus: Annotated[float, Ge(0)] = 1.0
    """CPUs Ray schedules on the node."""
    num_gpus: Annotated[float, Ge(0)] = 0.0
    """GPUs of the node."""
    count: Annotated[int, Ge(1)] = 1
    """Nodes of this shape."""


@dataclass
class ClusterConfig:
    """Where Ray runs and what each stage resource class asks for."""

    name: str = "local"
    """Cluster profile name."""
    address: str | None = None
    """Ray address (``auto``, ``HOST:PORT`` or ``ray://...``); null starts a local Ray with ``num_cpus`` (or the
    ``sim`` cluster)."""
    connect_timeout_s: Annotated[float, Gt(0)] = 10.0
    """How long ``address`` may take to answer before the run gives up with one line naming it (exit 1)."""
    num_cpus: Annotated[int | None, Ge(1)] = 2
    """CPUs of the local Ray (ignored when ``address`` is set)."""
    num_gpus: Annotated[int, Ge(0)] = 0
    """GPUs of the local Ray (ignored when ``address`` is set)."""
    sim: SimConfig | None = None
    """A local multi-node Ray cluster gdwm starts and stops itself (``cluster=sim``, see ``gdwm.simcluster``);
    null = none. ``num_cpus``/``num_gpus`` are ignored then."""
    resources: dict[str, StageResources] = field(
        default_factory=lambda: {k: StageResources() for k in ("cpu", "gpu", "train", "eval")}
    )
    """Per resource class: what a stage of that class requests."""
    nodes: list[NodeShape] = field(default_factory=list)
    """The nodes tasks and actors run on, for a cluster not connected yet (a live one reports its own through
    ``ray.nodes()``); empty with ``address: null`` = one node of ``num_cpus`` and ``num_gpus``. Every launch checks
    each stage's resource shape against them (``gdwm.capacity``)."""


@dataclass
class TrackingConfig:
    """MLflow tracking store."""

    name: str = "sqlite"
    """Tracking profile name."""
    uri: str = "${sqlite_uri:${workdir}/mlflow.db}"
    """MLflow tracking URI (sqlite file under the workdir by default; ``sqlite_uri`` quotes the path, so a workdir
    named ``w #1?x=1`` is a path, not a URI's query)."""
    artifact_location: str | None = "${file_uri:${workdir}/mlartifacts}"
    """Artifact root for new experiments; null lets the server decide."""
    experiment: Annotated[str, Len(1, 256)] = "gdwm"
    """MLflow experiment name (a store on PostgreSQL holds at most 256 characters)."""
    single_writer: bool = True
    """Route every write through one process (required for sqlite)."""
    system_metrics_interval_s: Annotated[float, Ge(0)] = 10.0
    """Sampling interval of MLflow system metrics on stage runs; 0 turns them off."""
    lock_timeout_s: Annotated[float, Gt(0)] = 120.0
    """A sqlite store's writers take turns through ``<db>.lock``: how long one waits for another (a hung or stopped
    gdwm, named by its pid) before giving up with one line."""


class ReuseMode(StrEnum):
    same_code = "same_code"
    all = "all"
    none = "none"


@dataclass
class CacheConfig:
    """Content-addressed stage cache; see ``gdwm.cache`` and ``gdwm.fingerprint``."""

    uri: str = "${abspath:${workdir}}/cache"
    """A pyarrow.fs URI or local path: file:///..., s3://bucket/prefix, gs://..."""
    verify: bool = True
    """Re-hash every file of an entry when a run uses it (a corrupted entry is reported and recomputed, with its
    training checkpoints); false trusts a complete manifest (faster on big entries, blind to bit rot)."""
    reuse: ReuseMode = ReuseMode.same_code
    """Which entries count as a hit. ``same_code``: only one computed by the same code and libraries (the key holds
    their fingerprint); ``all``: else the newest entry of the same config, version and data under any code (old
    code included; the plan says so); ``none``: recompute every stage and replace its entry."""
    reuse_stages: list[str] = field(default_factory=list)
    """Stages pinned to ``all`` whatever ``reuse`` says: an earlier entry of the same config is reused even if
    their code changed (e.g. ``[reconstruct]`` where a re-run costs hours of a 16-GPU cluster)."""
    recompute: list[str] = field(default_factory=list)
    """Stages that recompute even when an entry of the same code exists, replacing it (``gdwm regress`` sets its
    evaluation targets here)."""


@dataclass
class CacheArgs:
    """``gdwm cache ls|gc|invalidate`` (set them as ``args.KEY=VALUE``; gc's limits are ``--flags``)."""

    stage: str | None = None
    """ls: list this stage's entries (null = one summary row per stage); gc: only this stage; invalidate: required."""
    key: str | None = None
    """invalidate: the entry's key or a prefix of it (>= 8 hex characters) matching exactly one entry."""
    grace: str = "1h"
    """gc: never delete an entry created or used within this age (s, m, h, d, w), so a driver that just published or
    looked it up can still read it."""


@dataclass
class StatusArgs:
    """``gdwm status [args.sweep=NAME] [args.state=STATE] [args.limit=N]``."""

    sweep: str | None = None
    """Show this sweep alone, with its rows."""
    state: str | None = None
    """Keep launches in this state: running, done, failed or killed."""
    limit: Annotated[int, Ge(1)] = 20
    """At most this many launches per list, newest first."""


@dataclass
class ReproduceArgs:
    """``gdwm reproduce RUN_ID [workdir=DIR]`` (``RUN_ID`` sets ``args.run``; ``gdwm.reproduce``)."""

    run: str | None = None
    """The run to reproduce, by id or a unique prefix of at least 8 characters: a trial, a row (its seeds), a
    ``gdwm run`` or a sweep (every trial)."""
    store: str | None = None
    """Where it is recorded: a workdir or an MLflow tracking URI. null = the configured store (``tracking.uri``) as
    the command line sets it without its ``workdir=``, which names the fresh workdir."""


class SceneErrorPolicy(StrEnum):
    fail = "fail"
    skip = "skip"


@dataclass
class RunSettings:
    """How ``gdwm run`` executes the DAG."""

    on_scene_error: SceneErrorPolicy = SceneErrorPolicy.fail
    """Per-scene user errors: ``fail`` the stage after the other scenes finish, or ``skip`` the scene."""
    max_retries: Annotated[int, Ge(0)] = 3
    """Retries of a task or actor call whose worker process died (user errors are not retried)."""
    checkpoint_every: Annotated[int, Ge(1)] = 1
    """Training stages report a checkpoint every N steps."""
    max_failures: Annotated[int, Ge(0)] = 2
    """Ray Train FailureConfig: worker-group restarts from the last checkpoint."""
    plan: bool = False
    """Print the plan (cached / to run / blocked per stage and scene) and exit; same as --dry-run."""
    live: bool = True
    """Show the live board while running (off when stdout is not a terminal: then one line per event)."""
    heartbeat_s: Annotated[float, Gt(0)] = 30.0
    """Off a terminal: a line for every stage still running this often (its step, loss, scenes and ETA)."""
    snapshot_s: Annotated[float, Gt(0)] = 10.0
    """The launch's progress snapshot on its MLflow run (``gdwm.events``) is written at most this often."""
    worker_logs: bool = False
    """Stream Ray workers' stdout/stderr to the driver, to their last line: before Ray stops, the driver waits until
    Ray has forwarded what the workers wrote (``gdwm.workerlogs``). Errors reach MLflow as error.txt either way."""
    deterministic: bool | None = None
    """Bit-identical trials: every stage starts from its seed with a fixed torch thread count, and CUDA uses
    deterministic kernels (slower on GPUs). null = on where a stage runs without CUDA, off where it has CUDA."""


class UiAuth(StrEnum):
    none = "none"
    mlflow = "mlflow"


@dataclass
class UiConfig:
    """``gdwm ui`` (gdwm's dashboard over the tracking store; ``--mlflow`` adds MLflow's own UI) and the run links of
    ``gdwm compare`` reports."""

    host: str = "127.0.0.1"
    """Interface the dashboard binds to; 0.0.0.0 exposes it to the network."""
    port: Annotated[int, Interval(ge=0, le=65535)] = 5000
    """Port of the dashboard; 0 picks a free one (``--port 0``)."""
    mlflow_port: Annotated[int, Interval(ge=0, le=65535)] = 5001
    """Port of MLflow's own UI with ``gdwm ui --mlflow`` (on ``host``); 0 picks a free one."""
    url: str | None = None
    """Base URL of an MLflow UI that links to runs point at (reports, every dashboard page); null = MLflow's UI of
    ``gdwm ui --mlflow`` (http://<host>:<mlflow_port>), or the tracking server itself for ``tracking=server``."""
    poll_s: Annotated[float, Interval(gt=0)] = 2.0
    """How often a live page (a running sweep, the home page) asks the dashboard for news."""
    auth: UiAuth = UiAuth.none
    """``mlflow``: every request needs HTTP basic-auth credentials that the tracking server (``tracking=server``)
    accepts for the experiment, as its own UI does (the k8s Service); ``none``: no login (loopback)."""


@dataclass
class GdwmConfig:
    """Top level of every composed config."""

    workdir: str = "./gdwm-work"
    """Roots everything a run writes: data, cache, MLflow store, reports."""
    source: str | None = None
    """Input directory of import/convert commands."""
    overwrite: bool = False
    """Replace an existing output (e.g. a dataset) instead of refusing."""
    seed: Annotated[int, SEED] = 0
    """The trial seed: seeded stages (training, sampling) derive every random stream from it; model configs follow
    it through ``${seed}``. Seed-free stages (reconstruction, distillation) ignore it."""
    seeds: Annotated[list[int] | None, SEED] = None
    """One trial per seed, for ``gdwm run`` and ``gdwm sweep`` alike (e.g. ``seeds=[0,1,2]``); overrides a sweep's or
    a benchmark's own ``seeds``. null = the sweep's/benchmark's seeds, else ``[seed]``."""
    data: Any = MISSING
    """Dataset (group ``data/``)."""
    cluster: Any = MISSING
    """Ray cluster profile (group ``cluster/``)."""
    tracking: Any = MISSING
    """MLflow tracking profile (group ``tracking/``)."""
    pipeline: Any = None
    """Stage DAG (group ``pipeline/``)."""
    stage: Any = field(default_factory=dict)
    """Per-stage settings (groups ``stage/<name>/``)."""
    model: Any = field(default_factory=dict)
    """Model components and variants (groups ``model/<component>/``)."""
    targets: list[str] = field(default_factory=list)
    """Stages to produce; only they and their ancestors run. Empty = the whole pipeline."""
    args: Any = field(default_factory=dict)
    """Arguments of a plugin command (``conf/args/<command>.yaml``), e.g. ``gdwm generate args.shift_m=1``."""
    compare: Any = None
    """Table layout of ``gdwm compare`` (group ``compare/``)."""
    sweep: Any = None
    """Ablation table or grid of ``gdwm sweep`` (group ``sweep/``)."""
    benchmark: Any = None
    """Regression suite of ``gdwm regress`` (group ``benchmark/``)."""
    ui: UiConfig = field(default_factory=UiConfig)
    """Dashboard (``gdwm ui``) and MLflow UI addresses."""
    cache: CacheConfig = field(default_factory=CacheConfig)
    """Stage cache."""
    run: RunSettings = field(default_factory=RunSettings)
    """Execution policy."""
    from_env: dict[str, str] = field(default_factory=dict)
    """Set when the config is composed (not by hand): every key whose value comes from the environment
    (``${oc.env:NAME}``), with the text gdwm records instead of its value (``<env:NAME>``; ``gdwm.fromenv``)."""


@dataclass
class SweepRow:
    """One row of the table."""

    label: str = MISSING
    """Row label in the table (unique in the sweep)."""
    factors: dict[str, str] = field(default_factory=dict)
    """Factor column -> the value this row shows (e.g. ``Coarse Selection: Driving-Aware``)."""
    overrides: list[str] = field(default_factory=list)
    """Hydra overrides the row means."""


@dataclass
class SweepConfig:
    """An ablation table or grid (group ``sweep/``)."""

    name: str = MISSING
    """Sweep name: the MLflow parent run and ``workdir/reports/<name>``."""
    layout: str | None = None
    """Table layout of the report (a ``conf/compare/`` option); null = the default of ``gdwm compare``
    (``conf/args/compare.yaml``)."""
    targets: list[str] = field(default_factory=list)
    """Stages the reported metrics need; only they and their ancestors run (empty = the whole pipeline)."""
    overrides: list[str] = field(default_factory=list)
    """Overrides of every trial (the command line's come after them)."""
    rows: list[SweepRow] = field(default_factory=list)
    """Explicit rows; none = one row of the base config."""
    only: list[str] = field(default_factory=list)
    """Labels of the rows to run (empty = every row), e.g. the rows a dataset can feed:
    ``"sweep.only=['Voxel Top-K + Similarity']"``."""
    grid: dict[str, list[str]] = field(default_factory=dict)
    """Override key -> values; their cartesian product is crossed with every row."""
    baseline: str | None = None
    """Row label the report's deltas are against (default: the first row)."""
    seeds: Annotated[list[int] | None, SEED] = None
    """Seeds of every row: one trial per (row, grid point, seed); ``seeds=[...]`` on the command line overrides
    them. null = ``[seed]``."""


# ---- regression suites (`gdwm regress`, group benchmark/) -----------------------------------------------------


class CheckTest(StrEnum):
    none = "none"
    bootstrap = "bootstrap"


@dataclass
class MetricCheck:
    """One watched metric."""

    name: str = MISSING
    """Metric name as logged (``<section>/<metric>`` of an evaluation stage, ``perf/<bench>/<metric>``)."""
    direction: Direction = Direction.higher
    """Which way is better."""
    tolerance: Any = 0.0
    """Allowed worsening before it is a regression: an amount (``1.0``), or ``{sigma: K}``: K standard deviations of
    the difference of the two seed means, Welch's ``K * sqrt(s_b^2/n_b + s_now^2/n_now)`` from both runs' spreads over
    their seeds (``K * s_b * sqrt(1/n_b + 1/n_now)`` when now ran one seed; the baseline needs >= 2 seeds)."""
    relative: bool = False
    """A numeric ``tolerance`` is a fraction of the baseline value instead of an absolute amount."""
    test: CheckTest = CheckTest.none
    """``bootstrap``: a worsening beyond the tolerance counts only when a paired bootstrap over the held-out samples
    (baseline vs now, combined over seeds) finds it significant at ``alpha`` (needs per-sample predictions)."""

    def __post_init__(self) -> None:
        t = self.tolerance
        if isinstance(t, Mapping):
            if set(t) != {"sigma"} or isinstance(t["sigma"], bool) or not isinstance(t["sigma"], int | float):
                raise ValueError(f"metric '{self.name}': tolerance must be a number or {{sigma: K}}, got {dict(t)}")
            if t["sigma"] < 0 or self.relative:
                raise ValueError(f"metric '{self.name}': tolerance {{sigma: K}} needs K >= 0 and relative: false")
            self.tolerance = {"sigma": float(t["sigma"])}
        elif isinstance(t, bool) or not isinstance(t, int | float) or t < 0:
            raise ValueError(f"metric '{self.name}': tolerance must be a number >= 0 or {{sigma: K}}, got {t!r}")

    @property
    def sigma(self) -> float | None:
        return self.tolerance["sigma"] if isinstance(self.tolerance, dict) else None


@dataclass
class BenchmarkConfig:
    """A regression suite (group ``benchmark/``)."""

    name: str = MISSING
    """Suite name: its runs are tagged ``gdwm.benchmark=<name>``."""
    overrides: list[str] = field(default_factory=list)
    """What to evaluate: overrides of ``gdwm run`` (an experiment, zoo references)."""
    targets: list[str] = field(default_factory=list)
    """Stages whose evaluation metrics are compared; only they and their ancestors run (empty = the whole
    pipeline)."""
    metrics: list[MetricCheck] = field(default_factory=list)
    """The watched metrics."""
    perf: list[str] = field(default_factory=list)
    """Performance benchmarks by name (entry-point group ``gdwm.benchmarks``, run with ``quick=True``); their figures
    become ``perf/<bench>/<metric>``."""
    baseline: str | None = None
    """A run id to compare against; default: the latest run of this suite tagged as baseline."""
    seeds: Annotated[list[int] | None, SEED] = None
    """Seeds of the evaluation, one trial each; the watched value is their mean (``seeds=[...]`` on the command
    line overrides them). null = ``[seed]``."""
    alpha: Annotated[float, Interval(gt=0, lt=1)] = 0.05
    """Significance level of ``test: bootstrap``."""
    resamples: Annotated[int, Ge(2)] = 1000
    """Bootstrap resamples of ``test: bootstrap``."""


def _register_platform(cs: ConfigStore) -> None:
    cs.store(name="gdwm_schema", node=GdwmConfig)
    cs.store(group="schema/cluster", name="cluster", node=ClusterConfig)
    cs.store(group="schema/tracking", name="tracking", node=TrackingConfig)
    from gdwm.dag import PipelineConfig

    cs.store(group="schema/pipeline", name="pipeline", node=PipelineConfig)
    from gdwm.compare.layout import CompareArgs, LayoutConfig

    cs.store(group="schema/compare", name="layout", node=LayoutConfig)
    cs.store(group="schema/sweep", name="sweep", node=SweepConfig)
    cs.store(group="schema/benchmark", name="benchmark", node=BenchmarkConfig)
    cs.store(group="schema/args", name="compare", node=CompareArgs)
    from gdwm.zoo.refs import ZooArgs

    cs.store(group="schema/args", name="zoo", node=ZooArgs)
    cs.store(group="schema/args", name="cache", node=CacheArgs)
    cs.store(group="schema/args", name="status", node=StatusArgs)
    cs.store(group="schema/args", name="reproduce", node=ReproduceArgs)


@cache
def _register_all() -> tuple[str, ...]:
    for name, fn in PATH_RESOLVERS.items():
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, fn)
    cs = ConfigStore.instance()
    _register_platform(cs)
    loaded = []
    for ep in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name):
        try:
            ep.load()(cs)
        except Exception as e:  # a broken plugin must name itself, not surface as a bare ImportError
            raise ConfigError(f"plugin '{ep.name}' ({ep.value}) failed to register its configs: {e!r}") from e
        loaded.append(ep.name)
    return tuple(loaded)


def conf_dir() -> Path:
    """``$GDWM_CONF_DIR``, else the ``conf/`` of the checkout this package runs from."""
    env = os.environ.get("GDWM_CONF_DIR")
    candidates = [Path(env)] if env else []
    candidates += [Path(__file__).resolve().parents[2] / "conf", Path.cwd() / "conf"]
    for c in candidates:
        if (c / "config.yaml").is_file():
            return c.resolve()
    raise ConfigError(
        f"no gdwm config tree found (looked for config.yaml in {[str(c) for c in candidates]}); set GDWM_CONF_DIR"
    )


def _abspath(path: str) -> str:
    return str(Path(path).expanduser().resolve())


PATH_RESOLVERS = {
    "abspath": _abspath,
    "sqlite_uri": lambda p: "sqlite:///" + urllib.parse.quote(_abspath(p)),
    "file_uri": lambda p: Path(_abspath(p)).as_uri(),
}
"""Paths made absolute, and into URIs with their characters quoted: a workdir is a path, whatever it is named (a
``?`` or ``#`` in it would otherwise start a URI's query or fragment)."""


def drop_mlflow_litter(uri: str) -> None:
    """Remove the empty directory MLflow makes from a quoted sqlite URI's raw text (it creates the parent of
    ``uri.removeprefix("sqlite:///")`` before SQLAlchemy unquotes it: ``w%20%231%3F...`` beside a workdir ``w #1?...``)
    once a command is done with the store."""
    db = sqlite_path(uri)
    if db is None:
        return
    raw = Path(uri.removeprefix("sqlite:///")).parent
    if raw != Path(db).parent:
        with contextlib.suppress(OSError):
            raw.rmdir()  # only ever an empty directory


def sqlite_path(uri: str) -> str | None:
    """The database file of a ``sqlite:///`` tracking URI, as SQLAlchemy reads it (up to a ``?``, unquoted); None for
    any other store."""
    if not uri.startswith("sqlite:///"):
        return None
    return urllib.parse.unquote(uri.removeprefix("sqlite:///").split("?", 1)[0])


def group_options(group: str) -> list[str]:
    roots = [conf_dir(), *(Path(p) for p in os.environ.get("GDWM_CONF_PATH", "").split(os.pathsep) if p)]
    return sorted({p.stem for r in roots if (r / group).is_dir() for p in (r / group).glob("*.yaml")})


def env_sources(cfg: DictConfig) -> dict[str, str]:
    """Key -> interpolation of every value of ``cfg`` read from the environment (``from_env`` itself aside); read
    before the config is resolved. Empty for a config without ``from_env``."""
    if "from_env" not in cfg:
        return {}
    found = env_keys(OmegaConf.to_container(cfg, resolve=False))
    return {k: v for k, v in found.items() if not k.startswith("from_env")}


def load_config(overrides: list[str] | tuple[str, ...] = (), config_name: str = "config") -> DictConfig:
    """Compose and validate; every interpolation is resolved so missing values fail here, not mid-run."""
    return validated(lambda: compose_raw(overrides, config_name), overrides)


def compose_raw(overrides: list[str] | tuple[str, ...], config_name: str = "config") -> DictConfig:
    """Hydra's composition of ``conf/`` (and ``GDWM_CONF_PATH``'s trees) with ``overrides``: unresolved, unchecked
    (``validated`` does both; ``load_config`` is the two)."""
    _register_all()
    extra = [p for p in os.environ.get("GDWM_CONF_PATH", "").split(os.pathsep) if p]
    if extra:  # user / plugin config trees searched after conf/
        overrides = [f"hydra.searchpath=[{','.join('file://' + str(Path(p).resolve()) for p in extra)}]", *overrides]
    with initialize_config_dir(config_dir=str(conf_dir()), version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))


def validated(make: Callable[[], DictConfig], overrides: list[str] | tuple[str, ...]) -> DictConfig:
    """``make()``'s config resolved and checked (every value resolvable, every numeric knob in range, values from
    the environment recorded as their interpolation); any error of ``make`` or of the checks is a ``ConfigError``
    naming the key (``overrides``: what the config was made from, for the message)."""
    try:
        cfg = make()
        secret = env_sources(cfg)
        _check_resolvable(cfg)
        OmegaConf.resolve(cfg)
        if "from_env" in cfg:  # values from the environment are recorded as their interpolation (gdwm.fromenv)
            cfg.from_env = secret
        if bad := check_ranges(cfg):  # every numeric knob's range, from its schema (gdwm.knobs)
            raise ConfigError(f"{bad}.")
    except (HydraException, OmegaConfBaseException) as e:
        raise ConfigError(explain(e)) from e
    except ValueError as e:  # hydra's own ValueErrors, e.g. `cluster=null` for a config group
        nulled = [
            o.split("=", 1)[0] for o in overrides if o.endswith(("=null", "=None")) and "." not in o.split("=")[0]
        ]
        groups = [g for g in nulled if group_options(g.lstrip("+~"))]
        if not groups:
            raise ConfigError(str(e)) from e
        g = groups[0].lstrip("+~")
        raise ConfigError(f"{g}=null: {g} is a config group; choose one of {', '.join(group_options(g))}") from e
    return cfg


def _check_resolvable(cfg: DictConfig | ListConfig, prefix: str = "") -> None:
    """Touch every value so a missing value or failing interpolation names its full key."""
    keys = cfg.keys() if isinstance(cfg, DictConfig) else range(len(cfg))
    for key in keys:
        full = f"{prefix}{key}"
        if OmegaConf.is_missing(cfg, key):
            raise MissingMandatoryValue(f"Missing mandatory value: {full}\n    full_key: {full}")
        try:
            value = cfg[key]
        except InterpolationResolutionError as e:
            raise ConfigError(f"invalid value for '{full}': {e}.") from e
        if isinstance(value, DictConfig | ListConfig):
            _check_resolvable(value, f"{full}.")


def _allowed_keys(inner: OmegaConfBaseException) -> list[str]:
    """Fields of the schema the bad key was checked against."""
    obj = getattr(inner, "object_type", None)
    return [f.name for f in dataclasses.fields(obj)] if dataclasses.is_dataclass(obj) else []


def explain(e: Exception) -> str:
    """One paragraph naming the full key (or group) and what is allowed."""
    if isinstance(e, MissingConfigException):
        m = re.search(r"Could not find '([^']+)'", str(e))
        missing = m.group(1) if m else str(e).splitlines()[0]
        group, _, option = missing.rpartition("/")
        allowed = group_options(group) if group else []
        if group and allowed:
            return f"config group '{group}' has no option '{option}'; allowed values: {', '.join(allowed)}."
        return f"config '{missing}' not found under {conf_dir()}."
    chain = [e]
    while chain[-1].__cause__ is not None and len(chain) < 5:
        chain.append(chain[-1].__cause__)
    inner = next((c for c in reversed(chain) if isinstance(c, OmegaConfBaseException)), e)
    text = str(inner)
    full_key = getattr(inner, "full_key", None)
    if not full_key:
        m = re.search(r"full_key: (\S+)", text)
        full_key = m.group(1) if m else None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    head = lines[0]
    where = re.match(r"In '([^']+)': \w+ raised while composing config:$", head)
    if where and len(lines) > 1:  # Hydra's wrapper: the validation message is the next line
        head = f"{lines[1]} (in {where.group(1)})"
    if isinstance(inner, MissingMandatoryValue):
        return f"missing mandatory value '{full_key}': set it with {full_key}=VALUE."
    if full_key and "not in" in head:
        allowed = _allowed_keys(inner)
        hint = f"; allowed keys here: {', '.join(allowed)}" if allowed else ""
        return f"unknown config key '{full_key}'{hint}."
    if full_key:
        return f"invalid value for '{full_key}': {head}."
    return " ".join(line.strip() for line in str(e).splitlines() if line.strip() and "search path" not in line)


def ui_url(cfg: DictConfig) -> str:
    """Where an MLflow UI answers for the store: ``ui.url``, else the tracking server itself (an http(s) store, its
    credentials left out), else MLflow's UI of ``gdwm ui --mlflow``; report and dashboard links to runs point there."""
    if cfg.ui.url:
        return cfg.ui.url
    uri = str(cfg.tracking.uri)
    if uri.startswith(("http://", "https://")):
        scheme, rest = uri.split("://", 1)
        host, sep, path = rest.partition("/")
        return f"{scheme}://{host.rpartition('@')[2]}{sep}{path}".rstrip("/")
    return f"http://{cfg.ui.host}:{cfg.ui.mlflow_port}"
