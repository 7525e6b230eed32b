"""The stage API: the one part of gdwm that ``pipelines`` imports.

A stage is a named, versioned function of (its config subtrees, its upstream outputs, the
data fingerprint, its code) to an output directory (see ``gdwm.cache`` and ``gdwm.fingerprint``)::

    @stage("distill", version="1", config=["stage.distill", "model.encoder"], upstream=["reconstruct"],
           per_scene=True, resources="gpu", setup=load_encoder)
    def distill(ctx: StageContext) -> None:
        gaussians_dir = ctx.upstream["reconstruct"].scenes[ctx.scene]
        ...  # write files under ctx.out_dir, log with ctx.tracker, report with ctx.progress

``setup(cfg)`` loads heavy state once per actor (per-scene stages) and arrives as ``ctx.state``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gdwm.zoo.refs import NAME_PREFIX, ZooError, parse_ref

RESOURCE_CLASSES = ("cpu", "gpu", "train", "eval")


@dataclass(frozen=True)
class StageDef:
    """What a stage declares about itself; the executor needs nothing else."""

    name: str
    version: str
    fn: Callable[[StageContext], Any]
    config: tuple[str, ...] = ()
    """Dotted config subtrees the output depends on; they (and nothing else) enter the cache key."""
    upstream: tuple[str, ...] = ()
    per_scene: bool = False
    resources: str = "cpu"
    setup: Callable[[Mapping], Any] | None = None
    evaluation: bool = False
    """Its returned numeric values are the trial's evaluation metrics (copied onto the trial's run)."""
    seeded: bool = False
    """It consumes the trial seed (``seed=``/``seeds=``): the seed enters its config (key ``seed``), its cache key and
    its MLflow params, and arrives as ``ctx.seed``. Seed-free stages (``ctx.seed`` is None) are shared by every seed
    of a row."""
    samples: str | None = None
    """Evaluation stages: a Parquet file of its output with one row per held-out sample (a ``sample_id`` column),
    what ``score`` recomputes the metrics from; ``gdwm compare`` resamples it for intervals and significance."""
    score: Callable[[Any, Any], Mapping[str, float]] | None = None
    """``score(table: pyarrow.Table, wanted: set[str] | None) -> metrics``: the stage's metrics of any subset of
    ``samples`` (rows may repeat; row order is ranking order), computing only ``wanted`` where it can (None: all;
    a bootstrap scores thousands of resamples). A module-level function, so compare and regress import it by
    name."""
    strata: str | None = None
    """A column of ``samples`` (e.g. ``task``) whose groups a bootstrap resamples separately, each at its own size,
    so a suite of per-group metrics stays defined on every resample."""
    libraries: tuple[str, ...] = ()
    """Distributions whose version enters the stage's code fingerprint besides those it imports from
    ``gdwm.fingerprint.NUMERIC_LIBRARIES`` (e.g. a renderer it loads by name)."""
    needs: tuple[tuple[str, str], ...] | Callable[[Mapping[str, Any]], Mapping[str, str]] = ()
    """Dataset tables it reads -> why (e.g. ``{"lidar": "initialises the Gaussians"}``), or a function of its config
    subset (``stage_config``) returning them, for needs that depend on the variant. A launch whose dataset lacks one
    (its ``dataset.json`` ``tables``) is refused before anything starts (``gdwm.plan.missing_inputs``)."""

    def needed(self, config: Mapping[str, Any]) -> dict[str, str]:
        """The tables this stage reads with ``config`` (its config subset), each with why."""
        return dict(self.needs(config) if callable(self.needs) else self.needs)

    def __post_init__(self) -> None:
        if self.resources not in RESOURCE_CLASSES:
            raise ValueError(
                f"stage '{self.name}': resources must be one of {RESOURCE_CLASSES}, got '{self.resources}'"
            )
        if not self.version:
            raise ValueError(f"stage '{self.name}': version must be non-empty")
        if (self.samples is None) != (self.score is None) or (self.samples and not self.evaluation):
            raise ValueError(f"stage '{self.name}': samples= and score= go together, on an evaluation stage")

    def __reduce__(self):
        # Ship by reference (module + attribute), so Ray workers import the real stage, not a pickled copy.
        return (_load_stage, (self.fn.__module__, self.fn.__name__))


_REGISTRY: dict[tuple[str, str], StageDef] = {}


def _load_stage(module: str, attr: str) -> StageDef:
    import importlib

    importlib.import_module(module)
    return _REGISTRY[(module, attr)]


def stage(
    name: str,
    version: str,
    config: Sequence[str] = (),
    upstream: Sequence[str] = (),
    per_scene: bool = False,
    resources: str = "cpu",
    setup: Callable[[Mapping], Any] | None = None,
    evaluation: bool = False,
    seeded: bool = False,
    samples: str | None = None,
    score: Callable[[Any, Any], Mapping[str, float]] | None = None,
    strata: str | None = None,
    libraries: Sequence[str] = (),
    needs: Mapping[str, str] | Callable[[Mapping[str, Any]], Mapping[str, str]] | None = None,
) -> Callable[[Callable[[StageContext], Any]], StageDef]:
    """Declare a stage; the decorated name becomes its StageDef (point ``_target_`` at it).

    Its cache key holds ``version`` and a fingerprint of its code (``gdwm.fingerprint``): bump ``version`` only for
    what the fingerprint can't see, such as a data file the stage reads at run time."""

    def wrap(fn: Callable[[StageContext], Any]) -> StageDef:
        sd = StageDef(name, str(version), fn, tuple(config), tuple(upstream), per_scene, resources, setup, evaluation,
                      seeded, samples, score, strata, tuple(libraries),
                      needs if callable(needs) else tuple(sorted((needs or {}).items())))  # fmt: skip
        _REGISTRY[(fn.__module__, fn.__name__)] = sd
        return sd

    return wrap


