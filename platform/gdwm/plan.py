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

from omegaconf import DictConfig, OmegaConf

from gdwm.cache import Cache, Manifest
from gdwm.composer import Composer
from gdwm.config import ConfigError, SweepConfig, SweepRow
from gdwm.dag import DagError, Pipeline, load_pipeline
from gdwm.executor import (
    ALL,
    COMPUTED,
    NONE,
    REUSED_SAME,
    RunEnv,
    StageResult,
    aggregate_key,
    find_entry,
    least_trusted,
    stage_base,
    stage_config,
    stage_key,
    upstream_bases,
    upstream_keys,
)
from gdwm.fingerprint import stage_fingerprint
from gdwm.fromenv import env_values
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
    """The entry's key: the one a cached row reuses (under ``cache.reuse=all`` maybe another code's), else the
    key the stage will publish."""
    status: str  # cached | to run
    resources: str
    reused: str = COMPUTED
    """Cached rows: ``same code``, ``other code`` or ``unknown code`` (``gdwm.executor.REUSED_*``)."""
    why: str = ""
    """Rows to run where the stage has entries: what differs from the closest one (code, library, config, upstream,
    data, version), e.g. ``code: model_zoo/adapter.py``; ``recompute`` when forced."""

    @property
    def shown(self) -> str:
        """The status as plans print it."""
        if self.status == "cached" and self.reused not in (COMPUTED, REUSED_SAME):
            return f"cached ({self.reused})"
        return self.status


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
    pending_data: str | None = None
    """A dry run's note that the dataset does not exist yet and would be generated (nothing is cached then)."""
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
    dry_run: bool = False,
) -> None:
    """Compose, validate and plan every trial: ``overrides`` (the command's), the row's, then ``seed=N``.

    Without ``overrides`` (a caller holding a composed config only), ``cfg`` is every trial's config, so its seed
    must be the only seed. Errors name ``where`` (and the row, with ``name_rows``)."""
    seen: dict[str, _Entries] = {}  # a cache's entries are read once per launch, whatever the number of trials
    composer = Composer(overrides) if overrides is not None else None  # Hydra composes once per set of group choices
    refused: dict[str, list[str]] = {}  # row -> what its stages need that the dataset lacks
    lacks = ""
    for t in trials:
        here = f"{where} row '{t.label}'" if name_rows else where
        if overrides is None:
            if cfg is None or t.row.overrides or int(cfg.seed) != t.seed:
                raise PlanError(f"{where}: seed {t.seed} needs the command's overrides to compose its config")
            t.cfg = cfg
        else:
            try:
                t.cfg = composer.load([*t.row.overrides, f"seed={t.seed}"])
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
        check_shapes(t.pipe, t.order, t.cfg, here if name_rows else None)
        meta = ensure_data(t.cfg, dry_run)
        if lacking := missing_inputs(t.pipe, t.order, t.cfg, meta):
            if not name_rows:
                raise PlanError(f"{_lacks(t.cfg, meta)}:\n  " + "\n  ".join(lacking))
            refused.setdefault(t.label, lacking)
            lacks = lacks or _lacks(t.cfg, meta)
            continue
        t.settings = env_settings(t.cfg, meta)
        t.pending_data = meta.get("pending")
        t.settings |= code_settings(t.cfg, t.pipe, t.order, here)
        uri = t.settings["cache_uri"]
        first = uri not in seen
        entries = seen.setdefault(uri, _Entries(Cache(uri)))
        t.plan, t.keys = plan_keys(t.pipe, t.order, t.cfg, t.env(), entries)
        if first:
            check_cache_owned(entries.cache, here)
    if refused:
        rows = "".join(f"\n  row '{label}': " + "\n    ".join(lines) for label, lines in refused.items())
        runnable = list(dict.fromkeys(t.label for t in trials if t.label not in refused))
        hint = f'\nrun the other rows alone with "sweep.only={runnable!r}"' if runnable else ""
        raise PlanError(f"{where}: {lacks}:{rows}{hint}")


def check_cache_owned(cache: Cache, where: str) -> None:
    """``PlanError`` (exit 2) when ``cache.uri`` holds what gdwm did not create (``gdwm.owned``): a launch would fill
    another tool's directory, or a home directory, with stage entries."""
    from gdwm.owned import NotOurs, cache_state

    try:
        cache_state(cache)
    except NotOurs as e:
        raise PlanError(f"{where}: {e}; point cache.uri at an empty or new directory, or at a gdwm cache") from None
    except OSError as e:
        raise cache._store_error(e, f"cache {cache.uri}: listing its top level") from None


