"""Trials and their plans, known before anything runs.

Every launch is a table: rows times seeds. ``gdwm sweep`` has a sweep's rows crossed with its grid; ``gdwm run`` has
one row. Each (row, seed) is a trial. Its config is composed from the command's overrides, then the row's, then
``seed=N``; it is validated, zoo aliases are pinned, and every stage key is predicted on the driver. So a bad row,
option or seed is refused before launch (exit 2, naming it), and a stage key that several trials share -- a
seed-free stage shares one key across all the seeds of a row -- is submitted once.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from gdwm.cache import Cache
from gdwm.config import ConfigError, SweepConfig, SweepRow, load_config
from gdwm.dag import DagError, Pipeline, load_pipeline
from gdwm.executor import RunEnv, StageResult, aggregate_key, stage_config, stage_key, upstream_keys
from gdwm.zoo.refs import ZooError
from gdwm.zoo.registry import pin_references


class PlanError(Exception):
    """A launch refused before anything ran (exit 2): the message names the row, the key or the seed."""


class RunError(Exception):
    """A run that could not start (exit 1), e.g. a dataset that is absent and cannot be generated."""


@dataclass
class PlanRow:
    stage: str
    scene: str | None
    key: str
    status: str  # cached | to run
    resources: str


@dataclass
class Row:
    """One row of the table: a sweep row crossed with one grid point (``gdwm run``: the whole invocation)."""

    index: int
    label: str
    factors: dict[str, str]
    overrides: list[str]
    seeds: list[int]
    run_id: str | None = None

    @property
    def key(self) -> str:
        """Identity across re-runs: label and overrides, not the config's values (a code change keeps the run)."""
        return hashlib.sha256(json.dumps([self.label, self.overrides]).encode()).hexdigest()[:16]


@dataclass
class Trial:
    """One seed of a row: a composed, validated config and the predicted key of every stage it needs."""

    row: Row
    seed: int
    cfg: DictConfig | None = None
    pipe: Pipeline | None = None
    order: list[str] = field(default_factory=list)
    keys: dict[str, str] = field(default_factory=dict)
    """Stage -> cache key (per-scene stages: the aggregate key)."""
    plan: list[PlanRow] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    """RunEnv fields of this trial's config (all but sink, parent run and progress)."""
    run_id: str | None = None

    @property
    def label(self) -> str:
        return self.row.label

    @property
    def name(self) -> str:
        """The label, with the seed where the row has several."""
        return self.label if len(self.row.seeds) == 1 else f"{self.label} · seed {self.seed}"

    @property
    def key(self) -> str:
        return hashlib.sha256(json.dumps([self.label, self.row.overrides, self.seed]).encode()).hexdigest()[:16]

    def env(self, sink=None, parent_run_id: str | None = None, progress=None, **kw) -> RunEnv:
        return RunEnv(sink=sink, parent_run_id=parent_run_id, progress=progress, **self.settings, **kw)


# ---- seeds -------------------------------------------------------------------------------------------------------
def _override_key(o: str) -> str:
    return o.split("=", 1)[0].lstrip("+~")


def resolve_seeds(cfg: DictConfig, own: Sequence[int] | None = None, own_key: str = "sweep.seeds") -> list[int]:
    """The seeds of every row: ``seeds=[...]`` (the command line, or an experiment) over the launch's own
    (``own``: a sweep's or a benchmark's ``seeds``), else ``[seed]``."""
    key, seeds = ("seeds", cfg.seeds) if cfg.get("seeds") is not None else (own_key, own)
    if seeds is None:
        return [int(cfg.seed)]
    seeds = list(seeds)
    if not seeds:
        raise PlanError(f"{key}: no seeds given; give one or more, e.g. {key}=[0,1,2] (or leave it unset: [seed])")
    bad = [s for s in seeds if isinstance(s, bool) or not isinstance(s, int) or s < 0]
    if bad:
        raise PlanError(f"{key}: seeds must be integers >= 0, got {bad}")
    dup = sorted({s for s in seeds if seeds.count(s) > 1})
    if dup:
        raise PlanError(f"{key}: seed(s) {dup} listed twice")
    return seeds