@dataclass(frozen=True)
class UpstreamOutput:
    """A published upstream entry as a stage sees it."""

    name: str
    key: str
    path: Path | None
    """Local directory with the entry's files (None for per-scene stages: see ``scenes``)."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    scenes: Mapping[str, Path] = field(default_factory=dict)
    """Per-scene stages: scene id -> local directory of that scene's entry (failed, skipped scenes absent)."""


@dataclass(frozen=True)
class Registration:
    """A component a stage declared for the model zoo (``StageContext.register``)."""

    name: str
    path: str
    """Relative to the stage's output directory; ``.`` is the whole output."""
    variant: str
    tags: Mapping[str, str] = field(default_factory=dict)


@dataclass
class StageContext:
    """Everything a stage function receives."""

    name: str
    key: str
    config: Mapping[str, Any]
    """The resolved config subtrees the stage declared, by dotted key (plain containers)."""
    out_dir: Path
    """Write outputs here; the platform publishes them atomically after the function returns."""
    upstream: Mapping[str, UpstreamOutput]
    data_root: Path
    data_fingerprint: str
    tracker: Any
    """``gdwm.tracking.Tracker`` bound to this stage's MLflow run (params, step-aware metrics, artifacts)."""
    checkpoint_dir: Path
    """Persistent across attempts of the same key: training resumes from what it finds here."""
    resources: Mapping[str, float]
    scene: str | None = None
    state: Any = None
    progress_sink: Any = None
    seed: int | None = None
    """The trial seed for a ``seeded`` stage (derive every random stream of the trial from it); None otherwise."""
    deterministic: bool | None = None
    """``run.deterministic``: null = deterministic kernels and a fixed thread count without CUDA (see
    ``gdwm.determinism``); training loops started with ``train`` apply the same on every worker."""
    train_settings: Mapping[str, Any] = field(default_factory=dict)
    tracking_uri: str | None = None
    """MLflow store of the run (its model registry is the zoo ``zoo_path`` reads)."""
    registrations: list[Registration] = field(default_factory=list)
    """What ``register`` declared; the platform registers it once the output is published."""

    def cfg(self, dotted: str) -> Any:
        """One declared config subtree, e.g. ``ctx.cfg("stage.lora")``."""
        if dotted not in self.config:
            raise KeyError(f"stage '{self.name}' did not declare config '{dotted}' (declared: {sorted(self.config)})")
        return self.config[dotted]

    def register(self, name: str, path: str | Path, variant: str, tags: Mapping[str, str] | None = None) -> None:
        """Declare ``out_dir / path`` (written already; ``"."`` = the whole output) as model-zoo component ``name``
        (``gdwm-<component>``) of variant ``variant``. Once the output is published it is logged as an MLflow model
        of this stage's run and registered as a new version (alias ``candidate``) with its lineage as tags; a failed
        stage registers nothing, and a cache hit nothing new."""
        target = self.out_dir / path
        if not name.startswith(NAME_PREFIX) or not variant:
            raise ValueError(f"stage '{self.name}': zoo component '{name}' needs a {NAME_PREFIX}* name and a variant")
        if not target.exists() or not target.resolve().is_relative_to(self.out_dir.resolve()):
            raise FileNotFoundError(f"stage '{self.name}': zoo component '{name}': {path} is not in the stage output")
        self.registrations.append(Registration(name, str(path), variant, dict(tags or {})))

    def zoo_path(self, ref: str) -> Path:
        """Local directory with the files of the zoo version ``zoo:NAME/VERSION`` (``gdwm run`` pins config values
        like ``zoo:NAME@champion`` to that form before planning, so the stage's cache key names the version)."""
        from gdwm.zoo.registry import download

        r = parse_ref(ref)
        if r.version is None:
            raise ZooError(f"stage '{self.name}': zoo reference '{ref}' is not pinned to a version (zoo:NAME/VERSION)")
        if self.tracking_uri is None:
            raise ZooError(f"stage '{self.name}': no MLflow store to read '{ref}' from")
        return download(self.tracking_uri, r.name, r.version, self.checkpoint_dir / "zoo" / r.name / str(r.version))

    def progress(self, done: int, total: int, message: str = "") -> None:
        """Report ``done`` of ``total`` units of work (iterations, samples, views) with a short text: the launch's
        board, log heartbeats and ETA show it."""
        if self.progress_sink is not None:
            self.progress_sink.progress(self.scene, done, total, message)

    def train(
        self, loop: Callable[[dict], None], loop_config: Mapping[str, Any] | None = None, total_steps: int | None = None
    ) -> Any:
        """Run ``loop`` under Ray Train with this stage's ScalingConfig; resumes from ``checkpoint_dir``.
        ``total_steps``: the steps the loop will run, so the board and the log show ``step / total`` and an ETA."""
        from gdwm.training import fit

        return fit(self, loop, dict(loop_config or {}), total_steps)