def check_shapes(pipe: Pipeline, order: list[str], cfg: DictConfig, where: str | None) -> None:
    """``PlanError`` (exit 2) when a stage of ``order`` asks for a resource shape no node of the cluster can host
    (``gdwm.capacity``): Ray would leave it pending forever."""
    from gdwm.capacity import cluster_nodes, shape_errors

    resources = OmegaConf.to_container(cfg.cluster.resources, resolve=True)
    stages = {n: pipe.stages[n].resources for n in order}
    if errors := shape_errors(stages, resources, cluster_nodes(cfg.cluster), str(cfg.cluster.name)):
        raise PlanError((f"{where}: " if where else "") + "\n  ".join(errors))


def held_tables(cfg: DictConfig, meta: dict) -> list[str] | None:
    """What the dataset holds (``dataset.json`` ``tables``; before a generated dataset exists, its option's
    ``data.tables``); None when unknown (a dataset built before tables were recorded): nothing is checked."""
    held = meta.get("tables")
    if held is None and meta.get("fingerprint") == PENDING_DATA:
        held = list(cfg.data.get("tables") or []) or None
    return None if held is None else list(held)


def missing_inputs(pipe: Pipeline, order: list[str], cfg: DictConfig, meta: dict) -> list[str]:
    """One line per stage of ``order`` that needs, with this config, tables the dataset lacks, naming them and why
    the stage needs each; empty when nothing is missing or the dataset's tables are unknown."""
    held = held_tables(cfg, meta)
    if held is None:
        return []
    out = []
    for name in order:
        sd = pipe.stages[name]
        lacking = [f"'{t}' ({why})" for t, why in sorted(sd.needed(stage_config(sd, cfg)).items()) if t not in held]
        if lacking:
            out.append(f"stage '{name}' needs {', '.join(lacking)}")
    return out


def _lacks(cfg: DictConfig, meta: dict) -> str:
    held = held_tables(cfg, meta) or []
    return f"dataset '{cfg.data.name}' at {cfg.data.root} (tables: {', '.join(held) or 'none'}) lacks inputs"


_WARNED: set[str] = set()


def code_settings(cfg: DictConfig, pipe: Pipeline, order: list[str], where: str) -> dict:
    """``RunEnv.code`` (each stage's code fingerprint) and ``RunEnv.reuse`` (each stage's ``cache.reuse`` mode);
    a module that can't be hashed is named once per process."""
    for key in ("cache.reuse_stages", "cache.recompute"):
        for name in OmegaConf.select(cfg, key) or []:
            if name not in pipe.stages:
                raise PlanError(f"{where}: {key}: no stage '{name}' in pipeline '{pipe.name}' "
                                f"(stages: {', '.join(pipe.order)})")  # fmt: skip
    code, reuse = {}, {}
    for name in order:
        sd = pipe.stages[name]
        fp = stage_fingerprint(sd, stage_config(sd, cfg))
        code[name] = fp.as_dict()
        fresh = [f for f in fp.unhashable if f not in _WARNED]
        if fresh:
            _WARNED.update(fresh)
            from gdwm.term import err_console

            err_console.print(
                f"stage {name}: {', '.join(fresh)} has no Python source to hash; changes to it are not seen by the "
                "cache key (bump the stage's version when it changes)",
                markup=False,
            )
        reuse[name] = (
            NONE if name in cfg.cache.recompute else ALL if name in cfg.cache.reuse_stages else str(cfg.cache.reuse)
        )
    return {"code": code, "reuse": reuse}


def read_dataset_meta(root: Path) -> dict:
    meta = root / "dataset.json"
    if not meta.is_file():
        raise RunError(f"dataset at {root} is absent or incomplete (no dataset.json)")
    return json.loads(meta.read_text())


PENDING_DATA = "not-generated-yet"
"""The data fingerprint a dry run plans with while the dataset does not exist: no cache entry can match it."""