def check_seed_overrides(seeds_given: bool, where: str, overrides: Sequence[str], what: str = "override") -> None:
    """With ``seeds``, nothing else may set the trial seed: each trial sets ``seed=N`` itself."""
    if not seeds_given:
        return
    for o in overrides:
        if _override_key(o) == "seed":
            raise PlanError(f"{where}: {what} '{o}' sets the trial seed, which seeds=[...] sets per trial; drop one")


def check_grid_seeds(sweep: SweepConfig, seeds_given: bool) -> None:
    if not seeds_given:
        return
    for k in sweep.grid:
        if k == "seed" or k.endswith(".seed"):
            raise PlanError(
                f"sweep '{sweep.name}': grid key '{k}' sets a seed itself, and seeds= makes every row a trial per "
                f"seed; use seeds=[...] (or sweep.seeds) alone"
            )


# ---- rows --------------------------------------------------------------------------------------------------------
def expand(sweep: SweepConfig, seeds: list[int]) -> list[Row]:
    """Rows x grid, in row order then grid order, each with every seed; labels must be unique."""
    rows_in = sweep.rows or [SweepRow(label=sweep.name, factors={}, overrides=[])]
    keys = list(sweep.grid)
    rows: list[Row] = []
    for row in rows_in:
        for combo in itertools.product(*(sweep.grid[k] for k in keys)):
            grid = [f"{k}={v}" for k, v in zip(keys, combo, strict=True)]
            label = ", ".join([row.label, *grid]) if grid and sweep.rows else ", ".join(grid) or row.label
            factors = {**row.factors, **{k: str(v) for k, v in zip(keys, combo, strict=True)}}
            rows.append(Row(len(rows), label, factors, [*row.overrides, *grid], list(seeds)))
    seen: dict[str, int] = {}
    for r in rows:
        if r.label in seen:
            raise PlanError(f"sweep '{sweep.name}': rows {seen[r.label]} and {r.index} share the label '{r.label}'")
        seen[r.label] = r.index
    return rows


def trials_of(rows: list[Row]) -> list[Trial]:
    return [Trial(r, s) for r in rows for s in r.seeds]


# ---- composing and planning --------------------------------------------------------------------------------------
def compose(
    trials: list[Trial],
    overrides: Sequence[str] | None,
    where: str,
    cfg: DictConfig | None = None,
    *,
    name_rows: bool = False,
) -> None:
    """Compose, validate and plan every trial: ``overrides`` (the command's), the row's, then ``seed=N``.

    Without ``overrides`` (a caller holding a composed config only), ``cfg`` is every trial's config, so its seed
    must be the only seed. Errors name ``where`` (and the row, with ``name_rows``)."""
    for t in trials:
        here = f"{where} row '{t.label}'" if name_rows else where
        if overrides is None:
            if cfg is None or t.row.overrides or int(cfg.seed) != t.seed:
                raise PlanError(f"{where}: seed {t.seed} needs the command's overrides to compose its config")
            t.cfg = cfg
        else:
            try:
                t.cfg = load_config([*overrides, *t.row.overrides, f"seed={t.seed}"])
            except ConfigError as e:
                raise PlanError(f"{here}: {e}") from e
        try:
            t.pipe = load_pipeline(t.cfg, list(t.cfg.targets) or None)
            t.order = t.pipe.ancestors(list(t.cfg.targets)) if t.cfg.targets else list(t.pipe.order)
            # zoo:NAME@ALIAS -> zoo:NAME/VERSION in what the stages read: their keys name exact versions
            t.cfg = pin_references(t.cfg, t.cfg.tracking.uri, [k for n in t.order for k in t.pipe.stages[n].config])
        except (DagError, ZooError) as e:
            if not name_rows:  # gdwm run reports them as it always has: a pipeline error (2), a zoo error (1)
                raise
            raise PlanError(f"{here}: {e}") from e
        t.settings = env_settings(t.cfg, ensure_data(t.cfg))
        t.plan, t.keys = plan_keys(t.pipe, t.order, t.cfg, t.env())