def planned_scenes(cfg: DictConfig) -> list[str] | None:
    """The scenes the dataset's builder would write (its ``data.planner``: the ``data.*`` keys checked, nothing
    written); None when the dataset has no planner. A bad key is a ``PlanError`` naming it (exit 2)."""
    if not cfg.data.get("planner"):
        return None
    from gdwm.callables import resolve_callable

    try:
        return list(resolve_callable(cfg, "data.planner")(cfg.data))
    except ValueError as e:  # the builders' DataError: the message names data.<key>
        raise PlanError(f"data={cfg.data.name}: {e}") from e


def ensure_data(cfg: DictConfig, dry_run: bool = False) -> dict:
    """The dataset's meta, verified (``gdwm.datasets.check_dataset``); a dataset that needs no source (synthetic) is
    generated first if absent. A dry run generates nothing: it plans with the scenes the builder would write and
    ``PENDING_DATA`` as the fingerprint (so every stage is to run), and says so under ``pending``."""
    from gdwm.callables import check_callables

    root = Path(cfg.data.root)
    check_callables(cfg)  # data.builder, data.planner, data.summarizer: registered ones only, before any runs
    scenes = planned_scenes(cfg)  # checked before anything exists or is generated
    if not (root / "dataset.json").is_file():
        if cfg.source is None and not cfg.data.needs_source:
            if dry_run:
                n = f"{len(scenes)} scenes" if scenes is not None else "its scenes"
                return {"fingerprint": PENDING_DATA, "scenes": scenes or [],
                        "pending": f"would generate {cfg.data.name} ({n}) at {root}"}  # fmt: skip
            from gdwm.datasets import build_dataset
            from gdwm.term import console

            console.print(f"generating {cfg.data.name} at {root} ...")
            build_dataset(cfg, source=None)
        else:
            from gdwm.datasets import build_hint

            raise RunError(f"dataset '{cfg.data.name}' not found at {root}: build it first ({build_hint(cfg.data)})")
    from gdwm.callables import resolve_callable
    from gdwm.datasets import DataMismatch, check_dataset

    checker = resolve_callable(cfg, "data.checker") if cfg.data.get("checker") else None
    try:  # the fingerprint of the files as they are now; params other than requested: exit 2 before anything runs
        return check_dataset(cfg.data, root, read_dataset_meta(root), checker)
    except DataMismatch as e:
        raise PlanError(str(e)) from e


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
        verify=cfg.cache.verify,
        train_settings={"checkpoint_every": cfg.run.checkpoint_every, "max_failures": cfg.run.max_failures},
        tracking_uri=cfg.tracking.uri,
        env_values=env_values(cfg),
    )


def reasons(trials: list[Trial]) -> dict[str, list[str]]:
    """Stage -> the distinct reasons its rows about to run give, in plan order (what ``--dry-run`` prints)."""
    out: dict[str, list[str]] = {}
    for t in trials:
        for r in t.plan:
            if r.status == "to run" and r.why and r.why not in out.setdefault(r.stage, []):
                out[r.stage].append(r.why)
    return {s: w for s, w in out.items() if w}


def print_reasons(trials: list[Trial]) -> None:
    from gdwm.term import console

    why = reasons(trials)
    if why:
        console.print("why stages re-run (compared with their closest cache entry):")
    for stage, lines in why.items():
        for line in lines[:3]:
            console.print(f"  {stage:<14} {line}", markup=False)
        if len(lines) > 3:
            console.print(f"  {stage:<14} (+{len(lines) - 3} more)", markup=False)


class _Entries:
    """Every entry of a stage, read once per plan: what a stage about to run is compared with."""

    def __init__(self, cache: Cache):
        self.cache = cache
        self.by_stage: dict[str, list[Manifest]] = {}

    def of(self, stage: str, scene: str | None) -> list[Manifest]:
        if stage not in self.by_stage:
            self.by_stage[stage] = self.cache.entries(stage)
        return [m for m in self.by_stage[stage] if m.scene == scene]


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict) and d:
        return {k: v for key, val in d.items() for k, v in _flat(val, f"{prefix}{key}.").items()}
    return {prefix.rstrip("."): d}


def _short(v: Any) -> str:
    text = json.dumps(v) if not isinstance(v, str) else v
    return text if len(text) <= 24 else text[:21] + "..."