def read_dataset_meta(root: Path) -> dict:
    meta = root / "dataset.json"
    if not meta.is_file():
        raise RunError(f"dataset at {root} is absent or incomplete (no dataset.json)")
    return json.loads(meta.read_text())


def ensure_data(cfg: DictConfig) -> dict:
    """The dataset's meta; a dataset that needs no source (synthetic) is generated first if absent."""
    root = Path(cfg.data.root)
    if not (root / "dataset.json").is_file():
        if cfg.source is None and not cfg.data.needs_source:
            from gdwm.datasets import build_dataset
            from gdwm.term import console

            console.print(f"generating {cfg.data.name} at {root} ...")
            build_dataset(cfg, source=None)
        else:
            raise RunError(
                f"dataset '{cfg.data.name}' not found at {root}: build it first "
                f"(gdwm data import-gaussiandwm / convert-nuscenes source=DIR data={cfg.data.name})"
            )
    return read_dataset_meta(root)


def env_settings(cfg: DictConfig, meta: dict) -> dict:
    """RunEnv fields of a composed config (all but the tracking sink, parent run and progress actor)."""
    from omegaconf import OmegaConf

    res = {k: dict(v) for k, v in OmegaConf.to_container(cfg.cluster.resources, resolve=True).items()}
    return dict(
        cache_uri=cfg.cache.uri,
        data_root=str(Path(cfg.data.root).resolve()),
        data_fingerprint=meta["fingerprint"],
        scenes=tuple(meta["scenes"]),
        checkpoint_root=str(Path(cfg.workdir).resolve() / "checkpoints"),
        resources=res,
        on_scene_error=cfg.run.on_scene_error,
        max_retries=cfg.run.max_retries,
        deterministic=cfg.run.deterministic,
        train_settings={"checkpoint_every": cfg.run.checkpoint_every, "max_failures": cfg.run.max_failures},
        tracking_uri=cfg.tracking.uri,
    )


def _plan_result(sd, sub, env: RunEnv, ups: tuple[StageResult, ...], cache: Cache, rows: list[PlanRow]) -> StageResult:
    """Predict one stage's keys and cache status, assuming every upstream scene succeeds."""
    if sd.per_scene:
        keys = {s: stage_key(sd, sub, upstream_keys(ups, s), env, scene=s) for s in env.scenes}
        for s, k in keys.items():
            hit = cache.lookup(sd.name, k, verify=False) is not None
            rows.append(PlanRow(sd.name, s, k, "cached" if hit else "to run", sd.resources))
        return StageResult(
            sd.name, aggregate_key(sd, sub, keys, env), False, None, scenes={s: (k, "") for s, k in keys.items()}
        )
    key = stage_key(sd, sub, upstream_keys(ups, None), env)
    hit = cache.lookup(sd.name, key, verify=False) is not None
    rows.append(PlanRow(sd.name, None, key, "cached" if hit else "to run", sd.resources))
    return StageResult(sd.name, key, hit, None)


def plan_keys(pipe: Pipeline, order: list[str], cfg: DictConfig, env: RunEnv) -> tuple[list[PlanRow], dict[str, str]]:
    """Keys depend on upstream keys, not outputs, so the whole DAG's keys are known before anything runs: the plan's
    rows, and each stage's key as its downstream sees it (per-scene stages: the aggregate key)."""
    cache = Cache(env.cache_uri)
    rows: list[PlanRow] = []
    predicted: dict[str, StageResult] = {}
    for name in order:
        sd = pipe.stages[name]
        ups = tuple(predicted[u] for u in sd.upstream)
        predicted[name] = _plan_result(sd, stage_config(sd, cfg), env, ups, cache, rows)
    return rows, {name: r.key for name, r in predicted.items()}