def why(entries: list[Manifest], sd, sub: dict, upstream: dict[str, str], base: str, env: RunEnv) -> str:
    """What differs between a stage about to run and its closest entry: the newest of the same config (then code,
    libraries, upstream or data changed), else the newest of the stage (then the config says how). "" = no entry."""
    if not entries:
        return ""
    same = [m for m in entries if m.identity == base]
    new = _flat(dict(sub))

    def distance(m: Manifest) -> tuple[int, float]:
        # the entry whose config differs least (a row's other seed, not another row's), then the newest
        old = _flat(m.config)
        return sum(old.get(k, "-") != new.get(k, "-") for k in old.keys() | new.keys()), -m.created_at

    ref = min(same, key=lambda m: -m.created_at) if same else min(entries, key=distance)
    out = [f"version: {ref.version} -> {sd.version}"] if ref.version != sd.version else []
    old = _flat(ref.config)
    out += [f"config: {k} {_short(old.get(k, '-'))} -> {_short(new.get(k, '-'))}"
            for k in sorted(old.keys() | new.keys()) if old.get(k, "-") != new.get(k, "-")]  # fmt: skip
    if ref.data_fingerprint != env.data_fingerprint:
        out.append(f"data: {ref.data_fingerprint[:12]} -> {env.data_fingerprint[:12]}")
    mine = env.code.get(sd.name)
    if ref.code is None:
        out.append("code: unknown (an entry of an older gdwm)")
    elif mine is not None:
        a, b = ref.code.get("files", {}), mine["files"]
        files = [f for f in sorted(a.keys() | b.keys()) if a.get(f) != b.get(f)]
        if files:
            out.append("code: " + ", ".join(files[:3]) + (f" (+{len(files) - 3} more)" if len(files) > 3 else ""))
        la, lb = ref.code.get("libraries", {}), mine["libraries"]
        out += [f"library: {d} {la.get(d, '-')} -> {lb.get(d, '-')}"
                for d in sorted(la.keys() | lb.keys()) if la.get(d) != lb.get(d)]  # fmt: skip
    ups = [u for u in sorted(upstream) if ref.upstream.get(u) != upstream[u]]
    if ups:
        out.append("upstream: " + ", ".join(ups))
    if env.reuse.get(sd.name) == NONE:
        out.insert(0, "recompute")
    return "; ".join(out) or "the entry was removed"


def _plan_result(sd, sub, env: RunEnv, ups: tuple[StageResult, ...], cache: Cache, rows: list[PlanRow],
                 entries: _Entries) -> StageResult:  # fmt: skip
    """Predict one stage's keys and cache status, assuming every upstream scene succeeds."""
    mode = env.reuse.get(sd.name, "same_code")
    scenes = list(env.scenes) if sd.per_scene else [None]
    keys, bases, how = {}, {}, {}
    for s in scenes:
        upk = upstream_keys(ups, s)
        key, bases[s] = stage_key(sd, sub, upk, env, scene=s), stage_base(sd, sub, upstream_bases(ups, s), env, scene=s)
        hit, how[s] = find_entry(cache, sd.name, key, bases[s], mode, verify=False, use=False)
        keys[s] = hit.key if hit is not None else key
        reason = "" if hit is not None else why(entries.of(sd.name, s), sd, sub, upk, bases[s], env)
        rows.append(PlanRow(sd.name, s, keys[s], "cached" if hit else "to run", sd.resources, how[s], reason))
    if sd.per_scene:
        return StageResult(sd.name, aggregate_key(sd, sub, keys, env), False, None,
                           scenes={s: (k, "") for s, k in keys.items()}, base=aggregate_key(sd, sub, bases, env),
                           bases=bases, reused=least_trusted(list(how.values())))  # fmt: skip
    return StageResult(sd.name, keys[None], how[None] != COMPUTED, None, base=bases[None], reused=how[None])


def plan_keys(pipe: Pipeline, order: list[str], cfg: DictConfig, env: RunEnv, entries: _Entries | None = None
              ) -> tuple[list[PlanRow], dict[str, str]]:  # fmt: skip
    """Keys depend on upstream keys, not outputs, so the whole DAG's keys are known before anything runs: the plan's
    rows, and each stage's key as its downstream sees it (per-scene stages: the aggregate key)."""
    cache = Cache(env.cache_uri)
    entries = entries or _Entries(cache)
    rows: list[PlanRow] = []
    predicted: dict[str, StageResult] = {}
    for name in order:
        sd = pipe.stages[name]
        ups = tuple(predicted[u] for u in sd.upstream)
        predicted[name] = _plan_result(sd, stage_config(sd, cfg), env, ups, cache, rows, entries)
    return rows, {name: r.key for name, r in predicted.items()}
